/* confidence.cl - per-pixel confidence of the final cost volume.
 * Driven by mccnn_cl/stages/confidence.py; numpy twin (and the measure's
 * rationale) in mccnn_cl/reference/confidence.py.
 *
 * For pixel (x, y), over its valid levels d = max(0, x - Wr + 1) .. min(D-1, x)
 * (validity by index, see common.h; Wr below), the curve c(d) = C(d, y, x) is
 * read once as runs of equal cost.  A run is a local minimum when the costs on both sides of it
 * are higher (the curve's ends count as higher).  With c1 <= c2 the two
 * lowest local minima (c2 = the curve's largest cost when there is one
 * only) and f the matching cost's lower bound (argument cost_floor):
 *     confidence = (c2 - c1) / ((c1 - f) + (c2 - f)),  clamped to [0, 1]
 * 0 when the denominator is not positive and for pixels the left-right
 * check did not label correct.
 *
 * Padding (the working frame of a range with M < 0, mccnn_cl/disprange.py):
 * Wr is the number of columns of the real right image and lo the first real
 * left column, as the left-right check, interpolation and subpixel kernels
 * take them.  Cells (d, y, x) with x - d >= Wr compare with the right image's
 * padding and are not part of the curve; pixels x < lo are the left image's
 * padding and get 0 (their curves are padding only), as does a pixel with no
 * valid level.  On the real pair Wr = W and lo = 0: nothing changes.
 */
#include "common.h"

#define LABEL_CORRECT 0 /* as disparity.cl */

/* Pushes `run` where `push` (a lane mask) into m1 <= m2, the two lowest
 * local minima of each lane so far. */
#define CONFIDENCE_PUSH(push, run, m1, m2)                                 \
    do {                                                                   \
        const int16 lt1_ = (push) & ((run) < (m1));                        \
        const int16 lt2_ = (push) & ~lt1_ & ((run) < (m2));                \
        (m2) = select(select((m2), (run), lt2_), (m1), lt1_);              \
        (m1) = select((m1), (run), lt1_);                                  \
    } while (0)

/* One work-item per 16 consecutive pixels of a row (as disparity_wta_left:
 * one contiguous line per plane and level), lanes holding their own run
 * state, which each lane starts at its own first valid level; cells outside
 * a lane's levels (d > x: NaN; x - d >= Wr: the padding's costs) may be
 * read with the other lanes' but are masked out, never compared.  Global
 * size (ceil(W / 16), H). */
__kernel void confidence_curve(
    __global const vol_t *cost,  /* C, D x H x W (the volume the WTA used) */
    __global const int *labels,  /* left-right labels, H x W (LABEL_CORRECT = 0) */
    __global float *conf,        /* out: confidence in [0, 1], H x W */
    const int D,                 /* disparity levels */
    const int H,                 /* rows */
    const int W,                 /* columns */
    const float cost_floor,      /* f: lower bound of the matching cost (0; fst: -1) */
    const int Wr,                /* columns of the real right image (<= W) */
    const int lo)                /* first real left column (columns < lo: padding) */
{
    const int x0 = get_global_id(0) * 16;
    const int y = get_global_id(1);
    if (x0 >= W || y >= H)
        return;
    const int n = min(16, W - x0);
    const int16 xs = (int16)(x0) + LANES;
    const int16 dfirst = max((int16)(0), xs - (int16)(Wr - 1)); /* each lane's first level: x - d < Wr */
    const int16 real = xs >= (int16)(lo);                       /* lanes of real left pixels */
    const int16 some = real & (dfirst <= min((int16)(D - 1), xs)); /* ... with a valid level */
    const int dmax = min(D - 1, x0 + n - 1);
    float16 run = (float16)(0.0f);  /* cost of the current run */
    float16 cmax = run;
    float16 m1 = (float16)(INFINITY), m2 = (float16)(INFINITY);
    int16 left_higher = (int16)(-1); /* the run was entered going down (or starts the curve) */
    for (int d = max(0, x0 - Wr + 1); d <= dmax; d++) {
        const float16 c = vol_load16_partial(cost + VIDX(d, y, x0, H, W), 0, n, 0.0f);
        const int16 valid = real & ((int16)(d) <= xs) & ((int16)(d) >= dfirst);
        const int16 first = valid & ((int16)(d) == dfirst); /* the lane's curve starts here */
        const int16 changed = valid & ~first & (c != run);
        const int16 up = changed & (c > run);
        CONFIDENCE_PUSH(up & left_higher, run, m1, m2); /* the run ends going up: a local minimum */
        left_higher = select(select(left_higher, (int16)(0), up), (int16)(-1), (changed & ~up) | first);
        run = select(run, c, changed | first);
        cmax = select(cmax, select(fmax(cmax, c), c, first), valid);
    }
    CONFIDENCE_PUSH(left_higher & some, run, m1, m2); /* the last run, when entered going down */
    const float16 c2 = select(m2, cmax, isinf(m2));
    const float16 den = (m1 - cost_floor) + (c2 - cost_floor);
    float16 out = select((float16)(0.0f), fmin((float16)(1.0f), (c2 - m1) / den), den > 0.0f);
    const size_t p = (size_t)y * W + x0;
    int lab[16];
    for (int i = 0; i < 16; ++i)
        lab[i] = i < n ? labels[p + i] : LABEL_CORRECT;
    out = select((float16)(0.0f), out, some & (vload16(0, lab) == (int16)(LABEL_CORRECT)));
    store16_partial(out, conf + p, n);
}
