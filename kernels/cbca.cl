/* cbca.cl - cross-based cost aggregation (paper, "Cross-based cost
 * aggregation"), one iteration = cbca_rows then cbca_columns.
 * Driven by mccnn_cl/stages/cbca.py (the derivation of the two passes from
 * the set U_d(p) is in that module's docstring).
 *
 * Required define: MAX_ARM, an upper bound of every arm length; it sizes the
 * private ring buffers (RING = 2 * MAX_ARM + 2 entries).  Arms longer than
 * MAX_ARM are truncated to MAX_ARM.
 *
 * Both passes walk a line (a row of one disparity plane, or a column) with a
 * running prefix sum P and a look-ahead of MAX_ARM cells: at step t cell t is
 * added to P and the output of cell t - MAX_ARM, whose window [a, b] lies in
 * [t - 2 MAX_ARM, t], is P(b) - P(a - 1) read from the ring.  The output of a
 * cell is written only after the cell itself was read, so both passes may
 * work in place.  The prefix is a compensated (TwoSum) pair (s, e) with
 * P = s + e: window sums carry an error of a few ulp of the window's own
 * magnitude instead of growing with the line length.
 */
#include "common.h"

#ifndef MAX_ARM
#error "cbca.cl needs -D MAX_ARM=<largest arm length>"
#endif
#define RING (2 * MAX_ARM + 2)

/* Add v to the compensated prefix (s, e) (Knuth's TwoSum: the rounding error
 * of s + v is exact and goes to e). */
#define PREFIX_ADD(s, e, v)                          \
    do {                                             \
        const float ns_ = (s) + (v);                 \
        const float bv_ = ns_ - (s);                 \
        (e) += ((s) - (ns_ - bv_)) + ((v) - bv_);    \
        (s) = ns_;                                   \
    } while (0)

/* Ring slot of line position q when position t sits in slot head (q <= t, t - q < RING). */
static inline int ring_slot(const int head, const int t, const int q)
{
    int i = head - (t - q);
    return i < 0 ? i + RING : i;
}

/* Horizontal extent [lo, hi] of row y of U_d(p) for column x: intersection of
 * the left image's arm at (x, y) and the right image's arm at (x - d, y)
 * shifted by +d, clamped to the valid cells [d, W - 1]. */
static inline int2 row_extent(__global const uchar4 *arms_l, __global const uchar4 *arms_r,
                              const int d, const int y, const int x, const int W)
{
    const uchar4 al = arms_l[y * W + x];
    const uchar4 ar = arms_r[y * W + x - d];
    const int l = min(min((int)al.x, (int)ar.x), MAX_ARM);
    const int r = min(min((int)al.y, (int)ar.y), MAX_ARM);
    return (int2)(max(x - l, d), min(x + r, W - 1));
}

/* Pass 1: row sums.  dst(d, y, x) = sum of src(d, y, x') over the row extent
 * of x (not yet divided), NaN for invalid cells (x < d).  dst may be src. */
__kernel void cbca_rows(__global const float *src,     /* D x H x W cost C^{i-1} */
                        __global float *dst,           /* out: D x H x W row sums (may alias src) */
                        __global const uchar4 *arms_l, /* H x W arms of the left image */
                        __global const uchar4 *arms_r, /* H x W arms of the right image */
                        const int D,                   /* disparity levels */
                        const int H,                   /* height */
                        const int W)                   /* width */
{
    const int y = get_global_id(0);
    const int d = get_global_id(1);
    if (y >= H || d >= D)
        return;
    const size_t row = VIDX(d, y, 0, H, W);
    const int x0 = min(d, W); /* first valid x */
    for (int x = 0; x < x0; ++x)
        dst[row + x] = INVALID_COST;
    const int n = W - x0; /* valid cells x0 .. W-1, position i = x - x0 */
    float rs[RING], re[RING];
    float s = 0.0f, e = 0.0f;
    int head = RING - 1;
    for (int t = 0; t < n + MAX_ARM; ++t) {
        head = head + 1 == RING ? 0 : head + 1;
        if (t < n) {
            const float v = src[row + x0 + t];
            PREFIX_ADD(s, e, v);
        }
        rs[head] = s; /* past the end: P stays constant, never read beyond n - 1 */
        re[head] = e;
        const int i = t - MAX_ARM;
        if (i >= 0) {
            const int x = x0 + i;
            const int2 ext = row_extent(arms_l, arms_r, d, y, x, W);
            const int b = ring_slot(head, t, ext.y - x0);
            float sum = rs[b] + re[b];
            if (ext.x > x0) {
                const int a = ring_slot(head, t, ext.x - x0 - 1);
                sum = (rs[b] - rs[a]) + (re[b] - re[a]);
            }
            dst[row + x] = sum;
        }
    }
}

/* Pass 2: column sums, in place.  buf holds the row sums of pass 1; for each
 * valid cell (x >= d) it becomes the sum of the row sums over the rows of
 * U_d(p) divided by the number of cells |U_d(p)|.  Invalid cells (already
 * NaN from pass 1) are not touched. */
__kernel void cbca_columns(__global float *buf,           /* D x H x W row sums in, C^i out */
                           __global const uchar4 *arms_l, /* H x W arms of the left image */
                           __global const uchar4 *arms_r, /* H x W arms of the right image */
                           const int D,                   /* disparity levels */
                           const int H,                   /* height */
                           const int W)                   /* width */
{
    const int x = get_global_id(0);
    const int d = get_global_id(1);
    if (x >= W || d >= D || x < d)
        return;
    float rs[RING], re[RING];
    int rn[RING];
    float s = 0.0f, e = 0.0f;
    int cnt = 0;
    int head = RING - 1;
    for (int t = 0; t < H + MAX_ARM; ++t) {
        head = head + 1 == RING ? 0 : head + 1;
        if (t < H) {
            const float v = buf[VIDX(d, t, x, H, W)];
            PREFIX_ADD(s, e, v);
            const int2 ext = row_extent(arms_l, arms_r, d, t, x, W);
            cnt += ext.y - ext.x + 1;
        }
        rs[head] = s;
        re[head] = e;
        rn[head] = cnt;
        const int y = t - MAX_ARM;
        if (y >= 0) {
            const uchar4 al = arms_l[y * W + x];
            const uchar4 ar = arms_r[y * W + x - d];
            const int lo = max(y - min(min((int)al.z, (int)ar.z), MAX_ARM), 0);
            const int hi = min(y + min(min((int)al.w, (int)ar.w), MAX_ARM), H - 1);
            const int b = ring_slot(head, t, hi);
            float sum = rs[b] + re[b];
            int num = rn[b];
            if (lo > 0) {
                const int a = ring_slot(head, t, lo - 1);
                sum = (rs[b] - rs[a]) + (re[b] - re[a]);
                num -= rn[a];
            }
            buf[VIDX(d, y, x, H, W)] = sum / (float)num;
        }
    }
}
