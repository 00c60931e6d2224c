/* confidence.cl - per-pixel confidence of the final cost volume.
 * Driven by mccnn_cl/stages/confidence.py; numpy twin (and the measure's
 * rationale) in mccnn_cl/reference/confidence.py.
 *
 * For pixel (x, y), over its valid levels d = 0 .. min(D-1, x) (validity by
 * index, see common.h), the curve c(d) = C(d, y, x) is read once as runs of
 * equal cost.  A run is a local minimum when the costs on both sides of it
 * are higher (the curve's ends count as higher).  With c1 <= c2 the two
 * lowest local minima (c2 = the curve's largest cost when there is one
 * only) and f the matching cost's lower bound (argument cost_floor):
 *     confidence = (c2 - c1) / ((c1 - f) + (c2 - f)),  clamped to [0, 1]
 * 0 when the denominator is not positive and for pixels the left-right
 * check did not label correct.
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
 * state; cells with d > x are read (NaN, never uninitialised) but masked
 * out.  Global size (ceil(W / 16), H). */
__kernel void confidence_curve(
    __global const vol_t *cost,  /* C, D x H x W (the volume the WTA used) */
    __global const int *labels,  /* left-right labels, H x W (LABEL_CORRECT = 0) */
    __global float *conf,        /* out: confidence in [0, 1], H x W */
    const int D,                 /* disparity levels */
    const int H,                 /* rows */
    const int W,                 /* columns */
    const float cost_floor)      /* f: lower bound of the matching cost (0; fst: -1) */
{
    const int x0 = get_global_id(0) * 16;
    const int y = get_global_id(1);
    if (x0 >= W || y >= H)
        return;
    const int n = min(16, W - x0);
    const int16 xs = (int16)(x0) + LANES;
    const int dmax = min(D - 1, x0 + n - 1);
    float16 run = vol_load16_partial(cost + VIDX(0, y, x0, H, W), 0, n, 0.0f); /* cost of the current run */
    float16 cmax = run;
    float16 m1 = (float16)(INFINITY), m2 = (float16)(INFINITY);
    int16 left_higher = (int16)(-1); /* the run was entered going down (or starts the curve) */
    for (int d = 1; d <= dmax; d++) {
        const float16 c = vol_load16_partial(cost + VIDX(d, y, x0, H, W), 0, n, 0.0f);
        const int16 valid = (int16)(d) <= xs;
        const int16 changed = valid & (c != run);
        const int16 up = changed & (c > run);
        CONFIDENCE_PUSH(up & left_higher, run, m1, m2); /* the run ends going up: a local minimum */
        left_higher = select(select(left_higher, (int16)(0), up), (int16)(-1), changed & ~up);
        run = select(run, c, changed);
        cmax = select(cmax, fmax(cmax, c), valid);
    }
    CONFIDENCE_PUSH(left_higher, run, m1, m2); /* the last run, when entered going down */
    const float16 c2 = select(m2, cmax, isinf(m2));
    const float16 den = (m1 - cost_floor) + (c2 - cost_floor);
    float16 out = select((float16)(0.0f), fmin((float16)(1.0f), (c2 - m1) / den), den > 0.0f);
    const size_t p = (size_t)y * W + x0;
    int lab[16];
    for (int i = 0; i < 16; ++i)
        lab[i] = i < n ? labels[p + i] : LABEL_CORRECT;
    out = select((float16)(0.0f), out, vload16(0, lab) == (int16)(LABEL_CORRECT));
    store16_partial(out, conf + p, n);
}
