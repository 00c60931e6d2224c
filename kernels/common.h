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

#endif /* MCCNN_COMMON_H */
