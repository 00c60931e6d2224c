/* sgm.cl - semi-global matching along one direction (paper, "Semiglobal
 * matching").  Driven by mccnn_cl/stages/sgm.py, which launches one kernel
 * per direction and accumulates C_SGM = (1/4) sum_r C_r in the output.
 *
 * Required define: MAX_DISP >= D; it sizes the private arrays.
 * Optional define: SGM_CPU_PREFETCH=1 (CPU devices), see SGM_PREFETCH.
 *
 * Validity is decided by index: the cost of cell (d, y, x) is used only when
 * d <= x; entries of C_r(p - r, .) beyond p - r's valid range hold
 * +INFINITY, so they drop out of every minimum.  Invalid cost cells may be
 * loaded as part of a vector but their value is always discarded by a
 * select on the index.
 *
 * The volume is [d][y][x]: only x is contiguous, so both kernels move
 * 16-wide chunks along x (VW floats, one 64-byte line):
 *  - sgm_columns (vertical paths): one work-item walks 32 adjacent columns
 *    at once, as two groups of 16, all arithmetic on float16 lanes;
 *  - sgm_rows (horizontal paths): one work-item walks one row; for each
 *    chunk of 16 x it copies the chunk's D x 16 costs into private memory
 *    transposed to [x][d] (16 x 16 tiles, transposed in registers), runs
 *    the recurrence over those 16 pixels on float16 lanes over d (C_r
 *    overwriting the costs), and transposes the chunk back into the output.
 * Each step of either kernel reads one line in each of D planes, H x W
 * floats apart; the next step's lines are prefetched (SGM_PREFETCH).
 * Private memory per work-item, at MAX_DISP levels: sgm_rows 76 bytes per
 * level (+ ~1.4 KB), sgm_columns 128 bytes per level.
 * Output modes: 0 writes C_r (NaN in invalid cells), 1 adds C_r, 2 adds C_r
 * and divides by 4.
 */
#include "common.h"

#ifndef MAX_DISP
#error "sgm.cl needs -D MAX_DISP=<upper bound of the disparity levels D>"
#endif
#define VW 16

/* Prefetch hint for the line holding *p.  PoCL compiles OpenCL's prefetch()
 * to nothing; with -D SGM_CPU_PREFETCH=1 (set by the host for devices of type
 * CPU) clang's __builtin_prefetch emits a real prefetch instruction - only
 * where the kernel is compiled straight to a CPU instruction set (PoCL).
 * Compilers going through SPIR / SPIR-V (Intel's CPU runtime, Oclgrind,
 * Rusticl's llvmpipe, which aborts on the intrinsic) get prefetch(). */
#if defined(SGM_CPU_PREFETCH) && defined(__has_builtin) && \
    (defined(__x86_64__) || defined(__i386__) || defined(__aarch64__))
#if SGM_CPU_PREFETCH && __has_builtin(__builtin_prefetch)
#define SGM_PREFETCH(p) __builtin_prefetch(p)
#endif
#endif
#ifndef SGM_PREFETCH
#define SGM_PREFETCH(p) prefetch((const __global uchar *)(p), 1)
#endif


/* Combine C_r into the output according to mode (see the header). */
#define SGM_COMBINE(old, val, mode) \
    ((mode) == 1 ? (old) + (val) : ((old) + (val)) * 0.25f)

/* Vertical paths.  One step of the recurrence at level d for the 16 columns
 * x0 .. x0 + n - 1 (n <= 16) of row y, on float16 lanes over x: reads C and
 * the output's line, updates prev[d] = C_r(p, d), *pm1 = C_r(p - r, d) (the
 * next level's C_r(p - r, d - 1)) and *newm = running min_d C_r(p, d), and
 * writes the output's line.  Also prefetches this plane's line of the next
 * row on the path. */
