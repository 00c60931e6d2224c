/* cbca.cl - cross-based cost aggregation (paper, "Cross-based cost
 * aggregation"); one iteration = a rows pass (row sums over each cell's row
 * extent) then a columns pass (sums of row sums over the rows of U_d(p),
 * divided by the cell count).  Driven by mccnn_cl/stages/cbca.py (the
 * derivation of the two passes from the set U_d(p) is in that module's
 * docstring).  Four kernel paths: cbca_rows / cbca_columns (running sums,
 * any MAX_ARM, described here), cbca_rows_short / cbca_columns_short
 * (float16 direct sums, MAX_ARM <= CBCA_SHORT_MAX, further down), the short
 * passes fused into one launch per iteration (cbca_fused_short) and into one
 * launch per up to CBCA_K iterations (cbca_fused_multi_short, at the end).
 * Defines: MAX_ARM (required, below), VOL_HALF [0] (common.h), CBCA_GROUPS [8]
 * (16-column groups per work-item of the short column pass), CBCA_K
 * [4] (iterations per launch of the multi kernel), CBCA_PART [0] (which
 * kernels the program holds: 0 all, 1 all but the multi kernel, 2 the multi
 * kernel only; a program binary holds compiled code for each of its kernels,
 * so the host builds the multi path with 2 and the other paths with 1).
 *
 * Arms: bytes in four planes [4][H][W] (left, right, up, down), as written
 * by cross.cl; ARM(a, k, i) is arm k of pixel index i = y * W + x.
 *
 * Required define: MAX_ARM, an upper bound of every arm length; it sizes the
 * private ring buffers (RING = 2 * MAX_ARM + 2 entries).  Arms longer than
 * MAX_ARM are truncated to MAX_ARM.
 *
 * Running sums: both passes walk a line (a row of one disparity plane, or a column) with a
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
#ifndef CBCA_PART
#define CBCA_PART 0
#endif
#define RING (2 * MAX_ARM + 2)
#define ARM_LEFT 0
#define ARM_RIGHT 1
#define ARM_UP 2
#define ARM_DOWN 3
#define ARM(a, k, i) ((int)(a)[(size_t)(k) * (size_t)H * (size_t)W + (size_t)(i)])

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
static inline int2 row_extent(__global const uchar *arms_l, __global const uchar *arms_r,
                              const int d, const int y, const int x, const int H, const int W)
{
    const int il = y * W + x;
    const int ir = y * W + x - d;
    const int l = min(min(ARM(arms_l, ARM_LEFT, il), ARM(arms_r, ARM_LEFT, ir)), MAX_ARM);
    const int r = min(min(ARM(arms_l, ARM_RIGHT, il), ARM(arms_r, ARM_RIGHT, ir)), MAX_ARM);
    return (int2)(max(x - l, d), min(x + r, W - 1));
}

#if CBCA_PART != 2
/* Pass 1: row sums.  dst(d, y, x) = sum of src(d, y, x') over the row extent
 * of x (not yet divided), NaN for invalid cells (x < d).  dst may be src. */
__kernel void cbca_rows(__global const vol_t *src,     /* D x H x W cost C^{i-1} */
                        __global vol_t *dst,           /* out: D x H x W row sums (may alias src) */
                        __global const uchar *arms_l,  /* 4 x H x W arms of the left image */
                        __global const uchar *arms_r,  /* 4 x H x W arms of the right image */
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
        VOL_SET(dst, row + x, INVALID_COST);
    const int n = W - x0; /* valid cells x0 .. W-1, position i = x - x0 */
    float rs[RING], re[RING];
    float s = 0.0f, e = 0.0f;
    int head = RING - 1;
    for (int t = 0; t < n + MAX_ARM; ++t) {
        head = head + 1 == RING ? 0 : head + 1;
        if (t < n) {
            const float v = VOL_GET(src, row + x0 + t);
            PREFIX_ADD(s, e, v);
        }
        rs[head] = s; /* past the end: P stays constant, never read beyond n - 1 */
        re[head] = e;
        const int i = t - MAX_ARM;
        if (i >= 0) {
            const int x = x0 + i;
            const int2 ext = row_extent(arms_l, arms_r, d, y, x, H, W);
            const int b = ring_slot(head, t, ext.y - x0);
            float sum = rs[b] + re[b];
            if (ext.x > x0) {
                const int a = ring_slot(head, t, ext.x - x0 - 1);
                sum = (rs[b] - rs[a]) + (re[b] - re[a]);
            }
            VOL_SET(dst, row + x, sum);
        }
    }
}
#endif /* CBCA_PART != 2 */

#if CBCA_PART != 2
/* Pass 2: column sums, in place.  buf holds the row sums of pass 1; for each
 * valid cell (x >= d) it becomes the sum of the row sums over the rows of
 * U_d(p) divided by the number of cells |U_d(p)|.  Invalid cells (already
 * NaN from pass 1) are not touched. */
