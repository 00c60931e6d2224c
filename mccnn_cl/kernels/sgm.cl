/* sgm.cl - semi-global matching (paper, "Semiglobal matching").  Driven by
 * mccnn_cl/stages/sgm.py, which either launches one kernel per direction
 * (sgm_rows, sgm_columns) and accumulates C_SGM = (1/4) sum_r C_r in the
 * output, or runs the paired sweeps (sgm_paired, at the end: two launches
 * of two work-items for all four directions).
 *
 * Defines (the host, stages/sgm.py, passes all nine; defaults in brackets):
 *   MAX_DISP          required, >= D (a multiple of 32); sizes the private arrays
 *   VOL_HALF          [0] volumes stored as half (common.h)
 *   SGM_COLS          [32] columns per sgm_columns work-item, a multiple of 16
 *                     (the host's default: 128 on CPU devices, 32 elsewhere
 *                     and on llvmpipe; mccnn_cl.opencl.device.RULES)
 *   SGM_CPU_PREFETCH  [unset] 1: CPU prefetch instructions, see SGM_PREFETCH
 *   SGM_SPECIALIZE    [1] the column kernel's hot rows compiled per output mode
 *   SGM_WHOLE_TILES   [1] sgm_rows' separate path for whole 16 x 16 tiles
 *   SGM_PAIR_CW       [16] columns per chunk of sgm_paired
 *   SGM_PART          [0] which kernels the program holds: 0 all but the
 *                     16-bit sweeps, 1 the one-direction kernels (sgm_rows,
 *                     sgm_columns), 2 the paired sweeps only, 3 the paired
 *                     sweeps in 16-bit lanes only (sgm_paired_q16, at the
 *                     end; SGM_VW 16, Clang-based compilers).  A program binary holds compiled
 *                     code for each of its kernels (PoCL compiles them all
 *                     when it is asked for one), and sgm_columns alone took
 *                     15 s to compile on a Zen 3: the host builds only the
 *                     part it launches.
 *   SGM_VW            [16] lanes per vector, 16 or 8 (VW below; the host's
 *                     rule sgm_width: 8 on CPUs, measured faster there
 *                     with AVX2 and AVX-512 alike).  The text below says 16;
 *                     with 8, chunks, tiles and groups are 8 wide and the
 *                     same bits come out.
 *
 * Validity is decided by index: the cost of cell (d, y, x) is used only when
 * d <= x; entries of C_r(p - r, .) beyond p - r's valid range hold
 * +INFINITY, so they drop out of every minimum.  Invalid cost cells may be
 * loaded as part of a vector but their value is always discarded by a
 * select on the index.
 *
 * The volume is [d][y][x]: only x is contiguous, so both kernels move
 * 16-wide chunks along x (VW floats, one 64-byte line):
 *  - sgm_columns (vertical paths): one work-item walks SGM_COLS adjacent
 *    columns at once, as SGM_COLS / 16 groups of 16, all arithmetic on
 *    float16 lanes;
 *  - sgm_rows (horizontal paths): one work-item walks one row; for each
 *    chunk of 16 x it copies the chunk's D x 16 costs into private memory
 *    transposed to [x][d] (16 x 16 tiles, transposed in registers), runs
 *    the recurrence over those 16 pixels on float16 lanes over d (C_r
 *    overwriting the costs), and transposes the chunk back into the output.
 * Each step of either kernel reads one line in each of D planes, H x W
 * floats apart; the next step's lines are prefetched (SGM_PREFETCH).
 * Private memory per work-item, at MAX_DISP levels: sgm_rows 76 bytes per
 * level (+ ~1.4 KB), sgm_columns 128 bytes per level, sgm_paired about 80.
 * Output modes: 0 writes C_r (NaN in invalid cells), 1 adds C_r, 2 adds C_r
 * and divides by 4.
 * The loops that move a transposed tile between r[] and the private block
 * are unrolled: as loops, PoCL's LLVM kept r[] on the stack, and the
 * transposes' vector loads each spanned two of the loop's half-width stores,
 * which a CPU cannot forward (a stall per load; sgm_paired 141-154 ->
 * 125-129 ms on a KITTI-sized volume with AVX-512 code, 155 -> 139 ms with
 * AVX2 code, the same bits; BENCHMARKS.md).
 */
#include "common.h"
#include "sgm_recurrence.h"

#ifndef SGM_PART
#define SGM_PART 0
#endif

#ifndef MAX_DISP
#error "sgm.cl needs -D MAX_DISP=<upper bound of the disparity levels D>"
#endif
#ifndef SGM_VW
#define SGM_VW 16
#endif
/* Lanes per vector: 16 (float16) or 8 (float8, for CPUs whose vector
 * registers hold 8 floats: a 16 x 16 transpose needs 32 such registers,
 * an 8 x 8 one 8).  One text for both through these names. */
#if SGM_VW == 16
#define VW 16
#define floatV float16
#define intV int16
#define uintV uint16
#define vloadV vload16
#define vstoreV vstore16
#define LANESV LANES
#define REVERSEV ((uint16)(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0))
#define AS_INTV as_int16
#define AS_UINTV as_uint16
#define transposeV transpose16
#define loadV_partial load16_partial
#define vol_loadV_partial vol_load16_partial
#define vol_storeV_partial vol_store16_partial
#define VOL_LOADV VOL_LOAD16
#define sgm_stepV sgm_step16
#define sgm_step_mp2V sgm_step_mp216
#define fmin_aV fmin_a16
#define SGM_LARGEV SGM_LARGE16
#define SGM_BY_D1_V SGM_BY_D1_16
#elif SGM_VW == 8
#define VW 8
#define floatV float8
#define intV int8
#define uintV uint8
#define vloadV vload8
#define vstoreV vstore8
#define LANESV LANES8
#define REVERSEV ((uint8)(7, 6, 5, 4, 3, 2, 1, 0))
#define AS_INTV as_int8
#define AS_UINTV as_uint8
#define transposeV transpose8
#define loadV_partial load8_partial
#define vol_loadV_partial vol_load8_partial
#define vol_storeV_partial vol_store8_partial
#define VOL_LOADV VOL_LOAD8
#define sgm_stepV sgm_step8
#define sgm_step_mp2V sgm_step_mp28
#define fmin_aV fmin_a8
#define SGM_LARGEV SGM_LARGE8
#define SGM_BY_D1_V SGM_BY_D1_8
#else
#error "SGM_VW must be 16 or 8"
#endif
#define SGM_BY_D2_V SGM_BY_D2_16 /* select: any width */
#define LINE_FLOATS 16 /* floats per 64-byte cache line (prefetch strides) */
#ifndef SGM_COLS
#define SGM_COLS 32 /* columns per work-item of sgm_columns, a multiple of VW */
#endif

/* Prefetch hint for the line holding *p.  PoCL compiles OpenCL's prefetch()
 * to nothing; with -D SGM_CPU_PREFETCH=1 (set by the host on CPU devices,
 * mccnn_cl.opencl.device.RULES) clang's __builtin_prefetch emits a real prefetch instruction - only
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
/* The same hint into the L2 cache only (prefetcht1 where SGM_PREFETCH is a
 * CPU prefetch instruction; prefetch() elsewhere): sgm_paired's next-chunk
 * lines (on PoCL a paired SGM call 196-201 -> 144-156 ms; the row and column
 * kernels got slower with it, 285 -> 305 ms). */
#if defined(SGM_CPU_PREFETCH) && defined(__has_builtin) && \
    (defined(__x86_64__) || defined(__i386__) || defined(__aarch64__))
#if SGM_CPU_PREFETCH && __has_builtin(__builtin_prefetch)
#define SGM_PREFETCH_L2(p) __builtin_prefetch((p), 0, 2)
#endif
#endif
#ifndef SGM_PREFETCH_L2
#define SGM_PREFETCH_L2(p) SGM_PREFETCH(p)
#endif


/* Combine C_r into the output according to mode (see the header). */
#define SGM_COMBINE(old, val, mode) \
    ((mode) == 1 ? (old) + (val) : ((old) + (val)) * 0.25f)

#define SGM_G (SGM_COLS / VW) /* groups of VW columns per work-item of sgm_columns */

/* Vertical penalties of the columns x0 .. x0 + n - 1 (n <= 16; none when
 * n = 0) of row y, whose predecessor on the path is row py: P1 and P2 for a
 * small (*p1a, *p2a) and a large (*p1b, *p2b) D2, given the lanes' D1 =
 * |I^L(x, y) - I^L(x, py)| (sgm_columns, sgm_paired). */
static inline __attribute__((always_inline)) void vertical_penalties(
    __global const float *img_l, const int W, const int y, const int py, const int x0, const int n,
    const float tau_so, const float p1_small, const float p1_one, const float p1_both, const float p2_small,
    const float p2_one, const float p2_both, floatV *p1a, floatV *p1b, floatV *p2a, floatV *p2b)
{
    intV big_l = (intV)(0);
    if (n > 0)
        big_l = SGM_LARGEV(loadV_partial(img_l, y * W + x0, n, 0.0f) - loadV_partial(img_l, py * W + x0, n, 0.0f),
                            tau_so);
    SGM_BY_D1_V(p1_small, p1_one, p1_both, big_l, *p1a, *p1b);
    SGM_BY_D1_V(p2_small, p2_one, p2_both, big_l, *p2a, *p2b);
}

/* Vertical D2 flags (sgm_columns, sgm_paired): bigr[t] = D2 large (-1) or
 * not (0) at right pixel x' = xw - MAX_DISP + t, D2 = |I^R(x', y) -
 * I^R(x', py)|, for t_lo <= t < t_end (multiples of 16); pixels outside the
 * row read as 0 (their flags are never used). */
