/* subpixel.cl - subpixel enhancement (paper, "Subpixel enhancement").
 * Driven by mccnn_cl/stages/disparity.py (class Subpixel); numpy twin:
 * reference.disparity.subpixel.
 *
 *   D_SE(p) = d - (C+ - C-) / (2 (C+ - 2 C + C-)),  d = D_INT(p),
 *   C- = C(p, d-1), C = C(p, d), C+ = C(p, d+1)
 * on the final cost volume (the one the WTA used).  D_SE(p) = d unchanged when
 *   - d - 1 < 0 or d + 1 > D - 1 (range ends),
 *   - d + 1 > x (a neighbour, or d itself, is an invalid cell: x - d' < 0;
 *     D_INT may hold a disparity interpolated from another pixel),
 *   - x - (d - 1) >= Wr (a neighbour, or d itself, compares with a right
 *     pixel past the real right image: Wr = W on the real pair, where this
 *     never holds; the real cropped width in the working frame of a range
 *     with M < 0, whose padding cells hold a made-up cost, mccnn_cl/disprange.py),
 *   - the denominator C+ - 2C + C- is not > min_denom (zero or negative:
 *     no minimum to fit; the paper's case is min_denom = 0, the released
 *     code uses 1e-5).
 * With clamp_step != 0 the correction is clamped to [-1, 1] (released code).
 */
#include "common.h"

/* No fused multiply-add: the numpy twin evaluates the same float32
 * expression operation by operation, so the results match bit for bit. */
#pragma OPENCL FP_CONTRACT OFF

/* Global size (W, H). */
__kernel void subpixel_refine(
    __global const vol_t *cost, /* final cost volume, D x H x W */
    __global const int *disp,   /* D_INT, H x W */
    __global float *out,        /* out: D_SE, H x W */
    const int D,                /* disparity levels */
    const int H,                /* rows */
    const int W,                /* columns */
    const float min_denom,      /* fit only when C+ - 2C + C- > min_denom */
    const int clamp_step,       /* nonzero: clamp the correction to [-1, 1] */
    const int Wr)               /* columns of the real right image (<= W) */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    const int d = disp[(size_t)y * W + x];
    float result = (float)d;
    if (d >= 1 && d + 1 <= D - 1 && d + 1 <= x && x - d + 1 < Wr) {
        const float cm = VOL_GET(cost, VIDX(d - 1, y, x, H, W));
        const float c0 = VOL_GET(cost, VIDX(d, y, x, H, W));
        const float cp = VOL_GET(cost, VIDX(d + 1, y, x, H, W));
        const float denom = cp - 2.0f * c0 + cm;
        if (denom > min_denom) {
            float step = (cp - cm) / (2.0f * denom);
            if (clamp_step)
                step = clamp(step, -1.0f, 1.0f);
            result = (float)d - step;
        }
    }
    out[(size_t)y * W + x] = result;
}
