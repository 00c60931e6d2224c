/* cross.cl - cross arms for cross-based cost aggregation (paper, "Cross-based
 * cost aggregation").  Driven by mccnn_cl/stages/cross.py.
 *
 * For each pixel p the four arm lengths are stored as bytes in four planes,
 * [4][H][W]: plane 0 = left, 1 = right, 2 = up, 3 = down ("up" is towards
 * smaller y); planar so that the aggregation kernels load 16 arms of one
 * kind with one vector load.  The arm towards p + k*step extends for
 * k = 1, 2, ... while |I(p) - I(p + k*step)| < tau, k < eta and the pixel is
 * inside the image, and stops at the first k that fails.  With
 * include_neighbor != 0 (released code) k = 1 is accepted whenever the
 * neighbour is inside the image.  Lengths are capped at 255 (the host limits
 * eta to <= 256, so the cap never binds).
 */
#include "common.h"

/* Length of one arm of pixel (x, y) in direction (dx, dy). */
static int cross_arm_length(__global const float *img, const int H, const int W,
                            const int x, const int y, const int dx, const int dy,
                            const float tau, const int eta, const int include_neighbor)
{
    const float centre = img[y * W + x];
    int k = 0;
    while (k < 255) {
        const int n = k + 1;
        const int xx = x + n * dx;
        const int yy = y + n * dy;
        if (xx < 0 || xx >= W || yy < 0 || yy >= H)
            break;
        if (!(include_neighbor && n == 1)) {
            if (n >= eta)
                break;
            if (!(fabs(centre - img[yy * W + xx]) < tau)) /* a NaN pixel stops the arm too */
                break;
        }
        k = n;
    }
    return k;
}

__kernel void cross_build(__global const float *img,  /* H x W gray image in [0, 1] */
                          __global uchar *arms,        /* out: 4 x H x W planes left, right, up, down */
                          const int H,                 /* image height */
                          const int W,                 /* image width */
                          const float tau,             /* intensity threshold (paper 0.0442) */
                          const int eta,               /* exclusive length limit (paper 4) */
                          const int include_neighbor)  /* 1: +-1 neighbour always in the arm */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    const size_t plane = (size_t)H * (size_t)W;
    const size_t i = (size_t)y * W + x;
    arms[i] = (uchar)cross_arm_length(img, H, W, x, y, -1, 0, tau, eta, include_neighbor);
    arms[plane + i] = (uchar)cross_arm_length(img, H, W, x, y, 1, 0, tau, eta, include_neighbor);
    arms[2 * plane + i] = (uchar)cross_arm_length(img, H, W, x, y, 0, -1, tau, eta, include_neighbor);
    arms[3 * plane + i] = (uchar)cross_arm_length(img, H, W, x, y, 0, 1, tau, eta, include_neighbor);
}
