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
 *  - Volume storage: float32, or with -D VOL_HALF=1 IEEE half precision
 *    (storage only: values are converted to float on load and rounded to
 *    nearest even on store with vload_half / vstore_half, which need no
 *    cl_khr_fp16; all arithmetic stays float).  Kernels declare volumes as
 *    `vol_t *` and access them through VOL_GET / VOL_SET / vol_load16_partial /
 *    vol_store16_partial.
 */
#ifndef MCCNN_COMMON_H
#define MCCNN_COMMON_H

#define INVALID_COST NAN

/* Lane numbers 0 .. 15 of a 16-wide vector (x offsets of a 16-pixel chunk). */
#define LANES ((int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))

/* Index of cell (d, y, x) in a D x H x W volume. */
#define VIDX(d, y, x, H, W) (((size_t)(d) * (size_t)(H) + (size_t)(y)) * (size_t)(W) + (size_t)(x))

/* Partial N-wide vector access at the end of a row (N = 16 or 8).
 * loadN_partial gives lanes i = 0..N-1 = p[first + i]; lanes with i >= n or
 * first + i < 0 are not read and get `fill`.  storeN_partial writes lanes
 * 0 .. n-1 (n <= N). */
#define MCCNN_PARTIAL_ACCESS(N)                                                                          \
    static inline float##N load##N##_partial(__global const float *p, const int first, const int n,     \
                                             const float fill)                                          \
    {                                                                                                   \
        if (n == N && first >= 0)                                                                       \
            return vload##N(0, p + first);                                                              \
        float t[N];                                                                                     \
        for (int i = 0; i < N; ++i)                                                                     \
            t[i] = (i < n && first + i >= 0) ? p[first + i] : fill;                                     \
        return vload##N(0, t);                                                                          \
    }                                                                                                   \
    static inline void store##N##_partial(const float##N v, __global float *p, const int n)             \
    {                                                                                                   \
        if (n == N) {                                                                                   \
            vstore##N(v, 0, p);                                                                         \
            return;                                                                                     \
        }                                                                                               \
        float t[N];                                                                                     \
        vstore##N(v, 0, t);                                                                             \
        for (int i = 0; i < n; ++i)                                                                     \
            p[i] = t[i];                                                                                \
    }
MCCNN_PARTIAL_ACCESS(16)
MCCNN_PARTIAL_ACCESS(8)

/* Lane numbers 0 .. 7 of an 8-wide vector (sgm.cl built with SGM_VW 8). */
#define LANES8 ((int8)(0, 1, 2, 3, 4, 5, 6, 7))

/* Transpose of an N x N block held as N floatN rows (N = 16: in
 * log2 N stages): afterwards r[i].sj is the former r[j].si.  Each stage
 * splits every pair of rows into their even and odd lanes (rows 0..N/2-1
 * take the even ones, the others the odd ones), which rotates the index
 * (row, lane) right by one bit; log2 N stages swap row and lane.  Pure
 * register shuffles (no private-memory round trip); sgm.cl's horizontal
 * paths (SGM_VW 16) and fst.cl's fst_normalise16; transpose8 below for
 * SGM_VW 8 (the 16 x 16 form holds 32 registers of 8 floats). */