static inline __attribute__((always_inline)) void vertical_gradients(
    __global const float *img_r, const int W, const int y, const int py, const int xw, const int t_lo,
    const int t_end, const float tau_so, int *bigr)
{
    for (int t0 = t_lo; t0 < t_end; t0 += VW) {
        const int x1 = xw - MAX_DISP + t0;
        floatV a, b;
        if (x1 >= 0 && x1 + VW <= W) {
            a = vloadV(0, img_r + y * W + x1);
            b = vloadV(0, img_r + py * W + x1);
        } else {
            float ta[VW], tb[VW];
            for (int i = 0; i < VW; ++i) {
                const int in = x1 + i >= 0 && x1 + i < W;
                ta[i] = in ? img_r[y * W + x1 + i] : 0.0f;
                tb[i] = in ? img_r[py * W + x1 + i] : 0.0f;
            }
            a = vloadV(0, ta);
            b = vloadV(0, tb);
        }
        vstoreV(isless(fabs(a - b), (floatV)(tau_so)) == (intV)(0), 0, bigr + t0);
    }
}

/* Vertical paths: one row y of the path for the columns xw .. xw + SGM_COLS - 1
 * (groups g of VW columns on floatV lanes over x; groups past the image are
 * skipped), levels d = 0 .. dmax.  C_r(p - r, d) is read from the state row d
 * (st + d * ws) and overwritten by C_r(p, d); the level d + 1 read at step d
 * is carried to step d + 1 in registers (pd), the old level d - 1 too (pm1).
 * bigr[MAX_DISP + x' - xw] says whether D2 at right pixel x' is large (-1).
 * p1a/p1b (p2a/p2b) are P1 (P2) for a small / large D2, given the lanes'
 * D1.  m: min_k C_r(p - r, k), replaced by min_k C_r(p, k).  `first` and
 * `mode` are constants at each call, so each use compiles to its own loop;
 * so is `full` (1: all SGM_COLS columns inside the image). */
static inline __attribute__((always_inline)) void col_row(
    __global const vol_t *cost, __global vol_t *out, __global float *st, const int ws, const int H,
    const int W, const int xw, const int dmax, const int y, const int dy, const int last, const int first,
    const int mode, const int full, const int *bigr, const floatV *p1a, const floatV *p1b,
    const floatV *p2a, const floatV *p2b, floatV *m)
{
    const intV lane = LANESV;
    const size_t plane = (size_t)H * (size_t)W;
    const int next = dy * W; /* offset of the next row on the path */
    floatV newm[SGM_G], pm1[SGM_G], pd[SGM_G];
    int ng[SGM_G];
    __attribute__((opencl_unroll_hint))
    for (int g = 0; g < SGM_G; ++g) {
        ng[g] = full ? VW : clamp(W - xw - g * VW, 0, VW);
        newm[g] = (floatV)(INFINITY);
        pm1[g] = (floatV)(INFINITY);
        pd[g] = first || ng[g] == 0 ? (floatV)(INFINITY) : vloadV(0, st + xw + g * VW);
    }
    __global const vol_t *cp = cost + (size_t)y * W + xw;
    __global vol_t *op = out + (size_t)y * W + xw;
    __global float *sp = st + xw;
    for (int d = 0; d <= dmax; ++d, cp += plane, op += plane, sp += ws) {
        __attribute__((opencl_unroll_hint))
        for (int g = 0; g < SGM_G; ++g) {
            const int n = ng[g];
            if (n == 0)
                continue;
            if (!last) { /* this plane's line of the next row on the path */
                SGM_PREFETCH(cp + g * VW + next);
                SGM_PREFETCH(op + g * VW + next);
            }
            const intV valid = ((intV)(xw + g * VW) + lane >= (intV)(d)) & (lane < (intV)(n));
            const floatV c = vol_loadV_partial(cp, g * VW, n, 0.0f);
            floatV val;
            if (first) {
                val = c; /* first pixel of the path */
            } else {
                const intV big_r = vloadV(0, bigr + MAX_DISP + g * VW - d);
                const floatV pn = vloadV(0, sp + ws + g * VW); /* C_r(p - r, d + 1) */
                val = sgm_stepV(c, m[g], pm1[g], pd[g], pn, SGM_BY_D2_V(p1a[g], p1b[g], big_r),
                                 SGM_BY_D2_V(p2a[g], p2b[g], big_r));
                pm1[g] = pd[g];
                pd[g] = pn;
            }
            val = select((floatV)(INFINITY), val, valid);
            vstoreV(val, 0, sp + g * VW);
            newm[g] = fmin_aV(newm[g], val);
            floatV o;
            if (mode == 0) {
                o = select((floatV)(NAN), val, valid);
            } else {
                const floatV old = vol_loadV_partial(op, g * VW, n, 0.0f);
                o = select(old, SGM_COMBINE(old, val, mode), valid);
            }
            vol_storeV_partial(o, op + g * VW, n);
        }
    }
    __attribute__((opencl_unroll_hint))
    for (int g = 0; g < SGM_G; ++g)
        m[g] = newm[g];
}

/* col_row with constant first (f), mode and full (fl) arguments where it is
 * hot: every row after the first, all SGM_COLS columns inside the image (3
 * inlined copies, one per mode); the first row of a path and a work-item's
 * partial group of columns take the copy with run-time arguments.  Or, with
 * SGM_SPECIALIZE=0, that one copy everywhere.  The same operations on every
 * value (bit-identical).  Each copy unrolls SGM_G groups: 12 specialised
 * copies (every first/mode/full) took PoCL ~11 s to compile at SGM_COLS 128,
 * and Mesa's llvmpipe minutes at MAX_DISP = 32. */
#ifndef SGM_SPECIALIZE
#define SGM_SPECIALIZE 1
#endif
#define COL_ROW(f, md, fl) col_row(cost, out, state, ws, H, W, xw, dmax, y, dy, last, (f), (md), (fl), bigr, \
                                   p1a, p1b, p2a, p2b, m)

#if SGM_PART == 0 || SGM_PART == 1
/* Vertical paths, rows j0 .. j0 + nj - 1 of the path (row y = j on
 * top->bottom paths, H - 1 - j on bottom->top ones): one work-item walks
 * SGM_COLS adjacent columns (SGM_G groups of VW on floatV lanes over x, so
 * each step touches SGM_COLS contiguous elements of each plane).  The path's
 * state between rows, C_r(p - r, d) for d = 0 .. D (level D and levels beyond
 * the valid range hold +INFINITY) and min_k C_r(p - r, k) as level D + 1,
 * lives in `state` ([D + 2][ws] floats, ws >= W a multiple of SGM_COLS), so
 * a path can be walked in several launches (bands of rows). */
__kernel void sgm_columns(__global const vol_t *cost,  /* D x H x W cost volume (NaN invalid) */
                          __global const float *img_l, /* H x W left image, gray in [0, 1] */
                          __global const float *img_r, /* H x W right image, gray in [0, 1] */
                          __global vol_t *out,         /* D x H x W accumulated C_SGM */
                          __global float *state,       /* (D + 2) x ws path state (above) */
                          const int ws,                /* row stride of state */
                          const int D,                 /* disparity levels, <= MAX_DISP */
                          const int H,                 /* height */
                          const int W,                 /* width */
                          const int j0,                /* first row of the path walked here */
                          const int nj,                /* rows walked here */
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
    const int xw = get_global_id(0) * SGM_COLS;
    if (xw >= W)
        return;
    const int dmax = min(D - 1, min(W, xw + SGM_COLS) - 1);
    const int full = xw + SGM_COLS <= W;
    __global float *st_m = state + (size_t)(D + 1) * ws + xw;
    floatV m[SGM_G];
    __attribute__((opencl_unroll_hint))
    for (int g = 0; g < SGM_G; ++g)
        m[g] = j0 == 0 ? (floatV)(INFINITY) : vloadV(0, st_m + g * VW);
    if (j0 == 0) /* levels beyond the valid range (at least level D) */
        for (int d = dmax + 1; d <= D; ++d)
            __attribute__((opencl_unroll_hint))
            for (int g = 0; g < SGM_G; ++g)
                vstoreV((floatV)(INFINITY), 0, state + (size_t)d * ws + xw + g * VW);
    /* D2 large (-1) or not (0) at right pixel x' = xw - MAX_DISP + t, for
     * t >= MAX_DISP - dmax (x' < 0 or >= W: never used, set to 0) */
    int bigr[MAX_DISP + SGM_COLS];
    const int t_lo = (MAX_DISP - dmax) / VW * VW;
    for (int j = j0; j < j0 + nj; ++j) {
        const int y = dy > 0 ? j : H - 1 - j;
        const int last = j + 1 >= H;
        floatV p1a[SGM_G], p1b[SGM_G], p2a[SGM_G], p2b[SGM_G];
        if (j > 0) {
            const int py = y - dy;
            __attribute__((opencl_unroll_hint))
            for (int g = 0; g < SGM_G; ++g) {
                const int x0 = xw + g * VW;
                vertical_penalties(img_l, W, y, py, x0, clamp(W - x0, 0, VW), tau_so, p1_small, p1_one, p1_both,
                                   p2_small, p2_one, p2_both, &p1a[g], &p1b[g], &p2a[g], &p2b[g]);
            }
            vertical_gradients(img_r, W, y, py, xw, t_lo, MAX_DISP + SGM_COLS, tau_so, bigr);
        }
        if (SGM_SPECIALIZE && j > 0 && full) {
            if (mode == 0)
                COL_ROW(0, 0, 1);
            else if (mode == 1)
                COL_ROW(0, 1, 1);
            else
                COL_ROW(0, 2, 1);
        } else {
            COL_ROW(j == 0, mode, full); /* first row: p1a .. p2b and bigr are not read */
        }
        if (mode == 0)
            for (int d = dmax + 1; d < D; ++d)
                for (int g = 0; g < SGM_G; ++g) {
                    const int x0 = xw + g * VW, n = clamp(W - x0, 0, VW);
                    if (n > 0)
                        vol_storeV_partial((floatV)(NAN), out + VIDX(d, y, x0, H, W), n);
                }
    }
    __attribute__((opencl_unroll_hint))
    for (int g = 0; g < SGM_G; ++g)
        vstoreV(m[g], 0, st_m + g * VW);
}
#endif /* SGM_PART == 0 || SGM_PART == 1 */