static inline __attribute__((always_inline)) void col_cell(
    __global const vol_t *cost, __global const float *img_r, __global vol_t *out,
    const int H, const int W, const int x0, const int n, const int d, const int y, const int py, const int j,
    const int dy, const int mode, const int16 big_l, const float16 m, float16 *prev, float16 *pm1, float16 *newm,
    const float p1_small, const float p1_one, const float p1_both,
    const float p2_small, const float p2_one, const float p2_both, const float tau_so)
{
    const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const int16 valid = ((int16)(x0) + lane >= (int16)(d)) & (lane < (int16)(n));
    const size_t i0 = VIDX(d, y, x0, H, W);
    if (j + 1 < H) { /* this plane's line of the next row on the path */
        SGM_PREFETCH(cost + VIDX(d, y + dy, x0, H, W));
        if (mode != 0)
            SGM_PREFETCH(out + VIDX(d, y + dy, x0, H, W));
    }
    const float16 c = vol_load16_partial(cost, i0, n, 0.0f);
    float16 val;
    if (j == 0) {
        val = c; /* first pixel of the path */
    } else {
        /* pd = (x - d, y), pd - r = (x - d, py): inside whenever x - d >= 0 */
        const float16 a = load16_partial(img_r, y * W + x0 - d, n, 0.0f);
        const float16 b = load16_partial(img_r, py * W + x0 - d, n, 0.0f);
        const int16 big_r = isless(fabs(a - b), (float16)(tau_so)) == (int16)(0);
        const int16 one = big_l ^ big_r; /* masks: -1 (true) or 0 */
        const int16 both = big_l & big_r;
        const float16 p1 = select(select((float16)(p1_small), (float16)(p1_one), one), (float16)(p1_both), both);
        const float16 p2 = select(select((float16)(p2_small), (float16)(p2_one), one), (float16)(p2_both), both);
        const float16 pd = prev[d];
        const float16 best = fmin(fmin(pd, m + p2), fmin(*pm1, prev[d + 1]) + p1);
        val = c - m + best;
        *pm1 = pd;
    }
    val = select((float16)(INFINITY), val, valid);
    prev[d] = val;
    *newm = fmin(*newm, val);
    float16 o;
    if (mode == 0) {
        o = select((float16)(NAN), val, valid);
    } else {
        const float16 old = vol_load16_partial(out, i0, n, 0.0f);
        o = select(old, SGM_COMBINE(old, val, mode), valid);
    }
    vol_store16_partial(o, out + i0, n);
}