#define MCCNN_TRANSPOSE(N, STAGES)                                                    \
    static inline __attribute__((always_inline)) void transpose##N(float##N *r)      \
    {                                                                                 \
        __attribute__((opencl_unroll_hint))                                           \
        for (int s = 0; s < STAGES; ++s) {                                            \
            float##N t[N];                                                            \
            __attribute__((opencl_unroll_hint))                                       \
            for (int i = 0; i < N / 2; ++i) {                                         \
                t[i] = (float##N)(r[2 * i].even, r[2 * i + 1].even);                  \
                t[i + N / 2] = (float##N)(r[2 * i].odd, r[2 * i + 1].odd);            \
            }                                                                         \
            __attribute__((opencl_unroll_hint))                                       \
            for (int i = 0; i < N; ++i)                                               \
                r[i] = t[i];                                                          \
        }                                                                             \
    }
MCCNN_TRANSPOSE(16, 4)

/* transpose8: the 8 x 8 transpose (rows of 8 floats; SGM_VW 8) in the
 * three steps of the usual AVX form: interleave pairs of rows within each
 * 128-bit half (unpcklps / unpckhps), pairs of those pairs (unpcklpd /
 * unpckhpd), then the halves across (vperm2f128): 24 one-instruction
 * shuffles.  The even/odd stages of MCCNN_TRANSPOSE compiled to 128-bit
 * halves, extracts and spills on AVX2.  Where the kernel is compiled
 * straight to x86 with AVX (PoCL, SGM_CPU_PREFETCH 1), T8_OPAQUE hides each
 * step's vectors from the optimiser (an empty asm statement; "x" names a
 * ymm register), which otherwise merges the steps with each other and with
 * the loads before them into longer shuffle chains (the paired SGM sweeps
 * on a Zen 3 with AVX2: without it no faster than the even/odd form, with
 * it ~10 % faster).
 * Elsewhere nothing. */
#if defined(SGM_CPU_PREFETCH) && (defined(__x86_64__) || defined(__i386__)) && defined(__AVX__)
#if SGM_CPU_PREFETCH
#define T8_OPAQUE(v) __asm__("" : "+x"(v))
#endif
#endif
#ifndef T8_OPAQUE
#define T8_OPAQUE(v) ((void)0)
#endif
static inline __attribute__((always_inline)) void transpose8(float8 *r)
{
    const uint8 lo = (uint8)(0, 8, 1, 9, 4, 12, 5, 13), hi = (uint8)(2, 10, 3, 11, 6, 14, 7, 15);
    const uint8 s44 = (uint8)(0, 1, 8, 9, 4, 5, 12, 13), sEE = (uint8)(2, 3, 10, 11, 6, 7, 14, 15);
    const uint8 p20 = (uint8)(0, 1, 2, 3, 8, 9, 10, 11), p31 = (uint8)(4, 5, 6, 7, 12, 13, 14, 15);
    float8 t[8], s[8];
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < 8; ++i)
        T8_OPAQUE(r[i]);
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < 4; ++i) { /* t[2i], t[2i + 1]: rows 2i and 2i + 1 interleaved */
        t[2 * i] = shuffle2(r[2 * i], r[2 * i + 1], lo);
        t[2 * i + 1] = shuffle2(r[2 * i], r[2 * i + 1], hi);
        T8_OPAQUE(t[2 * i]);
        T8_OPAQUE(t[2 * i + 1]);
    }
    __attribute__((opencl_unroll_hint))
    for (int h = 0; h < 2; ++h) { /* s[4h + j]: lanes j and j + 4 of rows 4h .. 4h + 3 */
        s[4 * h] = shuffle2(t[4 * h], t[4 * h + 2], s44);
        s[4 * h + 1] = shuffle2(t[4 * h], t[4 * h + 2], sEE);
        s[4 * h + 2] = shuffle2(t[4 * h + 1], t[4 * h + 3], s44);
        s[4 * h + 3] = shuffle2(t[4 * h + 1], t[4 * h + 3], sEE);
        T8_OPAQUE(s[4 * h]);
        T8_OPAQUE(s[4 * h + 1]);
        T8_OPAQUE(s[4 * h + 2]);
        T8_OPAQUE(s[4 * h + 3]);
    }
    __attribute__((opencl_unroll_hint))
    for (int j = 0; j < 4; ++j) {
        r[j] = shuffle2(s[j], s[j + 4], p20);
        r[j + 4] = shuffle2(s[j], s[j + 4], p31);
    }
}

/* Volume element type and access (see the header comment):
 *   VOL_GET(p, i), VOL_SET(p, i, v)     one element, as float
 *   VOL_LOAD16(p), VOL_LOAD8(p)         16 or 8 consecutive elements
 *   vol_loadN_partial, vol_storeN_partial   as loadN_partial / storeN_partial */
#ifndef VOL_HALF
#define VOL_HALF 0
#endif
#if VOL_HALF
#define vol_t half
#define VOL_GET(p, i) vload_half((size_t)(i), (p))
#define VOL_SET(p, i, v) vstore_half((v), (size_t)(i), (p))
/* Element by element with scalar vload_half / vstore_half, not the 16-wide
 * forms: PoCL 3.1 (LLVM 15) miscompiles vstore_half16 inside
 * cbca_fused_short (a segfault at row strides that are not a multiple of 8
 * halves), though the same call is correct in a small kernel and on Intel's
 * runtime and Oclgrind.  Loads use the scalar form too (the half-precision
 * timings in docs/method.md were measured so).  The values are the same:
 * round to nearest even on store. */
#define MCCNN_VOL_HALF_ACCESS(N)                                                                      \
    static inline float##N vol_load##N##_partial(__global const half *p, const int first, const int n,  \
                                                 const float fill)                                      \
    {                                                                                                   \
        float t[N];                                                                                     \
        for (int i = 0; i < N; ++i)                                                                     \
            t[i] = (i < n && first + i >= 0) ? vload_half(first + i, p) : fill;                         \
        return vload##N(0, t);                                                                          \
    }                                                                                                   \
    static inline void vol_store##N##_partial(const float##N v, __global half *p, const int n)          \
    {                                                                                                   \
        float t[N];                                                                                     \
        vstore##N(v, 0, t);                                                                             \
        for (int i = 0; i < n; ++i)                                                                     \
            vstore_half(t[i], i, p);                                                                    \
    }
MCCNN_VOL_HALF_ACCESS(16)
MCCNN_VOL_HALF_ACCESS(8)
#define VOL_LOAD16(p) vol_load16_partial((p), 0, 16, 0.0f)
#define VOL_LOAD8(p) vol_load8_partial((p), 0, 8, 0.0f)
#else
#define vol_t float
#define VOL_GET(p, i) ((p)[i])
#define VOL_SET(p, i, v) ((p)[i] = (v))
#define VOL_LOAD16(p) vload16(0, (p))
#define VOL_LOAD8(p) vload8(0, (p))
#define vol_load16_partial load16_partial
#define vol_store16_partial store16_partial
#define vol_load8_partial load8_partial
#define vol_store8_partial store8_partial
#endif

#endif /* MCCNN_COMMON_H */