/* Whole 16 x 16 tiles (16 columns, 16 levels all inside the chunk's valid
 * range) are moved by sgm_rows with plain vector loads and stores one plane
 * apart, without the per-row tests and index arithmetic of the general path
 * (~9 % of the kernel on PoCL).  The values are the same either way;
 * SGM_WHOLE_TILES=0 leaves only the general path (less code, for compilers
 * that take long on it: Mesa's llvmpipe). */
#ifndef SGM_WHOLE_TILES
#define SGM_WHOLE_TILES 1
#endif

/* Floats of sgm_rows' state per row between chunk ranges: C_r(p - r, .) as
 * in prev, and its minimum. */
#define SGM_RST (MAX_DISP + 3 + VW)

/* Horizontal D2 flags of one chunk (sgm_rows, sgm_paired): D2 >= tau_so (-1)
 * or not (0) for the right pixels xr = base + t, 0 <= t < ntiles * 16 + cw
 * (x0 - 16 ntiles <= xr < x0 + cw for a chunk of cw columns at x0 with
 * levels in ntiles tiles), D2 = |I^R(xr) - I^R(xr - dir)|, pixels outside the
 * row large when outside_large; stored reversed at big_r_rev[rt - t], rt =
 * ntiles * 16 + cw - 1, so that lanes d0 .. d0 + 15 of pixel x (xr = x - d)
 * are one vector load (row_chunk); entries with xr < 0 are never used. */
static inline __attribute__((always_inline)) void row_gradients(
    __global const float *ir, const int W, const int base, const int ntiles, const int cw, const int dir,
    const float tau_so, const int outside_large, int *big_r_rev)
{
    const intV lane = LANESV;
    const uintV reverse = REVERSEV;
    for (int t0 = 0; t0 < ntiles * VW + cw; t0 += VW) {
        const int xa = base + t0, xb = xa - dir;
        floatV a, b;
        if (xa >= 0 && xb >= 0 && xa + VW <= W && xb + VW <= W) {
            a = vloadV(0, ir + xa);
            b = vloadV(0, ir + xb);
        } else {
            float ta[VW], tb[VW];
            for (int i = 0; i < VW; ++i) {
                ta[i] = (xa + i >= 0 && xa + i < W) ? ir[xa + i] : 0.0f;
                tb[i] = (xb + i >= 0 && xb + i < W) ? ir[xb + i] : 0.0f;
            }
            a = vloadV(0, ta);
            b = vloadV(0, tb);
        }
        const intV xrp = (intV)(xb) + lane;
        const intV outside = (xrp < (intV)(0)) | (xrp >= (intV)(W));
        intV big = isless(fabs(a - b), (floatV)(tau_so)) == (intV)(0);
        big = select(big, (intV)(outside_large ? -1 : 0), outside);
        vstoreV(AS_INTV(shuffle(AS_UINTV(big), reverse)), 0, big_r_rev + ntiles * VW + cw - VW - t0);
    }
}

/* The prefetches row_chunk spreads over a chunk's pixels (see there): levels
 * d0 .. d1 - 1 of pf_cost (a line per pf_cstep, only while d <= pf_cdmax,
 * where the cost's line lies in its row) and of pf_out (a plane apart), pf_n
 * cells each (the lines at 0, 16, ... and pf_n - 1); into L2 only with l2.
 * Also q16_row_chunk's. */
static inline __attribute__((always_inline)) void prefetch_levels(
    __global const vol_t *pf_cost, __global const vol_t *pf_out, const size_t plane, const int d0, const int d1,
    const int pf_n, const int l2, const size_t pf_cstep, const int pf_cdmax)
{
    for (int d = d0; d < d1; ++d) {
        __global const vol_t *pc = pf_cost + d * pf_cstep, *po = pf_out + d * plane;
        const int cst = d <= pf_cdmax; /* the cost's line lies in its row */
        for (int e = 0; e < pf_n; e += LINE_FLOATS) {
            if (l2) {
                if (cst)
                    SGM_PREFETCH_L2(pc + e);
                SGM_PREFETCH_L2(po + e);
            } else {
                if (cst)
                    SGM_PREFETCH(pc + e);
                SGM_PREFETCH(po + e);
            }
        }
        if (pf_n > 1) {
            if (l2) {
                if (cst)
                    SGM_PREFETCH_L2(pc + pf_n - 1);
                SGM_PREFETCH_L2(po + pf_n - 1);
            } else {
                if (cst)
                    SGM_PREFETCH(pc + pf_n - 1);
                SGM_PREFETCH(po + pf_n - 1);
            }
        }
    }
}

/* Horizontal recurrence over the n pixels x0 .. x0 + n - 1 of one chunk, in
 * the path's order dir (sgm_rows, sgm_paired).  blk holds the chunk as
 * [k][d] (MAX_DISP floats per pixel): costs in, C_r out (lanes d > x
 * undefined).  C_r(p - r, d) is at (*prev)[d + 1] (+INFINITY at 0 and beyond
 * the valid range), its minimum in *m; the two buffers swap per pixel.
 * big_r_rev, base, rt: from row_gradients.  Spread over the pixels, the
 * next chunk's lines are prefetched: levels 0 .. dmaxn of pf_cost and
 * pf_out (its first cells of level 0; levels a plane apart), pf_n cells
 * each (the lines at 0, 16, ... and pf_n - 1); into L2 only with l2. */
static inline __attribute__((always_inline)) void row_chunk(
    float *blk, float **prev, float **cur, float *m, const int x0, const int n, const int dir, const int D,
    const int W, __global const float *il, const float tau_so, const float p1_small, const float p1_one,
    const float p1_both, const float p2_small, const float p2_one, const float p2_both,
    const int *big_r_rev, const int base, const int rt, __global const vol_t *pf_cost,
    __global const vol_t *pf_out, const size_t plane, const int dmaxn, const int pf_n, const int l2,
    const size_t pf_cstep, const int pf_cdmax)
{
    const intV lane = LANESV;
    const int pf_per = dmaxn / n + 1; /* levels prefetched per pixel */
    for (int kk = 0; kk < n; ++kk) {
        const int k = dir > 0 ? kk : n - 1 - kk;
        const int x = x0 + k;
        prefetch_levels(pf_cost, pf_out, plane, kk * pf_per, min(kk * pf_per + pf_per, dmaxn + 1), pf_n, l2,
                        pf_cstep, pf_cdmax);
        const int dmax = min(D - 1, x);
        const int nvec = dmax / VW + 1;
        const int first = x == (dir > 0 ? 0 : W - 1); /* first pixel of the path: C_r = C */
        const int px = x - dir;
        const int big_l = first ? 0 : SGM_LARGE(il[x] - il[px], tau_so);
        float p1_a, p1_b, p2_a, p2_b;
        SGM_BY_D1(p1_small, p1_one, p1_both, big_l, p1_a, p1_b);
        SGM_BY_D1(p2_small, p2_one, p2_both, big_l, p2_a, p2_b);
        const float mm = *m;
        const float mp2_a = mm + p2_a, mp2_b = mm + p2_b; /* m + P2 (sgm_step_mp2N) */
        float *pv = *prev, *cv = *cur;
        const int *br = big_r_rev + rt - (x - base); /* lanes d0 .. at br + d0 */
        floatV newm = (floatV)(INFINITY);
        /* the path's first pixel, the vectors before the last, and the last one (the only one
         * with lanes d > dmax) each in a loop of its own: no test of either in the hot loop */
#define ROW_STEP(v, FIRST, LAST)                                                                        \
    do {                                                                                                \
        const int d0 = (v) * VW;                                                                        \
        float *bp = blk + k * MAX_DISP + d0;                                                            \
        const floatV c = vloadV(0, bp);                                                                 \
        floatV val;                                                                                     \
        if (FIRST) {                                                                                    \
            val = c;                                                                                    \
        } else { /* D2 large at pd = x - d, lanes d0 .. d0 + 15 */                                      \
            const intV big_r = vloadV(0, br + d0);                                                      \
            const floatV pm = vloadV(0, pv + d0);     /* d - 1 */                                        \
            const floatV pd = vloadV(0, pv + d0 + 1); /* d */                                            \
            const floatV pn = vloadV(0, pv + d0 + 2); /* d + 1 */                                        \
            val = sgm_step_mp2V(c, (floatV)(mm), pm, pd, pn,                                            \
                                SGM_BY_D2_V((floatV)(p1_a), (floatV)(p1_b), big_r),                      \
                                SGM_BY_D2_V((floatV)(mp2_a), (floatV)(mp2_b), big_r));                   \
        }                                                                                               \
        if (LAST)                                                                                       \
            val = select((floatV)(INFINITY), val, (intV)(d0) + lane <= (intV)(dmax));                   \
        vstoreV(val, 0, cv + d0 + 1);                                                                   \
        vstoreV(val, 0, bp); /* lanes d > dmax: discarded at write-back */                              \
        newm = fmin_aV(newm, val);                                                                      \
    } while (0)
        if (first) {
            for (int v = 0; v < nvec - 1; ++v)
                ROW_STEP(v, 1, 0);
            ROW_STEP(nvec - 1, 1, 1);
        } else {
            for (int v = 0; v < nvec - 1; ++v)
                ROW_STEP(v, 0, 0);
            ROW_STEP(nvec - 1, 0, 1);
        }
#undef ROW_STEP
        vstoreV((floatV)(INFINITY), 0, cv + nvec * VW + 1); /* d beyond the valid range */
#if VW == 16
        const float8 m8 = fmin(newm.lo, newm.hi);
        const float4 m4 = fmin(m8.lo, m8.hi);
#else
        const float4 m4 = fmin(newm.lo, newm.hi);
#endif
        const float2 m2 = fmin(m4.lo, m4.hi);
        *m = fmin(m2.x, m2.y);
        *prev = cv;
        *cur = pv;
    }
}