__kernel void cbca_columns(__global vol_t *buf,           /* D x H x W row sums in, C^i out */
                           __global const uchar *arms_l,  /* 4 x H x W arms of the left image */
                           __global const uchar *arms_r,  /* 4 x H x W arms of the right image */
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
            const float v = VOL_GET(buf, VIDX(d, t, x, H, W));
            PREFIX_ADD(s, e, v);
            const int2 ext = row_extent(arms_l, arms_r, d, t, x, H, W);
            cnt += ext.y - ext.x + 1;
        }
        rs[head] = s;
        re[head] = e;
        rn[head] = cnt;
        const int y = t - MAX_ARM;
        if (y >= 0) {
            const int il = y * W + x;
            const int ir = y * W + x - d;
            const int lo = max(y - min(min(ARM(arms_l, ARM_UP, il), ARM(arms_r, ARM_UP, ir)), MAX_ARM), 0);
            const int hi = min(y + min(min(ARM(arms_l, ARM_DOWN, il), ARM(arms_r, ARM_DOWN, ir)), MAX_ARM), H - 1);
            const int b = ring_slot(head, t, hi);
            float sum = rs[b] + re[b];
            int num = rn[b];
            if (lo > 0) {
                const int a = ring_slot(head, t, lo - 1);
                sum = (rs[b] - rs[a]) + (re[b] - re[a]);
                num -= rn[a];
            }
            VOL_SET(buf, VIDX(d, y, x, H, W), sum / (float)num);
        }
    }
}
#endif /* CBCA_PART != 2 */

/* ------------------------------------------------------------------------
 * Short-arm variant (MAX_ARM <= CBCA_SHORT_MAX): the same two passes as
 * direct sums of the 2 MAX_ARM + 1 candidate cells, masked by index, on
 * float16 lanes along x (the contiguous axis).  For short arms (the paper's
 * are <= 3 px) this is several times faster on CPUs than the scalar running
 * sums above, whose per-cell work is independent of the arm length.  Both
 * passes still work in place: the original values a cell's window needs are
 * kept in private memory until the window has been summed.
 * ------------------------------------------------------------------------ */
#define CBCA_SHORT_MAX 8
#define VW 16
#if MAX_ARM <= CBCA_SHORT_MAX

/* Arm k of the 16 pixels first .. first + 15 of one image; lanes not read
 * (i >= n or first + i < 0) get 0. */
static inline uchar16 cbca_arm16u(__global const uchar *a, const int k, const int first, const int n,
                                  const int H, const int W)
{
    __global const uchar *p = a + (size_t)k * (size_t)H * (size_t)W;
    if (n == VW && first >= 0)
        return vload16(0, p + first);
    uchar t[VW];
    for (int i = 0; i < VW; ++i)
        t[i] = (i < n && first + i >= 0) ? p[first + i] : (uchar)0;
    return vload16(0, t);
}

/* As cbca_arm16u, widened to int lanes. */
static inline int16 cbca_arm16(__global const uchar *a, const int k, const int first, const int n,
                               const int H, const int W)
{
    return convert_int16(cbca_arm16u(a, k, first, n, H, W));
}

/* Combined arm of one direction k (ARM_LEFT, ...) for 16 pixels starting at
 * index i of row-major H x W: the shorter of the left image's arm at i and the
 * right image's at i - d (pixel x - d), capped by `cap`.  Uses the caller's
 * arms_l, arms_r, n (lanes in the row), d, H and W. */
#define CBCA_COMBINED16(k, i, cap) \
    min(min(cbca_arm16(arms_l, (k), (i), n, H, W), cbca_arm16(arms_r, (k), (i) - d, n, H, W)), (cap))

#if CBCA_PART != 2
/* Pass 1, short arms: dst(d, y, x) = row sum over the row extent of x
 * (NaN where x < d).  One work-item per row; dst may be src. */
__kernel void cbca_rows_short(__global const vol_t *src,     /* D x H x W cost C^{i-1} */
                              __global vol_t *dst,           /* out: row sums (may alias src) */
                              __global const uchar *arms_l,  /* 4 x H x W arms of the left image */
                              __global const uchar *arms_r,  /* 4 x H x W arms of the right image */
                              const int D,                   /* disparity levels */
                              const int H,                   /* height */
                              const int W)                   /* width */
{
    const int y = get_global_id(0);
    const int d = get_global_id(1);
    if (y >= H || d >= D)
        return;
    const size_t row = VIDX(d, y, 0, H, W);
    /* original values of chunks c-1, c, c+1 (invalid cells and cells outside
     * the row as 0; the masks never select them) */
    float win[3 * VW];
    for (int i = 0; i < VW; ++i)
        win[i] = 0.0f;
    const int nch = (W + VW - 1) / VW;
    {
        const int n = min(VW, W);
        vstore16(select((float16)(0.0f), vol_load16_partial(src, row, n, 0.0f), LANES >= (int16)(d)), 0, win + VW);
    }
    for (int c = 0; c < nch; ++c) {
        const int x0 = c * VW;
        const int n = min(VW, W - x0);
        if (c + 1 < nch) {
            const int x1 = x0 + VW;
            const float16 nx = vol_load16_partial(src, row + x1, min(VW, W - x1), 0.0f);
            vstore16(select((float16)(0.0f), nx, (int16)(x1) + LANES >= (int16)(d)), 0, win + 2 * VW);
        } else {
            vstore16((float16)(0.0f), 0, win + 2 * VW);
        }
        const int16 xs = (int16)(x0) + LANES;
        const int16 valid = (xs >= (int16)(d)) & (LANES < (int16)(n));
        float16 s = (float16)(0.0f);
        if (any(valid)) {
            const int il = y * W + x0;
            const int16 l = CBCA_COMBINED16(ARM_LEFT, il, min((int16)(MAX_ARM), xs - (int16)(d)));
            const int16 r = CBCA_COMBINED16(ARM_RIGHT, il, min((int16)(MAX_ARM), (int16)(W - 1) - xs));
#pragma unroll
            for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {
                const int16 take = ((int16)(k) >= -l) & ((int16)(k) <= r);
                s += select((float16)(0.0f), vload16(0, win + VW + k), take);
            }
        }
        vol_store16_partial(select((float16)(INVALID_COST), s, valid), dst + row + x0, n);
        for (int i = 0; i < 2 * VW; ++i)
            win[i] = win[i + VW];
    }
}
#endif /* CBCA_PART != 2 */

