/* range.cl - the border of a disparity range that does not start at 0.
 * Driven by mccnn_cl/disprange.py (numpy twin: disprange.mask_reference).
 *
 * With a minimum disparity M < 0 the stereo method runs in a working frame
 * (docs/method.md, "Disparity ranges"): the left image padded by p = -M
 * columns on the left, the right one by p on the right, disparity levels
 * d' = d - M >= 0.  Cells with x - d' < 0 are invalid as everywhere (NaN,
 * common.h, never touched here); of the others, a cell whose left pixel is
 * padding (x < lo) or whose right pixel is padding (x - d' >= hi) gets the
 * cost `ceiling` (no real match is there: the worst cost of every matching
 * cost).  Global size (W, H, D).
 */
#include "common.h"

__kernel void range_mask(
    __global vol_t *cost, /* cost volume, [D][H][W] */
    const int D,
    const int H,
    const int W,
    const int lo,         /* first real left column (p) */
    const int hi,         /* first padded right column (the real width) */
    const float ceiling)
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    const int d = get_global_id(2);
    if (x >= W || y >= H || d >= D || x - d < 0)
        return;
    if (x < lo || x - d >= hi)
        VOL_SET(cost, VIDX(d, y, x, H, W), ceiling);
}
