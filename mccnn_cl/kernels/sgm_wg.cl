/* sgm_wg.cl - semi-global matching laid out for GPUs (driven by
 * mccnn_cl/stages/sgm_wg.py): one work-group per path line, one launch per
 * direction, the same recurrence, penalties and output modes as sgm.cl.
 *
 * A work-group walks one line of the path: a row (r = (+-1, 0)) or a column
 * (r = (0, +-1)); group g is row g or column g.  Its work-items share out
 * the disparity levels, work-item l taking d = l, l + L, l + 2L, ... (L the
 * work-group size, any L >= 1, also when D < L or D is not a multiple of L).
 * Per step (pixel p of the line) every work-item reads, for each of its
 * levels, the cost cell (d, y, x), C_r(p - r, d - 1 .. d + 1) from local
 * memory and min_k C_r(p - r, k) (computed by the group at the previous
 * step), and writes C_r(p, d) into the other of two local buffers, so the
 * reads of one step and the writes of the next never need a barrier between
 * them.  The group's minimum min_k C_r(p, k) is then a tree reduction in
 * local memory (one barrier per level of the tree, ceil(log2 L) levels, plus
 * one after the work-items' own minima); the reduction buffers alternate per
 * step too, so a work-item still reading the last step's minimum never sees
 * it overwritten.  Local memory: 2 (D + 2) + 2 P floats, P the power of two
 * >= L; no private arrays.
 *
 * Validity by index, as in sgm.cl: C_r(p - r, .) holds +INFINITY at index 0
 * (level -1) and beyond p - r's valid range, so those terms drop out of
 * every minimum; invalid output cells are NaN (mode 0) or left as they are.
 * Output modes: 0 writes C_r, 1 adds C_r, 2 adds C_r and divides by 4.
 * Volumes are vol_t (float, or half with VOL_HALF=1, see common.h).
 */
#include "common.h"
#include "sgm_recurrence.h"

/* One cell (d, y, x) of a path step, shared by both kernels: C_r(p, d) from
 * the cost cell at idx and, past the path's first pixel, C_r(p - r, .) at
 * levels d - 1, d, d + 1 (prev_d[0], prev_d[stride], prev_d[2 stride]; read
 * only then) and its minimum m, with D2 from the right image at columns xr
 * (of p) and xrp (of p - r) on rows y and py; stored into out by mode when
 * store is set.  Returns C_r(p, d). */
static inline float sgm_wg_cell(__global const vol_t *cost, __global const float *img_r,
                                __global vol_t *out, const size_t idx, const int first,
                                __local const float *prev_d, const int stride, const float m,
                                const int y, const int py, const int xr, const int xrp, const int W,
                                const float p1_a, const float p1_b, const float p2_a, const float p2_b,
                                const float tau_so, const int outside_large, const int mode,
                                const int store)
{
    const float c = VOL_GET(cost, idx);
    float val;
    if (first) {
        val = c; /* first pixel of the path */
    } else {
        int big_r;
        if (xrp < 0 || xrp >= W)
            big_r = outside_large;
        else
            big_r = SGM_LARGE(img_r[y * W + xr] - img_r[py * W + xrp], tau_so);
        val = sgm_step(c, m, prev_d[0], prev_d[stride], prev_d[2 * stride], SGM_BY_D2(p1_a, p1_b, big_r),
                       SGM_BY_D2(p2_a, p2_b, big_r));
    }
    if (store) {
        if (mode == 0) {
            VOL_SET(out, idx, val);
        } else {
            const float old = VOL_GET(out, idx);
            VOL_SET(out, idx, mode == 1 ? old + val : (old + val) * 0.25f);
        }
    }
    return val;
}