__kernel void sgm_columns(__global const vol_t *cost,  /* D x H x W cost volume (NaN invalid) */
                          __global const float *img_l, /* H x W left image, gray in [0, 1] */
                          __global const float *img_r, /* H x W right image, gray in [0, 1] */
                          __global vol_t *out,         /* D x H x W accumulated C_SGM */
                          const int D,                 /* disparity levels, <= MAX_DISP */
                          const int H,                 /* height */
                          const int W,                 /* width */
                          const int dy,                /* r = (0, dy): +1 top->bottom, -1 bottom->top */
                          const float p1_small,        /* P1 when 0, 1, 2 gradients are large */
                          const float p1_one,
                          const float p1_both,
                          const float p2_small,        /* P2 likewise */
                          const float p2_one,
                          const float p2_both,
                          const float tau_so,          /* gradient threshold (paper 0.0625) */
                          const int mode)              /* 0 write, 1 add, 2 add and divide by 4 */
{
    /* Two adjacent groups of 16 columns per work-item, a: xa .. and b: xa + 16 ..
     * (empty, nb = 0, past the image): each step then touches 128 contiguous
     * bytes of each plane, half the pages per byte of one group (measured
     * ~1.45x faster on PoCL; the pages, not the arithmetic, are the cost). */
    const int xa = get_global_id(0) * 2 * VW;
    if (xa >= W)
        return;
    const int xb = xa + VW;
    const int na = min(VW, W - xa), nb = clamp(W - xb, 0, VW);
    const int dmax = min(D - 1, xa + na + nb - 1);
    float16 prev_a[MAX_DISP + 1], prev_b[MAX_DISP + 1]; /* C_r(p - r, d) of each group */
    for (int d = 0; d <= MAX_DISP; ++d) {
        prev_a[d] = (float16)(INFINITY);
        prev_b[d] = (float16)(INFINITY);
    }
    float16 ma = (float16)(INFINITY), mb = (float16)(INFINITY);
    for (int j = 0; j < H; ++j) {
        const int y = dy > 0 ? j : H - 1 - j;
        const int py = y - dy;
        int16 big_la = (int16)(0), big_lb = (int16)(0);
        if (j > 0) {
            big_la = isless(fabs(load16_partial(img_l, y * W + xa, na, 0.0f) - load16_partial(img_l, py * W + xa, na, 0.0f)),
                            (float16)(tau_so)) == (int16)(0);
            if (nb > 0)
                big_lb = isless(fabs(load16_partial(img_l, y * W + xb, nb, 0.0f) - load16_partial(img_l, py * W + xb, nb, 0.0f)),
                                (float16)(tau_so)) == (int16)(0);
        }
        float16 newma = (float16)(INFINITY), newmb = (float16)(INFINITY);
        float16 pm1a = (float16)(INFINITY), pm1b = (float16)(INFINITY);
        for (int d = 0; d <= dmax; ++d) {
            col_cell(cost, img_r, out, H, W, xa, na, d, y, py, j, dy, mode, big_la, ma, prev_a, &pm1a, &newma,
                     p1_small, p1_one, p1_both, p2_small, p2_one, p2_both, tau_so);
            if (nb > 0)
                col_cell(cost, img_r, out, H, W, xb, nb, d, y, py, j, dy, mode, big_lb, mb, prev_b, &pm1b, &newmb,
                         p1_small, p1_one, p1_both, p2_small, p2_one, p2_both, tau_so);
        }
        if (mode == 0)
            for (int d = dmax + 1; d < D; ++d) {
                vol_store16_partial((float16)(NAN), out + VIDX(d, y, xa, H, W), na);
                if (nb > 0)
                    vol_store16_partial((float16)(NAN), out + VIDX(d, y, xb, H, W), nb);
            }
        ma = newma;
        mb = newmb;
    }
}

/* Transpose of a 16 x 16 block held as 16 float16 rows: afterwards r[i].sj
 * is the former r[j].si.  Each stage splits every pair of rows into their
 * even and odd lanes (rows 0..7 take the even ones, 8..15 the odd ones),
 * which rotates the 8-bit index (row, lane) right by one bit; four stages
 * swap row and lane.  Pure register shuffles (no private-memory round trip). */
static inline __attribute__((always_inline)) void transpose16(float16 *r)
{
    __attribute__((opencl_unroll_hint))
    for (int s = 0; s < 4; ++s) {
        float16 t[VW];
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < VW / 2; ++i) {
            t[i] = (float16)(r[2 * i].even, r[2 * i + 1].even);
            t[i + VW / 2] = (float16)(r[2 * i].odd, r[2 * i + 1].odd);
        }
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < VW; ++i)
            r[i] = t[i];
    }
}

/* Horizontal paths.  One work-item walks one row.  For each chunk of 16
 * x it copies the chunk's costs into a private block transposed to [x][d]
 * (16 x 16 tiles transposed in registers), so that the recurrence at one
 * pixel runs on float16 lanes over d: C_r(p - r, d - 1), (d) and (d + 1)
 * are three shifted loads of the array prev, which holds C_r(p - r, d) at
 * index d + 1 with +INFINITY at index 0 and beyond the valid range.  C_r
 * overwrites the costs in the block; the block is transposed back and
 * combined with the output row by row (vector loads of the output along x). */
