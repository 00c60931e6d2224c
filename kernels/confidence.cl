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

/* Keeps m1 <= m2 the two lowest local minima seen so far. */
static inline void confidence_push(const float v, float *m1, float *m2)
{
    if (v < *m1) {
        *m2 = *m1;
        *m1 = v;
    } else if (v < *m2) {
        *m2 = v;
    }
}

/* One work-item per pixel: the curve is read with a stride of H*W cells,
 * neighbouring work-items reading neighbouring cells of one plane.  Global
 * size (W, H). */
__kernel void confidence_curve(
    __global const vol_t *cost,  /* C, D x H x W (the volume the WTA used) */
    __global const int *labels,  /* left-right labels, H x W (LABEL_CORRECT = 0) */
    __global float *conf,        /* out: confidence in [0, 1], H x W */
    const int D,                 /* disparity levels */
    const int H,                 /* rows */
    const int W,                 /* columns */
    const float cost_floor)      /* f: lower bound of the matching cost (0; fst: -1) */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    const size_t p = (size_t)y * W + x;
    if (labels[p] != LABEL_CORRECT) {
        conf[p] = 0.0f;
        return;
    }
    const int dmax = min(D - 1, x);
    float run = VOL_GET(cost, VIDX(0, y, x, H, W)); /* cost of the current run */
    int left_higher = 1;                             /* the run was entered going down */
    float m1 = INFINITY, m2 = INFINITY, cmax = run;
    for (int d = 1; d <= dmax; d++) {
        const float c = VOL_GET(cost, VIDX(d, y, x, H, W));
        cmax = fmax(cmax, c);
        if (c != run) {
            if (c > run) {
                if (left_higher)
                    confidence_push(run, &m1, &m2);
                left_higher = 0;
            } else {
                left_higher = 1;
            }
            run = c;
        }
    }
    if (left_higher)
        confidence_push(run, &m1, &m2);
    const float c2 = isinf(m2) ? cmax : m2;
    const float den = (m1 - cost_floor) + (c2 - cost_floor);
    conf[p] = den > 0.0f ? fmin(1.0f, (c2 - m1) / den) : 0.0f;
}