/* Loads one 16 x 16 tile of the cost volume (sgm_rows, sgm_paired): r[i] =
 * level d0 + i of row y at the columns x0 .. x0 + n - 1; levels beyond dmax
 * and columns beyond n read as 0. */
static inline __attribute__((always_inline)) void load_tile(
    floatV *r, __global const vol_t *cost, const int y, const int x0, const int d0, const int n, const int dmax,
    const int H, const int W)
{
    if (SGM_WHOLE_TILES && n == VW && d0 + VW - 1 <= dmax) { /* plain loads, one plane apart */
        __global const vol_t *src = cost + VIDX(d0, y, x0, H, W);
        const size_t plane = (size_t)H * (size_t)W;
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < VW; ++i)
            r[i] = VOL_LOADV(src + i * plane);
    } else {
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < VW; ++i)
            r[i] = d0 + i <= dmax ? vol_loadV_partial(cost, VIDX(d0 + i, y, x0, H, W), n, 0.0f) : (floatV)(0.0f);
    }
}

/* SGM_OPAQUE(v): where the kernel is compiled straight to x86 with AVX (PoCL;
 * see SGM_PREFETCH; an 8-float vector is then one ymm register, which the
 * "x" constraint names), an empty asm statement that hides how v was made
 * from the optimiser: LLVM turns a reversed 8-float load into four 2-float
 * loads and four shuffles, not the one load and one permute it then gets.
 * Elsewhere nothing. */
#if defined(SGM_CPU_PREFETCH) && (defined(__x86_64__) || defined(__i386__)) && defined(__AVX__) && VW == 8
#if SGM_CPU_PREFETCH
#define SGM_OPAQUE(v) __asm__("" : "+x"(v))
#endif
#endif
#ifndef SGM_OPAQUE
#define SGM_OPAQUE(v) ((void)0)
#endif

/* load_tile of the right-reference volume C_R' without making it (sgm_paired
 * with mirror = 1): C_R'(d, y, x) = C(d, y, W - 1 + d - x) for x >= d, the
 * invalid cells x < d INVALID_COST, as disparity_right_volume would have
 * written them in place (disparity.cl), so the bits are those of the explicit
 * mirror.  Lane k of level d reads the line of C backwards: a whole tile is
 * VW plain loads, one plane + 1 cell apart, each reversed in registers; a
 * level whose lanes would reach past x = W - 1 (x0 < d, the diagonal) or
 * before x = 0 goes cell by cell. */
static inline __attribute__((always_inline)) void load_tile_mirror(
    floatV *r, __global const vol_t *cost, const int y, const int x0, const int d0, const int n, const int dmax,
    const int H, const int W)
{
    const size_t plane = (size_t)H * (size_t)W;
    if (SGM_WHOLE_TILES && n == VW && d0 + VW - 1 <= min(dmax, x0)) {
        __global const vol_t *src = cost + VIDX(d0, y, W - VW + d0 - x0, H, W);
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < VW; ++i) {
            floatV v = VOL_LOADV(src + i * (plane + 1));
            SGM_OPAQUE(v);
            r[i] = shuffle(v, REVERSEV);
        }
        return;
    }
    const intV lane = LANESV;
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < VW; ++i) {
        const int d = d0 + i;
        if (d > dmax) {
            r[i] = (floatV)(0.0f);
        } else if (d <= x0 && W - VW + d - x0 >= 0) {
            floatV v = VOL_LOADV(cost + VIDX(d, y, W - VW + d - x0, H, W));
            SGM_OPAQUE(v);
            r[i] = select((floatV)(0.0f), shuffle(v, REVERSEV), lane < (intV)(n));
        } else {
            __global const vol_t *line = cost + VIDX(d, y, 0, H, W);
            float t[VW];
            for (int k = 0; k < VW; ++k)
                t[k] = k >= n ? 0.0f : x0 + k < d ? INVALID_COST : VOL_GET(line, W - 1 + d - x0 - k);
            r[i] = vloadV(0, t);
        }
    }
}

/* Writes (mode 0) or combines (modes 1 and 2, SGM_COMBINE) one 16 x 16 tile
 * of C_r into the output (sgm_rows, sgm_paired): r[i] holds level d0 + i at
 * the columns x0 .. x0 + n - 1 of one row, plus, when add is not 0, add's
 * level row (16 floats per level, at add + d * 16); levels beyond dmax are
 * not written.  dst: the output at cell (d0, y, x0), levels a plane apart.
 * Cells with x < d keep their value (mode 0 writes NaN there). */
static inline __attribute__((always_inline)) void write_tile(
    const floatV *r, __global const float *add, __global vol_t *dst, const size_t plane, const int x0,
    const int d0, const int n, const int dmax, const int mode)
{
    const intV xs = (intV)(x0) + LANESV;
    if (SGM_WHOLE_TILES && n == VW && d0 + VW - 1 <= dmax && x0 >= d0 + VW - 1) {
        /* every cell valid (x >= d): plain loads and stores, no select */
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < VW; ++i) {
            const floatV v = add ? r[i] + vloadV(0, add + (d0 + i) * VW) : r[i];
            __global vol_t *p = dst + i * plane;
            vol_storeV_partial(mode == 0 ? v : SGM_COMBINE(VOL_LOADV(p), v, mode), p, VW);
        }
        return;
    }
    if (SGM_WHOLE_TILES && n == VW && d0 + VW - 1 <= dmax) { /* plain loads and stores */
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < VW; ++i) {
            const intV valid = xs >= (intV)(d0 + i);
            const floatV v = add ? r[i] + vloadV(0, add + (d0 + i) * VW) : r[i];
            __global vol_t *p = dst + i * plane;
            floatV o;
            if (mode == 0) {
                o = select((floatV)(INVALID_COST), v, valid);
            } else {
                const floatV old = VOL_LOADV(p);
                o = select(old, SGM_COMBINE(old, v, mode), valid);
            }
            vol_storeV_partial(o, p, VW);
        }
        return;
    }
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < VW; ++i) {
        const int d = d0 + i;
        if (d > dmax)
            break;
        const intV valid = xs >= (intV)(d);
        const floatV v = add ? r[i] + vloadV(0, add + d * VW) : r[i];
        __global vol_t *p = dst + i * plane;
        floatV o;
        if (mode == 0) {
            o = select((floatV)(INVALID_COST), v, valid);
        } else {
            const floatV old = vol_loadV_partial(p, 0, n, 0.0f);
            o = select(old, SGM_COMBINE(old, v, mode), valid);
        }
        vol_storeV_partial(o, p, n);
    }
}