__kernel void sgm_rows(__global const vol_t *cost,  /* D x H x W cost volume (NaN invalid) */
                       __global const float *img_l, /* H x W left image, gray in [0, 1] */
                       __global const float *img_r, /* H x W right image, gray in [0, 1] */
                       __global vol_t *out,         /* D x H x W accumulated C_SGM */
                       const int D,                 /* disparity levels, <= MAX_DISP */
                       const int H,                 /* height */
                       const int W,                 /* width */
                       const int dx,                /* r = (dx, 0): +1 left->right, -1 right->left */
                       const float p1_small,        /* P1 when 0, 1, 2 gradients are large */
                       const float p1_one,
                       const float p1_both,
                       const float p2_small,        /* P2 likewise */
                       const float p2_one,
                       const float p2_both,
                       const float tau_so,          /* gradient threshold (paper 0.0625) */
                       const int outside_large,     /* 1: pd - r outside the right image = large D2 */
                       const int mode)              /* 0 write, 1 add, 2 add and divide by 4 */
{
    const int y = get_global_id(0);
    if (y >= H)
        return;
    __global const float *il = img_l + y * W;
    __global const float *ir = img_r + y * W;
    float blk[VW * MAX_DISP]; /* one chunk, [k][d]: costs, overwritten by C_r */
    float buf_a[MAX_DISP + 2 + VW], buf_b[MAX_DISP + 2 + VW];
    float *prev = buf_a; /* C_r(p - r, d) at prev[d + 1] */
    float *cur = buf_b;  /* C_r(p, d) at cur[d + 1] */
    for (int i = 0; i < MAX_DISP + 2 + VW; ++i) {
        buf_a[i] = INFINITY;
        buf_b[i] = INFINITY;
    }
    const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const uint16 reverse = (uint16)(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
    float m = INFINITY; /* min_k C_r(p - r, k) */
    float16 r[VW];
    int big_r_row[MAX_DISP + VW]; /* D2 large, per right pixel of the chunk (below) */
    const int nchunks = (W + VW - 1) / VW;
    for (int ci = 0; ci < nchunks; ++ci) {
        const int x0 = (dx > 0 ? ci : nchunks - 1 - ci) * VW;
        const int n = min(VW, W - x0);
        const int dmaxc = min(D - 1, x0 + n - 1);
        const int ntiles = dmaxc / VW + 1;
        for (int g = 0; g < ntiles; ++g) { /* load the chunk, transposed; d > dmaxc read as 0 */
            const int d0 = g * VW;
            __attribute__((opencl_unroll_hint))
            for (int i = 0; i < VW; ++i)
                r[i] = d0 + i <= dmaxc ? vol_load16_partial(cost, VIDX(d0 + i, y, x0, H, W), n, 0.0f)
                                       : (float16)(0.0f);
            transpose16(r);
            for (int k = 0; k < VW; ++k)
                vstore16(r[k], 0, blk + k * MAX_DISP + d0);
        }
        /* D2 >= tau_so (-1) or not (0) for the right pixels xr = base + t this chunk
         * names (x0 - dmaxc <= xr < x0 + n); entries with xr < 0 are never used */
        const int base = x0 - ntiles * VW;
        for (int t0 = 0; t0 < (ntiles + 1) * VW; t0 += VW) {
            const int xa = base + t0, xb = xa - dx;
            float16 a, b;
            if (xa >= 0 && xb >= 0 && xa + VW <= W && xb + VW <= W) {
                a = vload16(0, ir + xa);
                b = vload16(0, ir + xb);
            } else {
                float ta[VW], tb[VW];
                for (int i = 0; i < VW; ++i) {
                    ta[i] = (xa + i >= 0 && xa + i < W) ? ir[xa + i] : 0.0f;
                    tb[i] = (xb + i >= 0 && xb + i < W) ? ir[xb + i] : 0.0f;
                }
                a = vload16(0, ta);
                b = vload16(0, tb);
            }
            const int16 xrp = (int16)(xb) + lane;
            const int16 outside = (xrp < (int16)(0)) | (xrp >= (int16)(W));
            int16 big = isless(fabs(a - b), (float16)(tau_so)) == (int16)(0);
            big = select(big, (int16)(outside_large ? -1 : 0), outside);
            vstore16(big, 0, big_r_row + t0);
        }
        /* the next chunk's lines of every plane, spread over this chunk's pixels */
        const int cin = ci + 1 < nchunks ? ci + 1 : ci;
        const int x0n = (dx > 0 ? cin : nchunks - 1 - cin) * VW;
        const int dmaxn = min(D - 1, x0n + min(VW, W - x0n) - 1);
        const int pf_per = dmaxn / VW + 1;
        for (int kk = 0; kk < n; ++kk) {
            const int k = dx > 0 ? kk : n - 1 - kk;
            const int x = x0 + k;
            for (int d = kk * pf_per; d < min(kk * pf_per + pf_per, dmaxn + 1); ++d) {
                SGM_PREFETCH(cost + VIDX(d, y, x0n, H, W));
                if (mode != 0)
                    SGM_PREFETCH(out + VIDX(d, y, x0n, H, W));
            }
            const int dmax = min(D - 1, x);
            const int nvec = dmax / VW + 1;
            const int first = x == (dx > 0 ? 0 : W - 1); /* first pixel of the path: C_r = C */
            const int px = x - dx;
            const int big_l = first ? 0 : !(fabs(il[x] - il[px]) < tau_so);
            const float p1_a = big_l ? p1_one : p1_small, p1_b = big_l ? p1_both : p1_one;
            const float p2_a = big_l ? p2_one : p2_small, p2_b = big_l ? p2_both : p2_one;
            float16 newm = (float16)(INFINITY);
            for (int v = 0; v < nvec; ++v) {
                const int d0 = v * VW;
                const int16 ds = (int16)(d0) + lane;
                const int16 valid = ds <= (int16)(dmax);
                float *bp = blk + k * MAX_DISP + d0;
                const float16 c = vload16(0, bp);
                float16 val;
                if (first) {
                    val = c;
                } else {
                    /* D2 large at pd = x - d, lanes d0 .. d0 + 15: big_r[xr - base] reversed */
                    const int16 big_r = as_int16(shuffle(vload16(0, (const uint *)big_r_row + (x - d0 - base - (VW - 1))),
                                                         reverse));
                    const float16 p1 = select((float16)(p1_a), (float16)(p1_b), big_r);
                    const float16 p2 = select((float16)(p2_a), (float16)(p2_b), big_r);
                    const float16 pm = vload16(0, prev + d0);     /* d - 1 */
                    const float16 pd = vload16(0, prev + d0 + 1); /* d */
                    const float16 pn = vload16(0, prev + d0 + 2); /* d + 1 */
                    const float16 best = fmin(fmin(pd, (float16)(m) + p2), fmin(pm, pn) + p1);
                    val = c - (float16)(m) + best;
                }
                val = select((float16)(INFINITY), val, valid);
                vstore16(val, 0, cur + d0 + 1);
                vstore16(val, 0, bp); /* lanes d > dmax: discarded at write-back */
                newm = fmin(newm, val);
            }
            vstore16((float16)(INFINITY), 0, cur + nvec * VW + 1); /* d beyond the valid range */
            const float8 m8 = fmin(newm.lo, newm.hi);
            const float4 m4 = fmin(m8.lo, m8.hi);
            const float2 m2 = fmin(m4.lo, m4.hi);
            m = fmin(m2.x, m2.y);
            float *sw = prev;
            prev = cur;
            cur = sw;
        }
        const int16 xs = (int16)(x0) + lane;
        for (int g = 0; g < ntiles; ++g) { /* write the chunk back, rows d of 16 x */
            const int d0 = g * VW;
            for (int k = 0; k < VW; ++k)
                r[k] = vload16(0, blk + k * MAX_DISP + d0);
            transpose16(r);
            __attribute__((opencl_unroll_hint))
            for (int i = 0; i < VW; ++i) {
                const int d = d0 + i;
                if (d > dmaxc)
                    break;
                const int16 valid = xs >= (int16)(d);
                const size_t i0 = VIDX(d, y, x0, H, W);
                float16 o;
                if (mode == 0) {
                    o = select((float16)(INVALID_COST), r[i], valid);
                } else {
                    const float16 old = vol_load16_partial(out, i0, n, 0.0f);
                    o = select(old, SGM_COMBINE(old, r[i], mode), valid);
                }
                vol_store16_partial(o, out + i0, n);
            }
        }
        if (mode == 0)
            for (int d = dmaxc + 1; d < D; ++d)
                vol_store16_partial((float16)(NAN), out + VIDX(d, y, x0, H, W), n);
    }
}
