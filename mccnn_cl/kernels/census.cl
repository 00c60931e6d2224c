/* census.cl - a classical matching cost (census transform + Hamming
 * distance), so that the stereo method runs without trained weights.
 * Driven by mccnn_cl/stages/census.py; numpy twins:
 * reference.disparity.census_transform / census_cost.
 *
 * The 9 x 9 window matches the network's patch, so the cost lives on the same
 * cropped domain (margin 4: volume pixel (x, y) is image pixel (x+4, y+4))
 * and the two cost volumes are interchangeable.  Each of the 80 neighours q
 * of the centre p (row-major order over dy, dx = -4..4, the centre skipped)
 * sets bit k when I(q) < I(p); bit k lives in word k / 32 at bit k % 32, the
 * three words of a pixel in planes [3][H][W].
 * Cost(d, y, x) = popcount(census_L(x, y) ^ census_R(x - d, y)) / 80 in
 * [0, 1]; NaN for invalid cells (x - d < 0).
 */
#include "common.h"

#define CENSUS_RADIUS 4
#define CENSUS_BITS 80
#define CENSUS_WORDS 3

/* Global size (W, H) of the cropped domain. */
__kernel void census_transform(
    __global const float *img, /* gray image, (H + 8) x (W + 8) */
    __global uint *bits,       /* out: 3 x H x W words */
    const int H,               /* cropped rows */
    const int W)               /* cropped columns */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    const int Wi = W + 2 * CENSUS_RADIUS;
    const float c = img[(size_t)(y + CENSUS_RADIUS) * Wi + x + CENSUS_RADIUS];
    uint words[CENSUS_WORDS] = {0u, 0u, 0u};
    int k = 0;
    for (int dy = -CENSUS_RADIUS; dy <= CENSUS_RADIUS; dy++) {
        const size_t row = (size_t)(y + CENSUS_RADIUS + dy) * Wi;
        for (int dx = -CENSUS_RADIUS; dx <= CENSUS_RADIUS; dx++) {
            if (dx == 0 && dy == 0)
                continue;
            if (img[row + x + CENSUS_RADIUS + dx] < c)
                words[k / 32] |= 1u << (k % 32);
            k++;
        }
    }
    const size_t plane = (size_t)H * W;
    for (int w = 0; w < CENSUS_WORDS; w++)
        bits[w * plane + (size_t)y * W + x] = words[w];
}

/* Global size (W, H, D). */
__kernel void census_cost(
    __global const uint *bits_l, /* census of the left image, 3 x H x W */
    __global const uint *bits_r, /* census of the right image, 3 x H x W */
    __global vol_t *cost,        /* out: D x H x W */
    const int D,                 /* disparity levels */
    const int H,                 /* cropped rows */
    const int W)                 /* cropped columns */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    const int d = get_global_id(2);
    if (x >= W || y >= H || d >= D)
        return;
    float c = INVALID_COST;
    if (x - d >= 0) {
        const size_t plane = (size_t)H * W;
        const size_t pl = (size_t)y * W + x;
        const size_t pr = pl - d;
        uint n = 0u;
        for (int w = 0; w < CENSUS_WORDS; w++)
            n += popcount(bits_l[w * plane + pl] ^ bits_r[w * plane + pr]);
        c = (float)n / (float)CENSUS_BITS;
    }
    VOL_SET(cost, VIDX(d, y, x, H, W), c);
}