#if SGM_PART == 0 || SGM_PART == 1
/* Horizontal paths.  One work-item walks one row.  For each chunk of 16
 * x it copies the chunk's costs into a private block transposed to [x][d]
 * (16 x 16 tiles transposed in registers), so that the recurrence at one
 * pixel runs on floatV lanes over d: C_r(p - r, d - 1), (d) and (d + 1)
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
                       const int mode,              /* 0 write, 1 add, 2 add and divide by 4 */
                       const int y0,                /* first row walked by this launch */
                       const int ny,                /* rows walked by this launch */
                       const int both,              /* 1: then walk each row the other way (-dx), adding */
                       const int c0,                /* chunks c0 .. c1 - 1 along the walk (both = 0 unless */
                       const int c1,                /*   the whole row: c0 = 0, c1 >= its chunks) */
                       __global float *rst)         /* ny x SGM_RST path state between chunk ranges */
{
    if (get_global_id(0) >= ny)
        return;
    const int y = y0 + get_global_id(0);
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
    const intV lane = LANESV;
    const size_t plane = (size_t)H * (size_t)W;
    for (int pass = 0; pass < 1 + both; ++pass) {
        /* the second pass (both = 1) walks the row the other way, adding to the
         * first pass's output while the row is still in the cache */
        const int dxp = pass ? -dx : dx;
        const int modep = pass ? 1 : mode;
        if (pass)
            for (int i = 0; i < MAX_DISP + 2 + VW; ++i) {
                buf_a[i] = INFINITY;
                buf_b[i] = INFINITY;
            }
        float m = INFINITY; /* min_k C_r(p - r, k) */
        /* a row walked in several launches (chunk ranges; llvmpipe ends a
         * work-item's loops after 65535 iterations): C_r(p - r, .) and its
         * minimum are kept in rst between them */
        __global float *rs = rst + (size_t)get_global_id(0) * SGM_RST;
        if (c0 > 0) {
            for (int i = 0; i < MAX_DISP + 2 + VW; ++i)
                prev[i] = rs[i];
            m = rs[MAX_DISP + 2 + VW];
        }
        floatV r[VW];
        int big_r_rev[MAX_DISP + VW]; /* D2 large, per right pixel of the chunk, reversed (row_gradients) */
        const int nchunks = (W + VW - 1) / VW;
        const int cend = min(c1, nchunks);
        for (int ci = c0; ci < cend; ++ci) {
            const int x0 = (dxp > 0 ? ci : nchunks - 1 - ci) * VW;
            const int n = min(VW, W - x0);
            const int dmaxc = min(D - 1, x0 + n - 1);
            const int ntiles = dmaxc / VW + 1;
            for (int g = 0; g < ntiles; ++g) { /* load the chunk, transposed; d > dmaxc read as 0 */
                const int d0 = g * VW;
                load_tile(r, cost, y, x0, d0, n, dmaxc, H, W);
                transposeV(r);
                __attribute__((opencl_unroll_hint)) /* unrolled: r[] stays in registers (header) */
                for (int k = 0; k < VW; ++k)
                    vstoreV(r[k], 0, blk + k * MAX_DISP + d0);
            }
            const int base = x0 - ntiles * VW, rt = (ntiles + 1) * VW - 1;
            row_gradients(ir, W, base, ntiles, VW, dxp, tau_so, outside_large, big_r_rev);
            /* the next chunk's lines of every plane, spread over this chunk's pixels */
            const int cin = ci + 1 < nchunks ? ci + 1 : ci;
            const int x0n = (dxp > 0 ? cin : nchunks - 1 - cin) * VW;
            const int dmaxn = min(D - 1, x0n + min(VW, W - x0n) - 1);
            row_chunk(blk, &prev, &cur, &m, x0, n, dxp, D, W, il, tau_so, p1_small, p1_one, p1_both, p2_small,
                      p2_one, p2_both, big_r_rev, base, rt, cost + VIDX(0, y, x0n, H, W), out + VIDX(0, y, x0n, H, W),
                      plane, dmaxn, 1, 0, plane, dmaxn);
            for (int g = 0; g < ntiles; ++g) { /* write the chunk back, rows d of 16 x */
                const int d0 = g * VW;
                __attribute__((opencl_unroll_hint)) /* unrolled: r[] stays in registers (header) */
                for (int k = 0; k < VW; ++k)
                    r[k] = vloadV(0, blk + k * MAX_DISP + d0);
                transposeV(r);
                write_tile(r, (__global const float *)0, out + VIDX(d0, y, x0, H, W), plane, x0, d0, n, dmaxc, modep);
            }
            if (modep == 0)
                for (int d = dmaxc + 1; d < D; ++d)
                    vol_storeV_partial((floatV)(NAN), out + VIDX(d, y, x0, H, W), n);
        }
        if (cend < nchunks) {
            for (int i = 0; i < MAX_DISP + 2 + VW; ++i)
                rs[i] = prev[i];
            rs[MAX_DISP + 2 + VW] = m;
        }
    }
}
#endif /* SGM_PART == 0 || SGM_PART == 1 */

#if SGM_PART == 0 || SGM_PART == 2
/* The vertical recurrence over the rows i < iend of one tile of sgm_paired
 * (levels d0 + i, lanes over VW columns): C_r from the costs r[i], the
 * previous row's C_r in the group's state sg ([D + 2][VW], level d at sg +
 * d * VW, overwritten) and its minimum mv (mp2a, mp2b: mv + P2 for a small
 * and a large D2, sgm_step_mp2N); pm1 and pd carry levels d - 1
 * and d from row to row; bigv[-d]: the lanes' D2 flags at level d; newmv
 * gathers the minimum.  masked = 0 for a whole tile of a row after the
 * path's first (every lane valid, so no select of +INFINITY for x < d or for
 * lanes past the image; all VW levels; vfirst 0): a constant at each call,
 * so that call compiles to straight code without those tests. */
static inline __attribute__((always_inline)) void vertical_tile(
    const floatV *r, const int *bigv, __global float *sg, const int d0, const int iend, const int vfirst,
    const floatV mv, const floatV p1a, const floatV p1b, const floatV mp2a, const floatV mp2b, floatV *pm1,
    floatV *pd, floatV *newmv, const intV xs, const intV valid_x, const int masked)
{
    /* the tile's flags and state from base pointers, each level at a constant offset */
    const int *bq = bigv - d0;
    __global float *sq = sg + d0 * VW;
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < VW; ++i) { /* a constant trip count keeps r[] in registers */
        const int d = d0 + i;
        if (!masked || i < iend) {
            floatV val;
            if (masked && vfirst) {
                val = r[i];
            } else {
                const intV big_r = vloadV(0, bq - i);
                const floatV pn = vloadV(0, sq + (i + 1) * VW); /* C_r(p - r, d + 1) */
                val = sgm_step_mp2V(r[i], mv, *pm1, *pd, pn, SGM_BY_D2_V(p1a, p1b, big_r),
                                    SGM_BY_D2_V(mp2a, mp2b, big_r));
                *pm1 = *pd;
                *pd = pn;
            }
            if (masked)
                val = select((floatV)(INFINITY), val, (xs >= (intV)(d)) & valid_x);
            vstoreV(val, 0, sq + i * VW);
            *newmv = fmin_aV(*newmv, val);
        }
    }
}
#endif /* SGM_PART == 0 || SGM_PART == 2 */

#if SGM_PART == 0 || SGM_PART == 2
/* Paired sweeps (``sgm_paired``, two work-items, two launches): work-item A
 * walks its rows top to bottom and adds the left->right and top->bottom
 * paths, work-item B walks its rows bottom to top and adds the right->left
 * and bottom->top paths.  Launch 0: A rows 0 .. h - 1, B rows H - 1 .. h,
 * each writing its pair's sum; launch 1: A rows h .. H - 1, B rows h - 1 .. 0,
 * each adding its pair's sum to the other's and dividing by 4, so every cell
 * is ((C_lr + C_tb) + (C_rl + C_bt)) / 4 (float addition commutes, so both
 * halves round alike).  The volume is read twice and the output written
 * twice (with one read), instead of four volume reads, three output reads
 * and four writes for the one-direction kernels.
 *
 * Per row, chunks of SGM_PAIR_CW columns (a multiple of 16; the host uses
 * 16: wider chunks measured slower on PoCL) in the horizontal path's order;
 * per chunk and 16-column group: the group's D x 16 costs are loaded as
 * 16 x 16 tiles and the vertical recurrence runs on the tiles' rows (floatV
 * lanes over x, levels in sequence, as in col_row), its C_r stored in the
 * path state (global; per work-item and group one contiguous [D + 2][16]
 * block, the minimum per column as level D + 1, so a chunk touches a few
 * pages of state instead of D + 2); the tiles are transposed into the
 * private block; then the horizontal recurrence runs over the chunk's pixels
 * as in sgm_rows, the block is transposed back, the group's vertical C_r
 * (still in the state) added, and the result written or added.
 *
 * mirror = 1: the costs are those of the right-reference volume C_R'(d, y, x)
 * = cost(d, y, W - 1 + d - x) (load_tile_mirror), which the pipeline's right
 * reference then never makes (RightReference.volume would mirror the volume
 * in place and back: two volume passes); the same bits as mirror = 0 on C_R'. */
#ifndef SGM_PAIR_CW
#define SGM_PAIR_CW 16
#endif
#define PCW SGM_PAIR_CW
/* vec_type_hint: the kernel is written on floatV vectors.  Intel's CPU runtime
 * otherwise vectorises the work-items' code once more across work-items (its
 * implicit vectoriser), and a call ran at 183-246 against 158-165 ms on a
 * KITTI-sized volume (kernel_ab.py with the hint as a switch, 4 rounds); PoCL's
 * code is the same either way (131-134 against 133-191 ms, AVX2 code 159-161
 * against 158-172 ms). */
