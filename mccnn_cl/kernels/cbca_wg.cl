/* cbca_wg.cl - cross-based cost aggregation laid out for GPUs: the two
 * passes of the short-arm path of cbca.cl (cbca_rows_short, then
 * cbca_columns_short), with the same float operations per cell in the same
 * order, spread over pixels and disparities instead of one work-item per
 * line.  Driven by mccnn_cl/stages/cbca.py (path "workgroup"; the derivation
 * of the passes from the set U_d(p) is in that module's docstring).
 *
 *   cbca_rows_wg     one work-group per (row y, disparity d); its L
 *                    work-items take L consecutive columns at a time
 *   cbca_columns_wg  one work-group per (tile of TX columns, d); its
 *                    TX x TY work-items take TY consecutive rows at a time
 *
 * Each work-group owns its whole line (a row of a plane, or a tile of
 * columns of a plane over all rows), so both passes work in place: the
 * original values a cell's window needs are held in a ring in local memory
 * (the cells of the current chunk plus MAX_ARM on each side: L + 2 MAX_ARM
 * floats, or (TY + 2 MAX_ARM) x TX row sums and row counts) until the whole
 * group has summed them; a cell of the line is written only after its value
 * went into the ring, and the global cells loaded later lie beyond every
 * cell written so far.  Two barriers per chunk: after the ring is filled
 * (also a global fence: the group's loads of a cell from the volume come
 * before another work-item of the group writes it, as Oclgrind checks), and
 * after every work-item has read the ring (before the next chunk overwrites
 * the slots no longer needed).  Any L, TX, TY >= 1 and any W, H,
 * D: work-items beyond the line take part in the barriers and write nothing.
 *
 * Bit-identity with the two short passes: cbca_rows_short forms
 * s = +0, s += select(0, v(x + k), take) for k = -MAX_ARM .. MAX_ARM; here
 * s += v(x + k) where taken.  Adding +0 leaves s unchanged because s starts
 * at +0 and a round-to-nearest sum is -0 only when both terms are, so s is
 * never -0.  The same holds for the column sums, the counts are the same
 * integers (l + r + 1 per row, capped at the borders) and the division is
 * the same s / (float)count.  In half storage the row sums are stored in
 * the volume (rounded to half) between the passes, as in the short passes.
 *
 * Defines: MAX_ARM (required, <= CBCA_WG_MAX), VOL_HALF [0] (common.h).
 * Arms: bytes in four planes [4][H][W] (left, right, up, down), cross.cl.
 */
#include "common.h"

#ifndef MAX_ARM
#error "cbca_wg.cl needs -D MAX_ARM=<largest arm length>"
#endif
#define CBCA_WG_MAX 8
#if MAX_ARM > CBCA_WG_MAX
#error "cbca_wg.cl serves MAX_ARM <= 8 (longer arms: the running-sum kernels of cbca.cl)"
#endif
#define ARM_LEFT 0
#define ARM_RIGHT 1
#define ARM_UP 2
#define ARM_DOWN 3
#define ARM(a, k, i) ((int)(a)[(size_t)(k) * (size_t)H * (size_t)W + (size_t)(i)])
/* Combined arm k at pixel (x, y) for disparity d: the shorter of the left
 * image's arm at (x, y) and the right image's at (x - d, y), capped. */
#define COMBINED(k, y, x, cap) min(min(ARM(arms_l, (k), (y) * W + (x)), ARM(arms_r, (k), (y) * W + (x) - d)), (cap))

/* Pass 1: dst(d, y, x) = sum of src(d, y, x') over the row extent of x
 * (NaN where x < d).  Global (L, H, D), local (L, 1, 1); ring: L + 2 MAX_ARM
 * floats of local memory.  dst may be src. */
__kernel void cbca_rows_wg(__global const vol_t *src,     /* D x H x W cost C^{i-1} */
                           __global vol_t *dst,           /* out: row sums (may alias src) */
                           __global const uchar *arms_l,  /* 4 x H x W arms of the left image */
                           __global const uchar *arms_r,  /* 4 x H x W arms of the right image */
                           __local float *ring,           /* L + 2 MAX_ARM floats */
                           const int D,                   /* disparity levels */
                           const int H,                   /* height */
                           const int W)                   /* width */
{
    const int L = (int)get_local_size(0);
    const int i = (int)get_local_id(0);
    const int y = (int)get_group_id(1);
    const int d = (int)get_group_id(2);
    if (y >= H || d >= D) /* whole groups only: the global size is (L, H, D) */
        return;
    const int R = L + 2 * MAX_ARM;
    const size_t row = VIDX(d, y, 0, H, W);
    /* cell x lives in slot (x + MAX_ARM) % R; the ring starts with cells
     * -MAX_ARM .. L + MAX_ARM - 1 (outside the row or invalid: 0, never taken) */
    for (int j = i; j < R; j += L) {
        const int x = j - MAX_ARM;
        ring[j] = (x >= d && x < W) ? VOL_GET(src, row + x) : 0.0f;
    }
    for (int x0 = 0; x0 < W; x0 += L) {
        /* the ring holds cells x0 - MAX_ARM .. x0 + L + MAX_ARM - 1; the global
         * fence orders every load of a cell before the chunk that writes it */
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        const int x = x0 + i;
        const int valid = x < W && x >= d;
        float s = 0.0f;
        if (valid) {
            const int l = COMBINED(ARM_LEFT, y, x, min(MAX_ARM, x - d));
            const int r = COMBINED(ARM_RIGHT, y, x, min(MAX_ARM, W - 1 - x));
            const int j0 = x % R; /* slot of cell x - MAX_ARM */
#pragma unroll
            for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {
                if (k >= -l && k <= r) {
                    int j = j0 + k + MAX_ARM;
                    j = j >= R ? j - R : j;
                    s += ring[j];
                }
            }
        }
        barrier(CLK_LOCAL_MEM_FENCE); /* every work-item has read the ring */
        /* the next chunk's new cell into the slot of cell xn - R, no longer needed */
        const int xn = x + L + MAX_ARM;
        if (x0 + L < W)
            ring[(xn + MAX_ARM) % R] = (xn >= d && xn < W) ? VOL_GET(src, row + xn) : 0.0f;
        if (x < W)
            VOL_SET(dst, row + x, valid ? s : INVALID_COST);
    }
}