#if CBCA_PART != 2
/* Pass 2, short arms, in place: buf(d, y, x) = (sum of the row sums over
 * the rows of U_d(p)) / |U_d(p)| for valid cells.  One work-item per tile of
 * CBCA_GROUPS x 16 columns of one disparity plane, walking down the rows:
 * wide tiles read CBCA_GROUPS consecutive lines per row, which the CPU's
 * prefetcher follows (a 16-column tile per work-item was ~2x slower). */
#ifndef CBCA_GROUPS
#define CBCA_GROUPS 8
#endif
__kernel void cbca_columns_short(__global vol_t *buf,          /* row sums in, C^i out */
                                 __global const uchar *arms_l, /* 4 x H x W arms of the left image */
                                 __global const uchar *arms_r, /* 4 x H x W arms of the right image */
                                 const int D,                  /* disparity levels */
                                 const int H,                  /* height */
                                 const int W)                  /* width */
{
    const int xt = get_global_id(0) * (VW * CBCA_GROUPS);
    const int d = get_global_id(1);
    if (xt >= W || d >= D)
        return;
    if (min(xt + VW * CBCA_GROUPS, W) - 1 < d)
        return; /* the whole tile is invalid (NaN from pass 1) */
#define RS (2 * MAX_ARM + 1)
    float16 ring[RS * CBCA_GROUPS]; /* row sums of rows t - 2 MAX_ARM .. t, [slot][group] */
    int16 cring[RS * CBCA_GROUPS];  /* their cell counts */
    for (int i = 0; i < RS * CBCA_GROUPS; ++i) { /* slots of rows above the image: defined zeros */
        ring[i] = (float16)(0.0f);
        cring[i] = (int16)(0);
    }
    int head = RS - 1;
    for (int t = 0; t < H + MAX_ARM; ++t) {
        head = head + 1 == RS ? 0 : head + 1;
        const int y = t - MAX_ARM;
        for (int g = 0; g < CBCA_GROUPS; ++g) {
            const int x0 = xt + g * VW;
            if (x0 >= W)
                break;
            const int n = min(VW, W - x0);
            if (x0 + n - 1 < d)
                continue; /* this group is invalid */
            const int16 xs = (int16)(x0) + LANES;
            const int16 valid = (xs >= (int16)(d)) & (LANES < (int16)(n));
            if (t < H) {
                ring[head * CBCA_GROUPS + g] = select((float16)(0.0f), vol_load16_partial(buf, VIDX(d, t, x0, H, W), n, 0.0f), valid);
                const int it = t * W + x0;
                const int16 l = CBCA_COMBINED16(ARM_LEFT, it, min((int16)(MAX_ARM), xs - (int16)(d)));
                const int16 r = CBCA_COMBINED16(ARM_RIGHT, it, min((int16)(MAX_ARM), (int16)(W - 1) - xs));
                cring[head * CBCA_GROUPS + g] = select((int16)(0), l + r + (int16)(1), valid);
            }
            if (y >= 0) {
                const int iy = y * W + x0;
                const int16 u = CBCA_COMBINED16(ARM_UP, iy, (int16)(min(MAX_ARM, y)));
                const int16 w = CBCA_COMBINED16(ARM_DOWN, iy, (int16)(min(MAX_ARM, H - 1 - y)));
                float16 s = (float16)(0.0f);
                int16 cnt = (int16)(0);
#pragma unroll
                for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {
                    int slot = head - (MAX_ARM - k); /* row y + k */
                    slot = slot < 0 ? slot + RS : slot;
                    const int16 take = ((int16)(k) >= -u) & ((int16)(k) <= w);
                    s += select((float16)(0.0f), ring[slot * CBCA_GROUPS + g], take);
                    cnt += select((int16)(0), cring[slot * CBCA_GROUPS + g], take);
                }
                const float16 res = s / convert_float16(max(cnt, (int16)(1)));
                vol_store16_partial(select((float16)(INVALID_COST), res, valid), buf + VIDX(d, y, x0, H, W), n);
            }
        }
    }
#undef RS
}
#endif /* CBCA_PART != 2 */