__kernel void sgm_wg_path(__global const vol_t *cost,  /* D x H x W cost volume (NaN invalid) */
                          __global const float *img_l, /* H x W left image, gray in [0, 1] */
                          __global const float *img_r, /* H x W right image */
                          __global vol_t *out,         /* D x H x W output (mode) */
                          __local float *path,         /* 2 x (D + 2) floats: C_r of p - r, of p */
                          __local float *red,          /* 2 x pw floats: the reduction buffers */
                          const int pw,                /* power of two >= the work-group size */
                          const int D,
                          const int H,
                          const int W,
                          const int dx,                /* r = (dx, dy), one of them 0 */
                          const int dy,
                          const float p1_small,        /* P1 when 0, 1, 2 gradients are large */
                          const float p1_one,
                          const float p1_both,
                          const float p2_small,        /* P2 likewise */
                          const float p2_one,
                          const float p2_both,
                          const float tau_so,
                          const int outside_large,     /* D2 outside the right image counts as large */
                          const int mode)
{
    const int lid = get_local_id(0);
    const int L = get_local_size(0);
    const int line = get_group_id(0);
    const int horizontal = dx != 0;
    const int nsteps = horizontal ? W : H;
    const size_t plane = (size_t)H * (size_t)W;
    __local float *prev = path, *cur = path + (D + 2);
    __local float *red_cur = red;
    float m = INFINITY; /* min_k C_r(p - r, k) */
    /* level -1 and level D of both buffers: never valid */
    if (lid == 0) {
        path[0] = path[D + 1] = INFINITY;
        path[D + 2] = path[2 * D + 3] = INFINITY;
    }
    for (int i = 0; i < nsteps; ++i) {
        int x, y;
        if (horizontal) {
            y = line;
            x = dx > 0 ? i : W - 1 - i;
        } else {
            x = line;
            y = dy > 0 ? i : H - 1 - i;
        }
        const int px = x - dx, py = y - dy; /* p - r, inside the image when i > 0 */
        const int dmax = min(D - 1, x);
        float d1 = 0.0f;
        if (i > 0)
            d1 = fabs(img_l[y * W + x] - img_l[py * W + px]);
        const int big_l = SGM_LARGE(d1, tau_so);
        float p1_a, p1_b, p2_a, p2_b;
        SGM_BY_D1(p1_small, p1_one, p1_both, big_l, p1_a, p1_b);
        SGM_BY_D1(p2_small, p2_one, p2_both, big_l, p2_a, p2_b);
        float own_min = INFINITY;
        for (int d = lid; d < D; d += L) {
            const size_t idx = VIDX(d, y, x, H, W);
            float val = INFINITY;
            if (d <= dmax) {
                /* pd and pd - r in the right image: x - d, px - d; prev[d + 1] is C_r(p - r, d) */
                val = sgm_wg_cell(cost, img_r, out, idx, i == 0, prev + d, 1, m, y, py, x - d, px - d, W,
                                  p1_a, p1_b, p2_a, p2_b, tau_so, outside_large, mode, 1);
                own_min = fmin(own_min, val);
            } else if (mode == 0) {
                VOL_SET(out, idx, INVALID_COST);
            }
            cur[d + 1] = val;
        }
        red_cur[lid] = own_min;
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int s = pw >> 1; s > 0; s >>= 1) {
            if (lid < s && lid + s < L)
                red_cur[lid] = fmin(red_cur[lid], red_cur[lid + s]);
            barrier(CLK_LOCAL_MEM_FENCE);
        }
        m = red_cur[0];
        /* swap the path buffers and the reduction buffers */
        __local float *t = prev;
        prev = cur;
        cur = t;
        red_cur = red_cur == red ? red + pw : red;
    }
}

/* The vertical paths (r = (0, +-1)) with SGM_WG_CW adjacent columns per
 * work-group (sgm_wg_cols): a work-group of (SGM_WG_CW, K) work-items walks
 * the columns x0 .. x0 + SGM_WG_CW - 1 together, work-item (c, k) taking
 * column x0 + c and the levels d = k, k + K, k + 2K, ...  In sgm_wg_path a
 * step reads one cell per level, a plane (H x W floats) apart: one memory
 * transaction per 4 bytes.  Here the work-items of one level read adjacent
 * columns, so a step's reads and writes come in runs of SGM_WG_CW floats.
 * The path state is [D + 2][SGM_WG_CW] in local memory (two buffers, as in
 * sgm_wg_path); min_k C_r(p, k) per column: each work-item writes its
 * levels' minimum, then after one barrier reads the column's K minima (the
 * reduction buffers alternate per step, so one barrier per step suffices).
 * Work-items beyond the image walk its last column and write nothing.  The
 * same recurrence, one cell by the same helper (sgm_wg_cell) as sgm_wg_path
 * (a minimum does not depend on the order of its terms), so the same bits.
 * Local memory: 2 (D + 2) SGM_WG_CW + 2 K SGM_WG_CW floats. */