/* Pass 2, in place: buf(d, y, x) = (sum of the row sums over the rows of
 * U_d(p)) / |U_d(p)| for valid cells (x >= d; the others stay NaN from
 * pass 1).  Global (TX ceil(W / TX), TY, D), local (TX, TY, 1); rings:
 * (TY + 2 MAX_ARM) x TX row sums (float) and row counts (uchar, <= 17) in
 * local memory. */
__kernel void cbca_columns_wg(__global vol_t *buf,           /* row sums in, C^i out */
                              __global const uchar *arms_l,  /* 4 x H x W arms of the left image */
                              __global const uchar *arms_r,  /* 4 x H x W arms of the right image */
                              __local float *rsum,           /* (TY + 2 MAX_ARM) x TX floats */
                              __local uchar *rcnt,           /* (TY + 2 MAX_ARM) x TX bytes */
                              const int D,                   /* disparity levels */
                              const int H,                   /* height */
                              const int W)                   /* width */
{
    const int TX = (int)get_local_size(0);
    const int TY = (int)get_local_size(1);
    const int tx = (int)get_local_id(0);
    const int ty = (int)get_local_id(1);
    const int xt = (int)get_group_id(0) * TX;
    const int d = (int)get_group_id(2);
    if (d >= D || min(xt + TX, W) - 1 < d)
        return; /* the whole tile is invalid (NaN from pass 1): uniform in the group */
    const int x = xt + tx;
    const int valid = x < W && x >= d;
    const int R = TY + 2 * MAX_ARM;
    const int capl = valid ? min(MAX_ARM, x - d) : 0;
    const int capr = valid ? min(MAX_ARM, W - 1 - x) : 0;
    /* row y lives in slot (y + MAX_ARM) % R; the ring starts with rows
     * -MAX_ARM .. TY + MAX_ARM - 1 (outside the image or invalid: 0, never taken) */
    for (int j = ty; j < R; j += TY) {
        const int yy = j - MAX_ARM;
        const int in = valid && yy >= 0 && yy < H;
        rsum[j * TX + tx] = in ? VOL_GET(buf, VIDX(d, yy, x, H, W)) : 0.0f;
        rcnt[j * TX + tx] = in ? (uchar)(COMBINED(ARM_LEFT, yy, x, capl) + COMBINED(ARM_RIGHT, yy, x, capr) + 1)
                               : (uchar)0;
    }
    for (int y0 = 0; y0 < H; y0 += TY) {
        /* the ring holds rows y0 - MAX_ARM .. y0 + TY + MAX_ARM - 1; the global
         * fence orders every load of a row before the chunk that writes it */
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        const int y = y0 + ty;
        const int out = valid && y < H;
        float res = 0.0f;
        if (out) {
            const int u = COMBINED(ARM_UP, y, x, min(MAX_ARM, y));
            const int w = COMBINED(ARM_DOWN, y, x, min(MAX_ARM, H - 1 - y));
            const int j0 = y % R; /* slot of row y - MAX_ARM */
            float s = 0.0f;
            int cnt = 0;
#pragma unroll
            for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {
                if (k >= -u && k <= w) {
                    int j = j0 + k + MAX_ARM;
                    j = j >= R ? j - R : j;
                    s += rsum[j * TX + tx];
                    cnt += (int)rcnt[j * TX + tx];
                }
            }
            res = s / (float)max(cnt, 1);
        }
        barrier(CLK_LOCAL_MEM_FENCE); /* every work-item has read the ring */
        /* the next chunk's new row into the slot of row yn - R, no longer needed */
        const int yn = y + TY + MAX_ARM;
        if (y0 + TY < H) {
            const int in = valid && yn < H;
            const int j = ((yn + MAX_ARM) % R) * TX + tx;
            rsum[j] = in ? VOL_GET(buf, VIDX(d, yn, x, H, W)) : 0.0f;
            rcnt[j] = in ? (uchar)(COMBINED(ARM_LEFT, yn, x, capl) + COMBINED(ARM_RIGHT, yn, x, capr) + 1) : (uchar)0;
        }
        if (out)
            VOL_SET(buf, VIDX(d, y, x, H, W), res);
    }
}