#if CBCA_PART != 2
/* One whole short-arm iteration per launch: the rows pass and the columns
 * pass above fused, so the volume is read once and written once (the two
 * passes move it twice each).  One work-item per disparity plane walks down
 * the rows: at step t it forms the row sums of row t exactly as
 * cbca_rows_short does (same masked float16 sums, same order) into a ring of
 * the last 2 MAX_ARM + 1 rows kept in global scratch (`ring`, one W-float row
 * per slot, plus the rows' cell counts in `cring`; a few tens of KB per plane,
 * which stay in the cache), then sums the ring rows of U_d(p) for row
 * t - MAX_ARM exactly as cbca_columns_short does and writes that row.  The
 * results are therefore bit-identical to the two-pass kernels.  dst may be
 * src: row t - MAX_ARM is written only after row t was read, all by the same
 * work-item, and no work-item reads another plane. */
#define RS (2 * MAX_ARM + 1)
__kernel void cbca_fused_short(__global const vol_t *src,     /* D x H x W cost C^{i-1} */
                               __global vol_t *dst,           /* out: C^i (may alias src) */
                               __global float *ring,          /* scratch: D x RS x W row sums */
                               __global uchar *cring,         /* scratch: D x RS x W cell counts */
                               __global const uchar *arms_l,  /* 4 x H x W arms of the left image */
                               __global const uchar *arms_r,  /* 4 x H x W arms of the right image */
                               const int D,                   /* disparity levels */
                               const int H,                   /* height */
                               const int W)                   /* width */
{
    const int d = get_global_id(0);
    if (d >= D)
        return;
    __global float *rg = ring + (size_t)d * RS * (size_t)W;
    __global uchar *cg = cring + (size_t)d * RS * (size_t)W;
    for (int i = 0; i < RS * W; ++i) { /* slots of rows above the image: defined zeros */
        rg[i] = 0.0f;
        cg[i] = (uchar)0;
    }
    const int nch = (W + VW - 1) / VW;
    const int c0 = min(d, W) / VW; /* chunks before c0 hold no valid cell */
    int head = RS - 1;
    for (int t = 0; t < H + MAX_ARM; ++t) {
        head = head + 1 == RS ? 0 : head + 1;
        if (t < H) { /* row sums and cell counts of row t into slot head */
            const size_t row = VIDX(d, t, 0, H, W);
            for (int c = c0; c < nch; ++c) {
                const int x0 = c * VW;
                const int n = min(VW, W - x0);
                const int16 xs = (int16)(x0) + LANES;
                const int16 valid = (xs >= (int16)(d)) & (LANES < (int16)(n));
                const int it = t * W + x0;
                const int16 l = CBCA_COMBINED16(ARM_LEFT, it, min((int16)(MAX_ARM), xs - (int16)(d)));
                const int16 r = CBCA_COMBINED16(ARM_RIGHT, it, min((int16)(MAX_ARM), (int16)(W - 1) - xs));
                float16 s = (float16)(0.0f);
                if (x0 >= MAX_ARM && x0 + VW + MAX_ARM <= W) {
                    /* interior: the window lies in the row; invalid (NaN)
                     * cells are never selected (l <= x - d) */
                    __global const vol_t *p = src + row + x0;
#pragma unroll
                    for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {
                        const int16 take = ((int16)(k) >= -l) & ((int16)(k) <= r);
                        s += select((float16)(0.0f), VOL_LOAD16(p + k), take);
                    }
                } else {
                    /* row ends: cells outside the row as 0 (never selected) */
                    float win[VW + 2 * MAX_ARM];
                    for (int i = 0; i < VW + 2 * MAX_ARM; ++i) {
                        const int xi = x0 - MAX_ARM + i;
                        win[i] = (xi >= 0 && xi < W) ? VOL_GET(src, row + xi) : 0.0f;
                    }
#pragma unroll
                    for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {
                        const int16 take = ((int16)(k) >= -l) & ((int16)(k) <= r);
                        s += select((float16)(0.0f), vload16(0, win + MAX_ARM + k), take);
                    }
                }
                const size_t o = (size_t)head * W + x0;
                store16_partial(select((float16)(0.0f), s, valid), rg + o, n);
                const uchar16 cnt = convert_uchar16(select((int16)(0), l + r + (int16)(1), valid));
                if (n == VW) {
                    vstore16(cnt, 0, cg + o);
                } else {
                    uchar tc[VW];
                    vstore16(cnt, 0, tc);
                    for (int i = 0; i < n; ++i)
                        cg[o + i] = tc[i];
                }
            }
        }
        const int y = t - MAX_ARM;
        if (y < 0)
            continue;
        const size_t orow = VIDX(d, y, 0, H, W);
        for (int c = 0; c < nch; ++c) { /* row y of C^i */
            const int x0 = c * VW;
            const int n = min(VW, W - x0);
            if (c < c0) {
                vol_store16_partial((float16)(INVALID_COST), dst + orow + x0, n);
                continue;
            }
            const int16 xs = (int16)(x0) + LANES;
            const int16 valid = (xs >= (int16)(d)) & (LANES < (int16)(n));
            const int iy = y * W + x0;
            const int16 u = CBCA_COMBINED16(ARM_UP, iy, (int16)(min(MAX_ARM, y)));
            const int16 w = CBCA_COMBINED16(ARM_DOWN, iy, (int16)(min(MAX_ARM, H - 1 - y)));
            float16 s = (float16)(0.0f);
            int16 cnt = (int16)(0);
#pragma unroll
            for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {
                int slot = head - (MAX_ARM - k); /* row y + k */
                slot = slot < 0 ? slot + RS : slot;
                const size_t o = (size_t)slot * W + x0;
                const int16 take = ((int16)(k) >= -u) & ((int16)(k) <= w);
                float16 v;
                int16 m;
                if (n == VW) {
                    v = vload16(0, rg + o);
                    m = convert_int16(vload16(0, cg + o));
                } else {
                    float tv[VW];
                    uchar tc[VW];
                    for (int i = 0; i < VW; ++i) {
                        tv[i] = i < n ? rg[o + i] : 0.0f;
                        tc[i] = i < n ? cg[o + i] : (uchar)0;
                    }
                    v = vload16(0, tv);
                    m = convert_int16(vload16(0, tc));
                }
                s += select((float16)(0.0f), v, take);
                cnt += select((int16)(0), m, take);
            }
            const float16 res = s / convert_float16(max(cnt, (int16)(1)));
            vol_store16_partial(select((float16)(INVALID_COST), res, valid), dst + orow + x0, n);
        }
    }
}
#endif /* CBCA_PART != 2 */
#undef RS