#ifndef SGM_WG_CW
#define SGM_WG_CW 8
#endif
__kernel void sgm_wg_cols(__global const vol_t *cost,  /* D x H x W cost volume (NaN invalid) */
                          __global const float *img_l, /* H x W left image, gray in [0, 1] */
                          __global const float *img_r, /* H x W right image */
                          __global vol_t *out,         /* D x H x W output (mode) */
                          __local float *path,         /* 2 x (D + 2) x SGM_WG_CW: C_r of p - r, of p */
                          __local float *red,          /* 2 x K x SGM_WG_CW: the levels' minima */
                          const int D,
                          const int H,
                          const int W,
                          const int dy,                /* r = (0, dy) */
                          const float p1_small,        /* P1 when 0, 1, 2 gradients are large */
                          const float p1_one,
                          const float p1_both,
                          const float p2_small,        /* P2 likewise */
                          const float p2_one,
                          const float p2_both,
                          const float tau_so,
                          const int outside_large,     /* D2 outside the right image counts as large */
                          const int mode)
{
    const int CW = SGM_WG_CW;
    const int c = get_local_id(0);
    const int k = get_local_id(1);
    const int K = get_local_size(1);
    const int x_own = get_group_id(0) * CW + c;
    const int inside = x_own < W;
    const int x = inside ? x_own : W - 1;
    __local float *prev = path, *cur = path + (D + 2) * CW;
    __local float *red_cur = red;
    float m = INFINITY; /* min_k C_r(p - r, k) of this column */
    /* level -1 and level D of both buffers: never valid */
    if (k == 0) {
        prev[c] = prev[(D + 1) * CW + c] = INFINITY;
        cur[c] = cur[(D + 1) * CW + c] = INFINITY;
    }
    const int dmax = min(D - 1, x);
    for (int i = 0; i < H; ++i) {
        const int y = dy > 0 ? i : H - 1 - i;
        const int py = y - dy; /* p - r, inside the image when i > 0 */
        float d1 = 0.0f;
        if (i > 0)
            d1 = fabs(img_l[y * W + x] - img_l[py * W + x]);
        const int big_l = SGM_LARGE(d1, tau_so);
        float p1_a, p1_b, p2_a, p2_b;
        SGM_BY_D1(p1_small, p1_one, p1_both, big_l, p1_a, p1_b);
        SGM_BY_D1(p2_small, p2_one, p2_both, big_l, p2_a, p2_b);
        float own_min = INFINITY;
        for (int d = k; d < D; d += K) {
            const size_t idx = VIDX(d, y, x, H, W);
            float val = INFINITY;
            if (d <= dmax) {
                /* pd and pd - r in the right image: the same column x - d; prev[(d + 1) CW + c] is
                 * C_r(p - r, d) */
                val = sgm_wg_cell(cost, img_r, out, idx, i == 0, prev + d * CW + c, CW, m, y, py, x - d, x - d,
                                  W, p1_a, p1_b, p2_a, p2_b, tau_so, outside_large, mode, inside);
                own_min = fmin(own_min, val);
            } else if (mode == 0 && inside) {
                VOL_SET(out, idx, INVALID_COST);
            }
            cur[(d + 1) * CW + c] = val;
        }
        red_cur[k * CW + c] = own_min;
        barrier(CLK_LOCAL_MEM_FENCE);
        float mm = INFINITY;
        for (int j = 0; j < K; ++j)
            mm = fmin(mm, red_cur[j * CW + c]);
        m = mm;
        /* swap the path buffers and the reduction buffers */
        __local float *t = prev;
        prev = cur;
        cur = t;
        red_cur = red_cur == red ? red + K * CW : red;
    }
}