__kernel __attribute__((vec_type_hint(floatV))) void sgm_paired(__global const vol_t *cost,  /* D x H x W cost volume (NaN invalid) */
                         __global const float *img_l, /* H x W left image, gray in [0, 1] */
                         __global const float *img_r, /* H x W right image, gray in [0, 1] */
                         __global vol_t *out,         /* D x H x W C_SGM */
                         __global float *state,       /* 2 x ws / 16 x (D + 2) x 16 vertical path state */
                         const int ws,                /* W rounded up to a multiple of SGM_PAIR_CW */
                         const int D,                 /* disparity levels, <= MAX_DISP */
                         const int H,                 /* height */
                         const int W,                 /* width */
                         const int h,                 /* rows 0 .. h - 1 are A's in launch 0 */
                         const int launch_no,         /* 0: write the pair's sum, 1: add and divide by 4 */
                         const float ph1_small,       /* horizontal P1 when 0, 1, 2 gradients are large */
                         const float ph1_one,
                         const float ph1_both,
                         const float ph2_small,       /* horizontal P2 likewise */
                         const float ph2_one,
                         const float ph2_both,
                         const float pv1_small,       /* vertical P1 */
                         const float pv1_one,
                         const float pv1_both,
                         const float pv2_small,       /* vertical P2 */
                         const float pv2_one,
                         const float pv2_both,
                         const float tau_so,          /* gradient threshold (paper 0.0625) */
                         const int outside_large,     /* 1: pd - r outside the right image = large D2 */
                         const int mirror)            /* 1: read cost as the right-reference volume C_R' */
{
    const int role = get_global_id(0);
    if (role > 1)
        return;
    const int dir = role == 0 ? 1 : -1; /* r = (dir, 0) and (0, dir) */
    const int mode = launch_no == 0 ? 0 : 2;
    const int split = role == 0 ? h : H - h; /* path rows j < split are walked in launch 0 */
    const int j0 = launch_no == 0 ? 0 : split, j1 = launch_no == 0 ? split : H;
    __global float *st = state + (size_t)role * (size_t)(D + 2) * (size_t)ws;
    float blk[PCW * MAX_DISP]; /* one chunk, [k][d]: costs, overwritten by the horizontal C_r */
    float buf_a[MAX_DISP + 2 + VW], buf_b[MAX_DISP + 2 + VW];
    int big_r_rev[MAX_DISP + PCW]; /* horizontal D2 large, reversed (as in sgm_rows) */
    int bigv[MAX_DISP + PCW];      /* vertical D2 large at right pixel x0 - MAX_DISP + t */
    const intV lane = LANESV;
    const size_t plane = (size_t)H * (size_t)W;
    const int nchunks = (W + PCW - 1) / PCW;
    for (int j = j0; j < j1; ++j) {
        const int y = dir > 0 ? j : H - 1 - j;
        const int vfirst = j == 0;
        const int py = vfirst ? y : y - dir; /* previous row of the vertical path */
        __global const float *il = img_l + y * W;
        __global const float *ir = img_r + y * W;
        float *prev = buf_a; /* horizontal C_r(p - r, d) at prev[d + 1] */
        float *cur = buf_b;
        for (int i = 0; i < MAX_DISP + 2 + VW; ++i) {
            buf_a[i] = INFINITY;
            buf_b[i] = INFINITY;
        }
        float m = INFINITY; /* horizontal min_k C_r(p - r, k) */
        floatV r[VW];
        for (int ci = 0; ci < nchunks; ++ci) {
            const int x0 = (dir > 0 ? ci : nchunks - 1 - ci) * PCW;
            const int n = min(PCW, W - x0);
            const int dmaxc = min(D - 1, x0 + n - 1);
            const int ntiles = dmaxc / VW + 1;
            if (!vfirst) /* vertical D2 at right pixels x0 - MAX_DISP + t, t >= MAX_DISP - dmaxc */
                vertical_gradients(img_r, W, y, py, x0, (MAX_DISP - dmaxc) / VW * VW, MAX_DISP + PCW, tau_so, bigv);
            for (int gx = 0; gx * VW < n; ++gx) { /* 16-column groups: vertical path, transpose into blk */
                const int xg = x0 + gx * VW, ng = min(VW, n - gx * VW);
                __global float *sg = st + (size_t)(xg / VW) * (D + 2) * VW; /* the group's state, [D + 2][16] */
                const intV xs = (intV)(xg) + lane;
                const intV valid_x = lane < (intV)(ng);
                const int dmaxg = min(D - 1, xg + ng - 1);
                floatV p1a = (floatV)(0.0f), p1b = p1a, p2a = p1a, p2b = p1a, mv, pd, pm1;
                if (vfirst) {
                    /* levels beyond the group's valid range read as +INFINITY at level d + 1 */
                    for (int d = dmaxg + 1; d <= D; ++d)
                        vstoreV((floatV)(INFINITY), 0, sg + d * VW);
                    mv = (floatV)(INFINITY);
                    pd = mv;
                    pm1 = mv;
                } else {
                    vertical_penalties(img_l, W, y, py, xg, ng, tau_so, pv1_small, pv1_one, pv1_both, pv2_small,
                                       pv2_one, pv2_both, &p1a, &p1b, &p2a, &p2b);
                    mv = vloadV(0, sg + (D + 1) * VW);
                    pd = vloadV(0, sg);
                    pm1 = (floatV)(INFINITY);
                }
                const floatV mp2a = mv + p2a, mp2b = mv + p2b; /* m + P2 (sgm_step_mp2N) */
                floatV newmv = (floatV)(INFINITY);
                for (int g = 0; g < ntiles; ++g) {
                    const int d0 = g * VW;
                    if (mirror)
                        load_tile_mirror(r, cost, y, xg, d0, ng, dmaxg, H, W);
                    else
                        load_tile(r, cost, y, xg, d0, ng, dmaxg, H, W);
                    const int iend = min(VW, dmaxg + 1 - d0);
                    /* the validity select, the first row and a partial tile only where they occur */
                    if (!vfirst && ng == VW && xg >= d0 + VW - 1 && iend == VW)
                        vertical_tile(r, bigv + MAX_DISP + gx * VW, sg, d0, iend, vfirst, mv, p1a, p1b, mp2a, mp2b,
                                      &pm1, &pd, &newmv, xs, valid_x, 0);
                    else
                        vertical_tile(r, bigv + MAX_DISP + gx * VW, sg, d0, iend, vfirst, mv, p1a, p1b, mp2a, mp2b,
                                      &pm1, &pd, &newmv, xs, valid_x, 1);
                    transposeV(r);
                    __attribute__((opencl_unroll_hint)) /* unrolled: r[] stays in registers (header) */
                    for (int k = 0; k < VW; ++k)
                        vstoreV(r[k], 0, blk + (gx * VW + k) * MAX_DISP + d0);
                }
                vstoreV(newmv, 0, sg + (D + 1) * VW);
            }
            /* horizontal D2 and recurrence, as in sgm_rows */
            const int base = x0 - ntiles * VW, rt = ntiles * VW + PCW - 1;
            row_gradients(ir, W, base, ntiles, PCW, dir, tau_so, outside_large, big_r_rev);
            const int cin = ci + 1 < nchunks ? ci + 1 : ci;
            const int x0n = (dir > 0 ? cin : nchunks - 1 - cin) * PCW;
            const int nn = min(PCW, W - x0n);
            const int dmaxn = min(D - 1, x0n + nn - 1);
            /* the next chunk's cost lines: in C_R' (mirror) those of C at W - x0n - nn + d, d <= x0n */
            row_chunk(blk, &prev, &cur, &m, x0, n, dir, D, W, il, tau_so, ph1_small, ph1_one, ph1_both, ph2_small,
                      ph2_one, ph2_both, big_r_rev, base, rt,
                      mirror ? cost + VIDX(0, y, W - x0n - nn, H, W) : cost + VIDX(0, y, x0n, H, W),
                      out + VIDX(0, y, x0n, H, W), plane, dmaxn, nn, 1, mirror ? plane + 1 : plane,
                      mirror ? min(dmaxn, x0n) : dmaxn);
            for (int gx = 0; gx * VW < n; ++gx) { /* write back: horizontal + vertical C_r, rows d of 16 x */
                const int xg = x0 + gx * VW, ng = min(VW, n - gx * VW);
                __global float *sg = st + (size_t)(xg / VW) * (D + 2) * VW; /* the group's state, [D + 2][16] */
                const int dmaxg = min(D - 1, xg + ng - 1);
                for (int g = 0; g <= dmaxg / VW; ++g) {
                    const int d0 = g * VW;
                    __attribute__((opencl_unroll_hint)) /* unrolled: r[] stays in registers (header) */
                    for (int k = 0; k < VW; ++k)
                        r[k] = vloadV(0, blk + (gx * VW + k) * MAX_DISP + d0);
                    transposeV(r);
                    write_tile(r, sg, out + VIDX(d0, y, xg, H, W), plane, xg, d0, ng, dmaxg, mode);
                }
                if (mode == 0)
                    for (int d = dmaxg + 1; d < D; ++d)
                        vol_storeV_partial((floatV)(NAN), out + VIDX(d, y, xg, H, W), ng);
            }
        }
    }
}
#endif /* SGM_PART == 0 || SGM_PART == 2 */

#if SGM_PART == 3
/* Paired sweeps in 16-bit lanes (sgm_paired_q16): sgm_paired's walk, chunks,
 * tiles and launches, with C_r held as shorts, 16 lanes per AVX2 register
 * instead of 8 floats (SGM is bound by instructions on CPUs; BENCHMARKS.md,
 * "SGM in 16-bit lanes").  The host (stages/sgm.py, q16_scale) picks a
 * power of two s with (2 B + 2 P2) s <= 32000 for costs bounded by |C| <= B;
 * each cost is loaded as Q(C) = C s rounded to nearest even, clamped to
 * [-qlim, qlim] (qlim = B s; a NaN cost in a valid cell counts as qlim), the
 * penalties come as integers (P s rounded, as floats).  On every path C_r
 * lies in [C, C + P2] and m + P2 <= (B + 2 P2) s, so nothing overflows; C_r
 * + P1 saturates (levels outside the valid range hold Q_BIG).  A pair's sum
 * fits a short; launch 0 stores it as a float (an integer), launch 1 adds
 * the other pair's and multiplies by qfinal = 1 / (4 s), so every output is
 * exactly (sum of the four integer C_r) / (4 s): float SGM of the costs
 * Q(C) / s with penalties P s rounded / s gives the same bits.
 * Clang constructs (PoCL, Intel's runtime, Oclgrind): unaligned short16
 * access through a 2-byte-aligned typedef (PoCL 3.1 compiles vload16 /
 * vstore16 of shorts to 16 scalar moves) and __builtin_shufflevector. */