/* ------------------------------------------------------------------------
 * cbca_fused_multi_short: up to CBCA_K iterations in one launch ("temporal
 * fusion"), bit-identical to `iters` launches of cbca_fused_short.
 *
 * One work-item per disparity plane walks down the rows once.  At step t
 * iteration i (1 <= i <= iters) forms the row sums of its input row
 * t - (i - 1) MAX_ARM and outputs row t - i MAX_ARM, which is at once the
 * input row of iteration i + 1 at the same step; only the last iteration's
 * rows go to dst.  The volume is thus read once and written once per launch.
 *
 * Everything that is the same in every iteration is computed once per plane
 * and row and kept in small rings in per-plane scratch (cache-resident):
 * the combined arms l, r, u, w (as bytes, already capped at the borders and 0
 * in invalid lanes) and the cell count |U_d(p)| as a float.  Per iteration
 * and 16-px chunk there remain 2 x (2 MAX_ARM + 1) masked adds and one
 * division.
 *
 * Bit-identity with cbca_fused_short: the same float additions in the same
 * order per element.  There `s += select(0, v, take)` for k = -MAX_ARM ..
 * MAX_ARM; here the same (CBCA_SELECT_ADD 1) or `s = select(s, s + v,
 * take)` (CBCA_SELECT_ADD 0, one masked add on AVX-512).  They agree
 * because s starts at +0 and a round-to-nearest sum is -0 only if both terms
 * are -0, so s is never -0 and s + 0 == s.  For a valid lane the term k = 0
 * is always taken (p is in U_d(p)), k < 0 is taken iff k >= -l (r >= 0) and
 * k > 0 iff k <= r.  The division is the same s / (float)count.  In the
 * half-volume variant an iteration's output row is rounded to half before
 * the next iteration reads it (the row buffer is a vol_t row), as the volume
 * round trip of cbca_fused_short does.
 *
 * In place (dst == src): row t of src is read at step t; dst row
 * t - iters MAX_ARM is written at step t, after it was read.
 *
 * Scratch, per plane, with WR = 16 ceil(W / 16) (see CBCA.scratch_bytes):
 *   fscr: CBCA_K x CBCA_NRS float rows of row sums, then CBCA_NCNT ushort
 *         rows of counts (CBCA_FROWS float rows in all)
 *   bscr: 4 x CBCA_NARM rows of arm bytes (l, r, u, w)
 *   xscr: one vol_t row of WR + 2 MAX_ARM cells (the current iteration's
 *         input row, MAX_ARM zero cells of padding on each side)
 * Rows outside the image are never selected; their loads are clamped to
 * rows that were written in this launch, so no scratch needs clearing.
 * ------------------------------------------------------------------------ */
#ifndef CBCA_K
#define CBCA_K 4
#endif
#define CBCA_NRS (2 * MAX_ARM + 1)                          /* row sums of rows y - A .. y + A */
#define CBCA_NARM ((CBCA_K > 2 ? CBCA_K : 2) * MAX_ARM + 1) /* arms of rows t - K A .. t (and t - 2 A) */
#define CBCA_NCNT ((CBCA_K - 1) * MAX_ARM + 1)              /* counts of rows t - K A .. t - A */
#ifndef CBCA_FEVERY
#define CBCA_FEVERY 4
#endif
#define CBCA_FROWS (CBCA_K * CBCA_NRS + (CBCA_NCNT + 1) / 2)  /* float rows per plane (2 count rows per float row) */

/* Aligned 16-lane access to the scratch rows (every scratch row and chunk
 * starts at a multiple of 16 elements from a buffer's base, which OpenCL
 * aligns to at least 128 bytes): one vector load/store, where vstore16 on an
 * unaligned pointer is split up (bytes one by one on PoCL). */
#define SCR_F16(p) (*(__global float16 *)(p))
#define SCR_U16(p) (*(__global uchar16 *)(p))
#if VOL_HALF
#define XROW_STORE16(p, v) vol_store16_partial((v), (p), VW)
#else
#define XROW_STORE16(p, v) (SCR_F16(p) = (v))
#endif

