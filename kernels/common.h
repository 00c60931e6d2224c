/* common.h - definitions shared by every mccnn_cl kernel.
 *
 * Pulled in with `#include "common.h"` and `-I <kernel dir>` so that
 * pyopencl's binary cache tracks it.  Conventions used by all stages:
 *
 *  - Cost volumes are float32, laid out [d][y][x] (disparity-major), of size
 *    D x H x W where H, W are the *cropped* sizes (the image minus the
 *    network's margin on each side).  Cell (d, y, x) compares left pixel
 *    (x, y) with right pixel (x - d, y).
 *  - A cell with x - d < 0 is INVALID: it holds NaN in every volume, and
 *    every stage decides validity by index (d <= x), never by value, so an
 *    invalid cell never enters a sum, a mean or a minimum.
 *  - Right-reference volumes: C_R(d, y, x) = C_L(d, y, x + d), invalid when
 *    x + d >= W.
 */
#ifndef MCCNN_COMMON_H
#define MCCNN_COMMON_H

#define INVALID_COST NAN

/* Index of cell (d, y, x) in a D x H x W volume. */
#define VIDX(d, y, x, H, W) (((size_t)(d) * (size_t)(H) + (size_t)(y)) * (size_t)(W) + (size_t)(x))

/* Partial 16-wide vector access at the end of a row.  load16_partial gives
 * lanes i = 0..15 = p[first + i]; lanes with i >= n or first + i < 0 are not
 * read and get `fill`.  store16_partial writes lanes 0 .. n-1 (n <= 16). */
static inline float16 load16_partial(__global const float *p, const int first, const int n, const float fill)
{
    if (n == 16 && first >= 0)
        return vload16(0, p + first);
    float t[16];
    for (int i = 0; i < 16; ++i)
        t[i] = (i < n && first + i >= 0) ? p[first + i] : fill;
    return vload16(0, t);
}

static inline void store16_partial(const float16 v, __global float *p, const int n)
{
    if (n == 16) {
        vstore16(v, 0, p);
        return;
    }
    float t[16];
    vstore16(v, 0, t);
    for (int i = 0; i < n; ++i)
        p[i] = t[i];
}

#endif /* MCCNN_COMMON_H */