#if VW != 16
#error "sgm_paired_q16 needs SGM_VW=16"
#endif
#ifndef SGM_PAIR_CW
#define SGM_PAIR_CW 16
#endif
#define PCW SGM_PAIR_CW
#define Q_BIG ((short)0x7fff)
typedef short16 __attribute__((aligned(2))) q16_u;
#define QLD(p) (*(const q16_u *)(p))
#define QST(v, p) (*(q16_u *)(p) = (v))
#define QLDG(p) (*(const __global q16_u *)(p))
#define QSTG(v, p) (*(__global q16_u *)(p) = (v))
#define QMIN(a, b) select((a), (b), (b) < (a))
#define QMAX(a, b) select((a), (b), (b) > (a))
/* saturating add: PoCL 3.1's add_sat on short16 is five instructions per
 * register, Clang's builtin one (vpaddsw) */
#if defined(__has_builtin)
#if __has_builtin(__builtin_elementwise_add_sat)
#define Q_ADD_SAT(a, b) __builtin_elementwise_add_sat((a), (b))
#endif
#endif
#ifndef Q_ADD_SAT
#define Q_ADD_SAT(a, b) add_sat((a), (b))
#endif
/* q16_transpose and Q_OPAQUE: the asm barriers where the kernel is compiled
 * straight to x86 with AVX (SGM_CPU_PREFETCH, PoCL) */
#if defined(SGM_CPU_PREFETCH) && SGM_CPU_PREFETCH
#define Q16_CPU_ASM 1
#endif
#include "q16.h"

/* Q(v) (above): v s rounded to nearest even by adding 1.5 * 2^23 (|v s| <
 * 2^22; PoCL's convert_*_rte and rint take ~10 instructions per 8
 * lanes), clamped to [-qlim, qlim] as an integer: the bits of v s + 1.5 *
 * 2^23 order like its value, so larger values clamp too; NaN (positive, as
 * INVALID_COST) gives qlim. */
static inline __attribute__((always_inline)) short16 q16_load(const float16 v, const float s, const int qlim)
{
    const short16 q = convert_short16_sat(as_int16(v * s + 12582912.0f) - 0x4B400000), hi = (short16)((short)qlim);
    return QMAX(QMIN(q, hi), -hi); /* not clamp(): Oclgrind 21.10 returns garbage for short16 with short bounds */
}

/* lanes reversed after quantising (the float16 reverse compiled to a chain of
 * extracts and inserts) */
static inline __attribute__((always_inline)) short16 q16_reverse(short16 v)
{
    Q_OPAQUE(v);
    return __builtin_shufflevector(v, v, 15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
}

/* load_tile / load_tile_mirror, each line quantised as it is loaded (q16_load) */
static inline __attribute__((always_inline)) void q16_load_tile(
    short16 *r, __global const vol_t *cost, const int y, const int x0, const int d0, const int n, const int dmax,
    const int H, const int W, const int mirror, const float s, const int qlim)
{
    const size_t plane = (size_t)H * (size_t)W;
    if (SGM_WHOLE_TILES && !mirror && n == 16 && d0 + 15 <= dmax) {
        __global const vol_t *src = cost + VIDX(d0, y, x0, H, W);
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < 16; ++i)
            r[i] = q16_load(VOL_LOAD16(src + i * plane), s, qlim);
        return;
    }
    if (SGM_WHOLE_TILES && mirror && n == 16 && d0 + 15 <= min(dmax, x0)) {
        __global const vol_t *src = cost + VIDX(d0, y, W - 16 + d0 - x0, H, W);
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < 16; ++i)
            r[i] = q16_reverse(q16_load(VOL_LOAD16(src + i * (plane + 1)), s, qlim));
        return;
    }
    float16 rf[16];
    if (mirror)
        load_tile_mirror(rf, cost, y, x0, d0, n, dmax, H, W);
    else
        load_tile(rf, cost, y, x0, d0, n, dmax, H, W);
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < 16; ++i)
        r[i] = q16_load(rf[i], s, qlim);
}

/* vertical_gradients / row_gradients with the flags as shorts (-1 / 0), made
 * once per chunk instead of converted at every use */
static inline __attribute__((always_inline)) void q16_flags(const int *f, short *q, const int t_lo, const int t_end)
{
    for (int t = t_lo; t < t_end; t += 16)
        QST(convert_short16(vload16(0, f + t)), q + t);
}

/* C_r from the cost c, m and C_r(p - r, .) at d - 1, d, d + 1 (as sgm_step_mp2N) */
static inline __attribute__((always_inline)) short16 q16_step(const short16 c, const short16 m, const short16 lo,
                                                               const short16 d, const short16 hi, const short16 p1,
                                                               const short16 mp2)
{
    const short16 best = QMIN(QMIN(d, mp2), Q_ADD_SAT(QMIN(lo, hi), p1));
    return c - m + best;
}

/* vertical_tile in 16-bit lanes (sg: the group's state as shorts; masked as there) */
static inline __attribute__((always_inline)) void q16_vertical_tile(
    const short16 *r, const short *bigv, __global short *sg, const int d0, const int iend, const int vfirst,
    const short16 mv, const short16 p1a, const short16 p1b, const short16 mp2a, const short16 mp2b, short16 *pm1,
    short16 *pd, short16 *newmv, const int16 xs, const int16 valid_x, const int masked)
{
    const short *bq = bigv - d0; /* as in vertical_tile: constant offsets per level */
    __global short *sq = sg + d0 * 16;
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < 16; ++i) {
        const int d = d0 + i;
        if (!masked || i < iend) { /* masked 0: all 16 levels of a row after the first (vertical_tile) */
            short16 val;
            if (masked && vfirst) {
                val = r[i];
            } else {
                const short16 big_r = QLD(bq - i);
                const short16 pn = QLDG(sq + (i + 1) * 16);
                val = q16_step(r[i], mv, *pm1, *pd, pn, select(p1a, p1b, big_r), select(mp2a, mp2b, big_r));
                *pm1 = *pd;
                *pd = pn;
            }
            if (masked)
                val = select((short16)(Q_BIG), val, convert_short16((xs >= (int16)(d)) & valid_x));
            QSTG(val, sq + i * 16);
            *newmv = QMIN(*newmv, val);
        }
    }
}

/* row_chunk in 16-bit lanes (blk, prev, cur as shorts; the penalties integers as floats) */
static inline __attribute__((always_inline)) void q16_row_chunk(
    short *blk, short **prev, short **cur, short *m, const int x0, const int n, const int dir, const int D,
    const int W, __global const float *il, const float tau_so, const float p1_small, const float p1_one,
    const float p1_both, const float p2_small, const float p2_one, const float p2_both,
    const short *big_r_rev, const int base, const int rt, __global const vol_t *pf_cost,
    __global const vol_t *pf_out, const size_t plane, const int dmaxn, const int pf_n,
    const size_t pf_cstep, const int pf_cdmax)
{
    const int16 lane = LANES;
    const int pf_per = dmaxn / n + 1; /* levels prefetched per pixel */
    for (int kk = 0; kk < n; ++kk) {
        const int k = dir > 0 ? kk : n - 1 - kk;
        const int x = x0 + k;
        prefetch_levels(pf_cost, pf_out, plane, kk * pf_per, min(kk * pf_per + pf_per, dmaxn + 1), pf_n, 1,
                        pf_cstep, pf_cdmax);
        const int dmax = min(D - 1, x);
        const int nvec = dmax / 16 + 1;
        const int first = x == (dir > 0 ? 0 : W - 1);
        const int px = x - dir;
        const int big_l = first ? 0 : SGM_LARGE(il[x] - il[px], tau_so);
        float p1_a, p1_b, p2_a, p2_b;
        SGM_BY_D1(p1_small, p1_one, p1_both, big_l, p1_a, p1_b);
        SGM_BY_D1(p2_small, p2_one, p2_both, big_l, p2_a, p2_b);
        const short mm = *m;
        const short16 p1v_a = (short16)((short)p1_a), p1v_b = (short16)((short)p1_b);
        const short16 mp2_a = (short16)((short)(mm + (short)p2_a)), mp2_b = (short16)((short)(mm + (short)p2_b));
        short *pv = *prev, *cv = *cur;
        const short *br = big_r_rev + rt - (x - base); /* lanes d0 .. at br + d0 */
        short16 newm = (short16)(Q_BIG);
        /* as in row_chunk: the first pixel and the last vector in loops of their own */
#define Q16_ROW_STEP(v, FIRST, LAST)                                                                   \
    do {                                                                                                \
        const int d0 = (v) * 16;                                                                        \
        short *bp = blk + k * MAX_DISP + d0;                                                            \
        const short16 c = QLD(bp);                                                                      \
        short16 val;                                                                                    \
        if (FIRST) {                                                                                    \
            val = c;                                                                                    \
        } else {                                                                                        \
            const short16 big_r = QLD(br + d0);                                                         \
            val = q16_step(c, (short16)(mm), QLD(pv + d0), QLD(pv + d0 + 1), QLD(pv + d0 + 2),          \
                           select(p1v_a, p1v_b, big_r), select(mp2_a, mp2_b, big_r));                   \
        }                                                                                               \
        if (LAST)                                                                                       \
            val = select((short16)(Q_BIG), val, convert_short16((int16)(d0) + lane <= (int16)(dmax)));  \
        QST(val, cv + d0 + 1);                                                                          \
        QST(val, bp);                                                                                   \
        newm = QMIN(newm, val);                                                                         \
    } while (0)
        if (first) {
            for (int v = 0; v < nvec - 1; ++v)
                Q16_ROW_STEP(v, 1, 0);
            Q16_ROW_STEP(nvec - 1, 1, 1);
        } else {
            for (int v = 0; v < nvec - 1; ++v)
                Q16_ROW_STEP(v, 0, 0);
            Q16_ROW_STEP(nvec - 1, 0, 1);
        }
#undef Q16_ROW_STEP
        QST((short16)(Q_BIG), cv + nvec * 16 + 1);
        const short8 m8 = QMIN(newm.lo, newm.hi);
        const short4 m4 = QMIN(m8.lo, m8.hi);
        const short2 m2 = QMIN(m4.lo, m4.hi);
        *m = m2.y < m2.x ? m2.y : m2.x;
        *prev = cv;
        *cur = pv;
    }
}