/* Masked running sum of the 2 MAX_ARM + 1 vectors LOAD(k), k = -MAX_ARM ..
 * MAX_ARM in order: term k < 0 taken where NEG >= -k, k > 0 where POS >= k.
 * NEG, POS: char16 arms (<= CBCA_SHORT_MAX, so positive as signed bytes).
 * Two forms of a masked term, the same bits (see above):
 *  CBCA_SELECT_ADD 0: s = select(s, s + v, take), the masks byte compares.
 *    Signed bytes on purpose: for k = +-1 LLVM turns an unsigned or int
 *    "arm >= 1" into "arm != 0" and PoCL then emits an add plus a masked
 *    blend (two 512-bit ops); a signed byte "arm > 0" stays one masked add
 *    (AVX-512).
 *  CBCA_SELECT_ADD 1: s = s + select(0, v, take): the mask applied to v off
 *    the chain of adds (an and, then an add); the arms widened to int lanes
 *    once per call, so that each term's mask is one int compare per 8 lanes
 *    where a byte compare took a compare, a shuffle and two widenings on
 *    AVX2.  Where the kernel is compiled straight to x86 with AVX (PoCL,
 *    CBCA_CPU_ASM 1), CBCA_OPAQUE16 hides the widened arms from the
 *    optimiser (an empty asm statement per 8-lane half), which otherwise
 *    narrows the compares back to bytes.  4 iterations on a 64-row volume
 *    (Zen 3, pthread-haswell): 48 against 59 ms median of 20 rounds (the
 *    byte masks), faster in every round; without the barrier 55 ms.
 * The host sets 1 where the CPU has no AVX-512 (DeviceProfile.wide_vectors). */
#ifndef CBCA_SELECT_ADD
#define CBCA_SELECT_ADD 0
#endif
#if defined(CBCA_CPU_ASM) && (defined(__x86_64__) || defined(__i386__)) && defined(__AVX__)
#if CBCA_CPU_ASM
#define CBCA_OPAQUE16(v)                  \
    do {                                  \
        int8 lo_ = (v).lo, hi_ = (v).hi;  \
        __asm__("" : "+x"(lo_));          \
        __asm__("" : "+x"(hi_));          \
        (v) = (int16)(lo_, hi_);          \
    } while (0)
#endif
#endif
#ifndef CBCA_OPAQUE16
#define CBCA_OPAQUE16(v) ((void)0)
#endif
#if CBCA_SELECT_ADD
#define CBCA_MASKED_SUM(s, LOAD, NEG, POS)                                        \
    do {                                                                          \
        int16 ni_ = convert_int16(NEG), pi_ = convert_int16(POS);                 \
        CBCA_OPAQUE16(ni_);                                                       \
        CBCA_OPAQUE16(pi_);                                                       \
        _Pragma("unroll") for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {             \
            const float16 v_ = LOAD(k);                                           \
            if (k < 0)                                                            \
                (s) = (s) + select((float16)(0.0f), v_, ni_ >= (int16)(-k));      \
            else if (k > 0)                                                       \
                (s) = (s) + select((float16)(0.0f), v_, pi_ >= (int16)(k));       \
            else                                                                  \
                (s) = (s) + v_;                                                   \
        }                                                                         \
    } while (0)
#else
#define CBCA_MASKED_SUM(s, LOAD, NEG, POS)                                        \
    do {                                                                          \
        _Pragma("unroll") for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {             \
            const float16 v_ = LOAD(k);                                           \
            if (k < 0)                                                            \
                (s) = select((s), (s) + v_, convert_int16((NEG) >= (char16)(-k))); \
            else if (k > 0)                                                       \
                (s) = select((s), (s) + v_, convert_int16((POS) >= (char16)(k)));  \
            else                                                                  \
                (s) = (s) + v_;                                                   \
        }                                                                         \
    } while (0)
#endif

/* One chunk (n <= 16 cells) of a volume row into an aligned row buffer. */
#if VOL_HALF
#define CBCA_COPY_CHUNK(to, from, n)                                                   \
    do {                                                                               \
        for (int i_ = 0; i_ < (n); ++i_)                                               \
            ((__global ushort *)(to))[i_] = ((__global const ushort *)(from))[i_];     \
    } while (0)
#else
#define CBCA_COPY_CHUNK(to, from, n)                                                   \
    do {                                                                               \
        if ((n) == VW)                                                                 \
            SCR_F16(to) = vload16(0, (from));                                          \
        else                                                                           \
            store16_partial(load16_partial((from), 0, (n), 0.0f), (to), (n));          \
    } while (0)
#endif

#if CBCA_PART != 1
__kernel void cbca_fused_multi_short(__global const vol_t *src,    /* D x H x W cost C^{i0} */
                                     __global vol_t *dst,          /* out: C^{i0 + iters} (may alias src) */
                                     __global float *fscr,         /* scratch: D x (K NRS + NCNT) x WR floats */
                                     __global uchar *bscr,         /* scratch: D x 5 NARM x WR bytes */
                                     __global vol_t *xscr,         /* scratch: D x 3 x (WR + 32) cells */
                                     __global const uchar *arms_l, /* 4 x H x W arms of the left image */
                                     __global const uchar *arms_r, /* 4 x H x W arms of the right image */
                                     const int D,                  /* disparity levels */
                                     const int H,                  /* height */
                                     const int W,                  /* width */
                                     const int iters)              /* iterations, 1 .. CBCA_K */
{
    const int d = get_global_id(0);
    if (d >= D || iters < 1 || iters > CBCA_K)
        return;
    const int nch = (W + VW - 1) / VW;
    const int WR = nch * VW;
    const int WP = WR + 2 * VW;
    __global float *rsum = fscr + (size_t)d * CBCA_FROWS * (size_t)WR;
    __global ushort *cnts = (__global ushort *)(rsum + (size_t)CBCA_K * CBCA_NRS * WR); /* 64-byte aligned */
    /* arm rings [l, r, u, w, row count l + r + 1][NARM][WR] */
    __global uchar *arm = bscr + (size_t)d * 5 * CBCA_NARM * (size_t)WR;
    const size_t AP = (size_t)CBCA_NARM * WR; /* one plane of arm rings */
    /* row buffers (cell x at offset VW + x, aligned; VW cells of padding on
     * each side, read under masks only): two for src rows (row t is summed
     * while row t + 1 is fetched), one for the later iterations' input */
    __global vol_t *xb = xscr + (size_t)d * 3 * WP;
    for (int i = 0; i < 3 * WP; ++i)
        VOL_SET(xb, i, 0.0f);
    __global vol_t *xs0 = xb + VW;
    __global vol_t *xs1 = xb + WP + VW;
    __global vol_t *xy = xb + 2 * WP + VW;
    const int c0 = min(d, W) / VW; /* chunks before c0 hold no valid cell */
    for (int c = c0; c < nch; ++c)
        CBCA_COPY_CHUNK(xs0 + c * VW, src + VIDX(d, 0, c * VW, H, W), min(VW, W - c * VW));
    for (int t = 0; t < H + iters * MAX_ARM; ++t) {
        if (t < H) { /* combined arms of row t, capped at the borders, 0 in invalid lanes */
            const size_t o = (size_t)(t % CBCA_NARM) * WR;
            const uchar16 capu = (uchar16)((uchar)min(MAX_ARM, t));
            const uchar16 capw = (uchar16)((uchar)min(MAX_ARM, H - 1 - t));
            for (int c = c0; c < nch; ++c) {
                const int x0 = c * VW;
                const int n = min(VW, W - x0);
                const int it = t * W + x0;
                /* bytes throughout (uchar16 is one 128-bit register where
                 * int16 takes four); the lane caps and the valid mask only
                 * near the row ends */
                uchar16 capl = (uchar16)(MAX_ARM), capr = (uchar16)(MAX_ARM), vm = (uchar16)(255);
                if (x0 < d + MAX_ARM || x0 + VW > W - MAX_ARM) {
                    const int16 xs = (int16)(x0) + LANES;
                    vm = as_uchar16(convert_char16((xs >= (int16)(d)) & (LANES < (int16)(n))));
                    capl = convert_uchar16(clamp(xs - (int16)(d), (int16)(0), (int16)(MAX_ARM))) & vm;
                    capr = convert_uchar16(clamp((int16)(W - 1) - xs, (int16)(0), (int16)(MAX_ARM))) & vm;
                }
#define CBCA_COMBINED16U(k) min(cbca_arm16u(arms_l, (k), it, n, H, W), cbca_arm16u(arms_r, (k), it - d, n, H, W))
                const uchar16 l = min(CBCA_COMBINED16U(ARM_LEFT), capl);
                const uchar16 r = min(CBCA_COMBINED16U(ARM_RIGHT), capr);
                SCR_U16(arm + o + x0) = l;
                SCR_U16(arm + AP + o + x0) = r;
                SCR_U16(arm + 2 * AP + o + x0) = min(CBCA_COMBINED16U(ARM_UP), capu) & vm;
                SCR_U16(arm + 3 * AP + o + x0) = min(CBCA_COMBINED16U(ARM_DOWN), capw) & vm;
                SCR_U16(arm + 4 * AP + o + x0) = (l + r + (uchar16)(1)) & vm;
#undef CBCA_COMBINED16U
            }
        }
        const int yc = t - MAX_ARM;
        if (yc >= 0 && yc < H) { /* |U_d(p)| of row yc: the row counts of the rows of U_d(p) */
            const size_t oc = (size_t)(yc % CBCA_NARM) * WR;
            size_t ok[CBCA_NRS]; /* ring offsets of rows yc - A .. yc + A (clamped into the image) */
            for (int k = -MAX_ARM; k <= MAX_ARM; ++k)
                ok[k + MAX_ARM] = 4 * AP + (size_t)(clamp(yc + k, 0, H - 1) % CBCA_NARM) * WR;
            for (int c = c0; c < nch; ++c) {
                const int x0 = c * VW;
                /* ushort lanes (counts <= (2 CBCA_SHORT_MAX + 1)^2), signed
                 * byte masks (see CBCA_MASKED_SUM) */
                const char16 u = as_char16(SCR_U16(arm + 2 * AP + oc + x0));
                const char16 w = as_char16(SCR_U16(arm + 3 * AP + oc + x0));
                ushort16 cnt = (ushort16)(0);
#pragma unroll
                for (int k = -MAX_ARM; k <= MAX_ARM; ++k) {
                    const ushort16 rc = convert_ushort16(SCR_U16(arm + ok[k + MAX_ARM] + x0));
                    if (k < 0)
                        cnt = select(cnt, cnt + rc, convert_short16(u >= (char16)(-k)));
                    else if (k > 0)
                        cnt = select(cnt, cnt + rc, convert_short16(w >= (char16)(k)));
                    else
                        cnt += rc;
                }
                *(__global ushort16 *)(cnts + (size_t)(yc % CBCA_NCNT) * WR + x0) = max(cnt, (ushort16)(1));
            }
        }
        /* src row t + 1 into the other src row buffer, one chunk every
         * CBCA_FEVERY chunk steps of the row-sum loops below (the rest after
         * them): spread over the step, the row's cache misses overlap with
         * arithmetic (fetched in one loop, as before, they outran the misses
         * the core keeps in flight and stalled it; spread over the column
         * loops as well it measured 3-5 % slower) */
        __global vol_t *xn = (t & 1) ? xs0 : xs1;
        __global const vol_t *nrow = src + VIDX(d, min(t + 1, H - 1), 0, H, W);
        int fc = t + 1 < H ? c0 : nch; /* next chunk of row t + 1 to fetch */
        int ftick = 0;
#define CBCA_FETCH()                                                                   \
    do {                                                                               \
        if (fc < nch && ++ftick == CBCA_FEVERY) {                                      \
            ftick = 0;                                                                 \
            CBCA_COPY_CHUNK(xn + fc * VW, nrow + fc * VW, min(VW, W - fc * VW));       \
            ++fc;                                                                      \
        }                                                                              \
    } while (0)
        for (int i = 1; i <= iters; ++i) {
            const int yin = t - (i - 1) * MAX_ARM; /* input row of iteration i */
            const int yo = yin - MAX_ARM;          /* output row of iteration i */
            if (yo >= H)
                continue; /* iteration i is done */
            if (yin < 0)
                break; /* neither it nor the later ones have started */
            __global float *rg = rsum + (size_t)(i - 1) * CBCA_NRS * WR;
            if (yin < H) { /* row sums of row yin into its ring slot */
                __global float *rs = rg + (size_t)(yin % CBCA_NRS) * WR;
                const size_t oa = (size_t)(yin % CBCA_NARM) * WR;
                __global const vol_t *xi = i > 1 ? xy : (t & 1) ? xs1 : xs0;
                for (int c = c0; c < nch; ++c) {
                    const int x0 = c * VW;
                    CBCA_FETCH();
                    const char16 l = as_char16(SCR_U16(arm + oa + x0));
                    const char16 r = as_char16(SCR_U16(arm + AP + oa + x0));
                    __global const vol_t *p = xi + x0;
                    float16 s = (float16)(0.0f);
#define CBCA_LOAD_X(k) VOL_LOAD16(p + (k))
                    CBCA_MASKED_SUM(s, CBCA_LOAD_X, l, r);
#undef CBCA_LOAD_X
                    SCR_F16(rs + x0) = s;
                }
            }
            if (yo < 0)
                break; /* no output row yet: no input for iteration i + 1 */
            /* output row yo: column sums of the row sums over the rows of U_d(p) */
            const size_t oa = (size_t)(yo % CBCA_NARM) * WR;
            __global const ushort *cn = cnts + (size_t)(yo % CBCA_NCNT) * WR;
            const int last = i == iters;
            const size_t orow = VIDX(d, yo, 0, H, W);
            size_t rk[CBCA_NRS]; /* ring offsets of rows yo - A .. yo + A (clamped into the image) */
            for (int k = -MAX_ARM; k <= MAX_ARM; ++k)
                rk[k + MAX_ARM] = (size_t)(clamp(yo + k, 0, H - 1) % CBCA_NRS) * WR;
            if (last)
                for (int c = 0; c < c0; ++c)
                    vol_store16_partial((float16)(INVALID_COST), dst + orow + c * VW, min(VW, W - c * VW));
            for (int c = c0; c < nch; ++c) {
                const int x0 = c * VW;
                const char16 u = as_char16(SCR_U16(arm + 2 * AP + oa + x0));
                const char16 w = as_char16(SCR_U16(arm + 3 * AP + oa + x0));
                float16 s = (float16)(0.0f);
#define CBCA_LOAD_R(k) SCR_F16(rg + rk[(k) + MAX_ARM] + x0)
                CBCA_MASKED_SUM(s, CBCA_LOAD_R, u, w);
#undef CBCA_LOAD_R
                float16 res = s / convert_float16(*(__global const ushort16 *)(cn + x0));
                if (x0 < d)
                    res = select((float16)(INVALID_COST), res, (int16)(x0) + LANES >= (int16)(d));
                if (last)
                    vol_store16_partial(res, dst + orow + x0, min(VW, W - x0));
                else
                    XROW_STORE16(xy + x0, res);
            }
        }
        for (; fc < nch; ++fc)
            CBCA_COPY_CHUNK(xn + fc * VW, nrow + fc * VW, min(VW, W - fc * VW));
#undef CBCA_FETCH
    }
}
#endif /* CBCA_PART != 1 */
#undef CBCA_COPY_CHUNK
#undef CBCA_MASKED_SUM
#undef CBCA_OPAQUE16
#endif /* MAX_ARM <= CBCA_SHORT_MAX */