/* write_tile of a pair's sums (r[i] + the group's vertical C_r at add): mode
 * 0 stores them as floats (NaN where x < d), mode 2 adds the stored sums and
 * multiplies by qfinal */
static inline __attribute__((always_inline)) void q16_write_tile(
    const short16 *r, __global const short *add, __global vol_t *dst, const size_t plane, const int x0,
    const int d0, const int n, const int dmax, const int mode, const float qfinal)
{
    const int16 xs = (int16)(x0) + LANES;
    const int whole = SGM_WHOLE_TILES && n == 16 && d0 + 15 <= dmax;
    const int all_valid = whole && x0 >= d0 + 15;
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < 16; ++i) {
        const int d = d0 + i;
        if (d > dmax)
            break;
        const float16 v = convert_float16(r[i] + QLDG(add + d * 16));
        __global vol_t *p = dst + i * plane;
        float16 o;
        if (all_valid) {
            o = mode == 0 ? v : (VOL_LOAD16(p) + v) * qfinal;
        } else {
            const int16 valid = xs >= (int16)(d);
            if (mode == 0) {
                o = select((float16)(INVALID_COST), v, valid);
            } else {
                const float16 old = whole ? VOL_LOAD16(p) : vol_load16_partial(p, 0, n, 0.0f);
                o = select(old, (old + v) * qfinal, valid);
            }
        }
        vol_store16_partial(o, p, whole ? 16 : n);
    }
}

/* sgm_paired in 16-bit lanes: the same arguments, plus qscale (s), qlim and
 * qfinal (above); the penalties are integers (P s rounded); state holds
 * shorts (half of sgm_paired's). */
__kernel __attribute__((vec_type_hint(float16))) void sgm_paired_q16(
    __global const vol_t *cost, __global const float *img_l, __global const float *img_r, __global vol_t *out,
    __global short *state, const int ws, const int D, const int H, const int W, const int h, const int launch_no,
    const float ph1_small, const float ph1_one, const float ph1_both, const float ph2_small, const float ph2_one,
    const float ph2_both, const float pv1_small, const float pv1_one, const float pv1_both, const float pv2_small,
    const float pv2_one, const float pv2_both, const float tau_so, const int outside_large, const int mirror,
    const float qscale, const int qlim, const float qfinal)
{
    const int role = get_global_id(0);
    if (role > 1)
        return;
    const int dir = role == 0 ? 1 : -1;
    const int mode = launch_no == 0 ? 0 : 2;
    const int split = role == 0 ? h : H - h;
    const int j0 = launch_no == 0 ? 0 : split, j1 = launch_no == 0 ? split : H;
    __global short *st = state + (size_t)role * (size_t)(D + 2) * (size_t)ws;
    short blk[PCW * MAX_DISP];
    short buf_a[MAX_DISP + 2 + 16], buf_b[MAX_DISP + 2 + 16];
    int big_r_rev[MAX_DISP + PCW];
    int bigv[MAX_DISP + PCW];
    short qbig_r_rev[MAX_DISP + PCW], qbigv[MAX_DISP + PCW];
    const int16 lane = LANES;
    const size_t plane = (size_t)H * (size_t)W;
    const int nchunks = (W + PCW - 1) / PCW;
    for (int j = j0; j < j1; ++j) {
        const int y = dir > 0 ? j : H - 1 - j;
        const int vfirst = j == 0;
        const int py = vfirst ? y : y - dir;
        __global const float *il = img_l + y * W;
        __global const float *ir = img_r + y * W;
        short *prev = buf_a;
        short *cur = buf_b;
        for (int i = 0; i < MAX_DISP + 2 + 16; ++i) {
            buf_a[i] = Q_BIG;
            buf_b[i] = Q_BIG;
        }
        short m = Q_BIG;
        short16 r[16];
        for (int ci = 0; ci < nchunks; ++ci) {
            const int x0 = (dir > 0 ? ci : nchunks - 1 - ci) * PCW;
            const int n = min(PCW, W - x0);
            const int dmaxc = min(D - 1, x0 + n - 1);
            const int ntiles = dmaxc / 16 + 1;
            if (!vfirst) {
                const int tlo = (MAX_DISP - dmaxc) / 16 * 16;
                vertical_gradients(img_r, W, y, py, x0, tlo, MAX_DISP + PCW, tau_so, bigv);
                q16_flags(bigv, qbigv, tlo, MAX_DISP + PCW);
            }
            for (int gx = 0; gx * 16 < n; ++gx) {
                const int xg = x0 + gx * 16, ng = min(16, n - gx * 16);
                __global short *sg = st + (size_t)(xg / 16) * (D + 2) * 16;
                const int16 xs = (int16)(xg) + lane;
                const int16 valid_x = lane < (int16)(ng);
                const int dmaxg = min(D - 1, xg + ng - 1);
                short16 p1a = (short16)(0), p1b = p1a, mv, pd, pm1, mp2a = p1a, mp2b = p1a;
                if (vfirst) {
                    for (int d = dmaxg + 1; d <= D; ++d)
                        QSTG((short16)(Q_BIG), sg + d * 16);
                    mv = (short16)(Q_BIG);
                    pd = mv;
                    pm1 = mv;
                } else {
                    float16 f1a, f1b, f2a, f2b;
                    vertical_penalties(img_l, W, y, py, xg, ng, tau_so, pv1_small, pv1_one, pv1_both, pv2_small,
                                       pv2_one, pv2_both, &f1a, &f1b, &f2a, &f2b);
                    p1a = convert_short16(f1a);
                    p1b = convert_short16(f1b);
                    mv = QLDG(sg + (D + 1) * 16);
                    pd = QLDG(sg);
                    pm1 = (short16)(Q_BIG);
                    mp2a = mv + convert_short16(f2a);
                    mp2b = mv + convert_short16(f2b);
                }
                short16 newmv = (short16)(Q_BIG);
                for (int g = 0; g < ntiles; ++g) {
                    const int d0 = g * 16;
                    q16_load_tile(r, cost, y, xg, d0, ng, dmaxg, H, W, mirror, qscale, qlim);
                    const int iend = min(16, dmaxg + 1 - d0);
                    if (!vfirst && ng == 16 && xg >= d0 + 15 && iend == 16)
                        q16_vertical_tile(r, qbigv + MAX_DISP + gx * 16, sg, d0, iend, vfirst, mv, p1a, p1b, mp2a,
                                          mp2b, &pm1, &pd, &newmv, xs, valid_x, 0);
                    else
                        q16_vertical_tile(r, qbigv + MAX_DISP + gx * 16, sg, d0, iend, vfirst, mv, p1a, p1b, mp2a,
                                          mp2b, &pm1, &pd, &newmv, xs, valid_x, 1);
                    q16_transpose(r);
                    __attribute__((opencl_unroll_hint))
                    for (int k = 0; k < 16; ++k)
                        QST(r[k], blk + (gx * 16 + k) * MAX_DISP + d0);
                }
                QSTG(newmv, sg + (D + 1) * 16);
            }
            const int base = x0 - ntiles * 16, rt = ntiles * 16 + PCW - 1;
            row_gradients(ir, W, base, ntiles, PCW, dir, tau_so, outside_large, big_r_rev);
            q16_flags(big_r_rev, qbig_r_rev, 0, ntiles * 16 + PCW);
            const int cin = ci + 1 < nchunks ? ci + 1 : ci;
            const int x0n = (dir > 0 ? cin : nchunks - 1 - cin) * PCW;
            const int nn = min(PCW, W - x0n);
            const int dmaxn = min(D - 1, x0n + nn - 1);
            q16_row_chunk(blk, &prev, &cur, &m, x0, n, dir, D, W, il, tau_so, ph1_small, ph1_one, ph1_both,
                          ph2_small, ph2_one, ph2_both, qbig_r_rev, base, rt,
                          mirror ? cost + VIDX(0, y, W - x0n - nn, H, W) : cost + VIDX(0, y, x0n, H, W),
                          out + VIDX(0, y, x0n, H, W), plane, dmaxn, nn, mirror ? plane + 1 : plane,
                          mirror ? min(dmaxn, x0n) : dmaxn);
            for (int gx = 0; gx * 16 < n; ++gx) {
                const int xg = x0 + gx * 16, ng = min(16, n - gx * 16);
                __global short *sg = st + (size_t)(xg / 16) * (D + 2) * 16;
                const int dmaxg = min(D - 1, xg + ng - 1);
                for (int g = 0; g <= dmaxg / 16; ++g) {
                    const int d0 = g * 16;
                    __attribute__((opencl_unroll_hint))
                    for (int k = 0; k < 16; ++k)
                        r[k] = QLD(blk + (gx * 16 + k) * MAX_DISP + d0);
                    q16_transpose(r);
                    q16_write_tile(r, sg, out + VIDX(d0, y, xg, H, W), plane, xg, d0, ng, dmaxg, mode, qfinal);
                }
                if (mode == 0)
                    for (int d = dmaxg + 1; d < D; ++d)
                        vol_store16_partial((float16)(NAN), out + VIDX(d, y, xg, H, W), ng);
            }
        }
    }
}
#endif /* SGM_PART == 3 */
