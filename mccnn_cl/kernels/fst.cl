/* fst.cl - the MC-CNN-fst matching cost after the conv stack, driven by
 * mccnn_cl/stages/fst.py (FstCost).
 *
 * fst_normalise: the conv stack's last map (pixel-major [m][CS], NK maps
 * used) -> L2-normalised features in a planar layout, one plane per map and
 * row:  out[(y NK + k) WP + PADL + x] = f_k(x, y) / sqrt(|f(x, y)|^2 + EPS)
 * (EPS = 1e-5 as in the released code's Normalize2).  The PADL columns
 * left of x = 0 and the columns from x = w to WP - PADL hold 0, so the volume
 * kernel reads whole 16-wide vectors without bounds tests.
 *
 * fst_volume_pairs: the cosine volume  C(d, y, x) = -f_L(x, y) . f_R(x - d, y),
 * NaN where x - d < 0 (each cost is 0, one fma per map in increasing order,
 * negated).  One work-item per 32 consecutive pixels of a row (two float16
 * vectors), walking the disparities in half-blocks of 8; the shifted right
 * vectors are made from two aligned loads by constant shuffles and shared by
 * both 16-pixel vectors (details above the kernel).  Blocks whose pixels are
 * all left of d are not computed: their cells (and every later disparity's)
 * get NaN.  The right vectors of a computed block start at x - d >= -31,
 * hence PADL >= 32.  Every cell of the band's rows is written (valid or NaN).
 * (Measured on PoCL, KITTI volume, same process: 61 ms, against 68 ms for one
 * 16-pixel vector per work-item with the same shuffles and 96 ms with one
 * unaligned load per shifted vector: those two forms were removed.)
 */
#include "common.h"

#ifndef NK
#error "NK (feature maps) must be defined"
#endif
#ifndef CS
#error "CS (channel stride of the conv stack's output) must be defined"
#endif
#ifndef PADL
#error "PADL (zero columns left of x = 0 in the planar features) must be defined"
#endif
#if PADL < 32
#error "PADL must be at least 32"
#endif

#define EPS 1e-5f

/* the 16 floats from offset s of the 32 in A (16) then B (16): literal indices,
 * so the shuffle is one constant permutation (no unaligned, line-splitting load) */
#define SHF(s) __builtin_shufflevector(A, B, s, s + 1, s + 2, s + 3, s + 4, s + 5, s + 6, s + 7, \
                                       s + 8, s + 9, s + 10, s + 11, s + 12, s + 13, s + 14, s + 15)

__kernel void fst_normalise(
    __global const float *feat, /* conv stack output, [hb * w][CS] */
    __global float *out,        /* planar features, [hb][NK][wp] */
    int w,                      /* pixels per row */
    int wp)                     /* row stride of a plane (PADL + w rounded up to 32) */
{
    const int xp = get_global_id(0);            /* 0 .. wp-1 */
    const int y = get_global_id(1);
    if (xp >= wp)
        return;
    const int x = xp - PADL;
    __global float *o = out + (size_t)y * NK * (size_t)wp + xp;
    if (x < 0 || x >= w) {
        for (int k = 0; k < NK; ++k)
            o[(size_t)k * wp] = 0.0f;
        return;
    }
    __global const float *f = feat + ((size_t)y * (size_t)w + (size_t)x) * CS;
    float s = 0.0f;
    for (int k = 0; k < NK; ++k)
        s = fma(f[k], f[k], s);
    const float inv = 1.0f / sqrt(s + EPS);
    for (int k = 0; k < NK; ++k)
        o[(size_t)k * wp] = f[k] * inv;
}

/* fst_volume_pairs: one work-item per 32 pixels of a row: two
 * 16-pixel vectors xa = x0 and xb = x0 + 16.  The right vectors that xa needs
 * at disparity d are the ones xb needs at d + 16, so each half-block e of 8
 * disparities (xa: d = 8e + i, xb: d = 8e + 16 + i, i = 0..7, e >= -2) makes
 * its 8 shifted vectors once (two aligned loads, constant shuffles; which
 * shuffles depends on the parity of e) for 16 FMAs.  Global size
 * (ceil(w / 32), hb). */
#define HALF_BLOCK(S0, S1, S2, S3, S4, S5, S6, S7)                               \
    for (int k = 0; k < NK; ++k) {                                              \
        const size_t o = (size_t)k * (size_t)wp;                                \
        const float16 la = vload16(0, L + o), lb = vload16(0, L + o + 16);     \
        const float16 A = vload16(0, R + o + base), B = vload16(0, R + o + base + 16); \
        float16 v;                                                              \
        v = S0; acc[0] = fma(la, v, acc[0]); acc[8] = fma(lb, v, acc[8]);       \
        v = S1; acc[1] = fma(la, v, acc[1]); acc[9] = fma(lb, v, acc[9]);       \
        v = S2; acc[2] = fma(la, v, acc[2]); acc[10] = fma(lb, v, acc[10]);     \
        v = S3; acc[3] = fma(la, v, acc[3]); acc[11] = fma(lb, v, acc[11]);     \
        v = S4; acc[4] = fma(la, v, acc[4]); acc[12] = fma(lb, v, acc[12]);     \
        v = S5; acc[5] = fma(la, v, acc[5]); acc[13] = fma(lb, v, acc[13]);     \
        v = S6; acc[6] = fma(la, v, acc[6]); acc[14] = fma(lb, v, acc[14]);     \
        v = S7; acc[7] = fma(la, v, acc[7]); acc[15] = fma(lb, v, acc[15]);     \
    }

__kernel void fst_volume_pairs(
    __global const float *fl, __global const float *fr, __global vol_t *cost,
    int h, int w, int y0, int D, int wp)
{
    const int x0 = get_global_id(0) * 32;
    const int yb = get_global_id(1);
    if (x0 >= w)
        return;
    const int na = min(16, w - x0), nb = min(16, w - x0 - 16);   /* nb <= 0: no xb */
    const int y = y0 + yb;
    __global const float *L = fl + (size_t)yb * NK * (size_t)wp + PADL + x0;
    __global const float *R = fr + (size_t)yb * NK * (size_t)wp + PADL + x0;
    const int16 xa = LANES + (int16)(x0), xbv = xa + (int16)(16);
    for (int e = -2; 8 * e < D; ++e) {
        const int da = 8 * e;
        if (x0 + 31 < da + 16) {                 /* both vectors invalid from here on */
            for (int d = max(da, 0); d < D; ++d)
                vol_store16_partial((float16)(INVALID_COST), cost + VIDX(d, y, x0, h, w), na);
            if (nb > 0)
                for (int d = da + 16; d < D; ++d)
                    vol_store16_partial((float16)(INVALID_COST), cost + VIDX(d, y, x0 + 16, h, w), nb);
            return;
        }
        float16 acc[16];
#pragma unroll
        for (int j = 0; j < 16; ++j)
            acc[j] = (float16)(0.0f);
        /* window i starts at right pixel x0 - da - i */
        if ((e & 1) == 0) {                      /* x0 - da is a multiple of 16 */
            const int base = -da - 16;           /* A = R[x0 - da - 16 ..], B = R[x0 - da ..] */
            HALF_BLOCK(B, SHF(15), SHF(14), SHF(13), SHF(12), SHF(11), SHF(10), SHF(9))
        } else {                                 /* x0 - da - 8 is a multiple of 16 */
            const int base = -da - 8;
            HALF_BLOCK(SHF(8), SHF(7), SHF(6), SHF(5), SHF(4), SHF(3), SHF(2), SHF(1))
        }
#pragma unroll
        for (int i = 0; i < 8; ++i) {
            const int d = da + i;
            if (d >= 0 && d < D)
                vol_store16_partial(select(-acc[i], (float16)(INVALID_COST), xa < (int16)(d)),
                                    cost + VIDX(d, y, x0, h, w), na);
            if (nb > 0 && d + 16 >= 0 && d + 16 < D)
                vol_store16_partial(select(-acc[8 + i], (float16)(INVALID_COST), xbv < (int16)(d + 16)),
                                    cost + VIDX(d + 16, y, x0 + 16, h, w), nb);
        }
    }
}

/* fst_volume_pairs8: fst_volume_pairs on 8-wide vectors, for CPUs whose
 * vectors are 8 floats (AVX2: there the 16 float16 accumulators above take 32
 * of the 16 registers and spill).  One work-item per 16 pixels of a row: two
 * 8-pixel vectors xa = x0 and xb = x0 + 8.  The right vectors xa needs at d
 * are the ones xb needs at d + 8, so each quarter-block e of 4 disparities
 * (xa: d = 4e + i, xb: d = 4e + 8 + i, i = 0..3, e >= -2) makes its 4
 * shifted vectors once from two aligned 8-float loads: 8 accumulators, 13
 * registers in all.  Every cost is the same fma chain over the maps as in
 * fst_volume_pairs, so the same bits.  Global size (ceil(w / 16), hb). */
#define SHF8(s) __builtin_shufflevector(A, B, s, s + 1, s + 2, s + 3, s + 4, s + 5, s + 6, s + 7)
#define QUARTER_BLOCK(S0, S1, S2, S3)                                               \
    for (int k = 0; k < NK; ++k) {                                              \
        const size_t o = (size_t)k * (size_t)wp;                                \
        const float8 la = vload8(0, L + o), lb = vload8(0, L + o + 8);         \
        const float8 A = vload8(0, R + o + base), B = vload8(0, R + o + base + 8); \
        float8 v;                                                               \
        v = S0; acc[0] = fma(la, v, acc[0]); acc[4] = fma(lb, v, acc[4]);       \
        v = S1; acc[1] = fma(la, v, acc[1]); acc[5] = fma(lb, v, acc[5]);       \
        v = S2; acc[2] = fma(la, v, acc[2]); acc[6] = fma(lb, v, acc[6]);       \
        v = S3; acc[3] = fma(la, v, acc[3]); acc[7] = fma(lb, v, acc[7]);       \
    }

/* lanes 0 .. n-1 of v to p (n <= 8) */
static inline void vol_store8_partial(const float8 v, __global vol_t *p, const int n)
{
#if VOL_HALF
    float t[8];
    vstore8(v, 0, t);
    for (int i = 0; i < n; ++i)
        vstore_half(t[i], i, p);
#else
    if (n == 8) {
        vstore8(v, 0, p);
        return;
    }
    float t[8];
    vstore8(v, 0, t);
    for (int i = 0; i < n; ++i)
        p[i] = t[i];
#endif
}

__kernel void fst_volume_pairs8(
    __global const float *fl, __global const float *fr, __global vol_t *cost,
    int h, int w, int y0, int D, int wp)
{
    const int x0 = get_global_id(0) * 16;
    const int yb = get_global_id(1);
    if (x0 >= w)
        return;
    const int na = min(8, w - x0), nb = min(8, w - x0 - 8);   /* nb <= 0: no xb */
    const int y = y0 + yb;
    __global const float *L = fl + (size_t)yb * NK * (size_t)wp + PADL + x0;
    __global const float *R = fr + (size_t)yb * NK * (size_t)wp + PADL + x0;
    const int8 xa = (int8)(0, 1, 2, 3, 4, 5, 6, 7) + (int8)(x0), xbv = xa + (int8)(8);
    for (int e = -2; 4 * e < D; ++e) {
        const int da = 4 * e;
        if (x0 + 15 < da + 8) {                  /* both vectors invalid from here on */
            for (int d = max(da, 0); d < D; ++d)
                vol_store8_partial((float8)(INVALID_COST), cost + VIDX(d, y, x0, h, w), na);
            if (nb > 0)
                for (int d = max(da + 8, 0); d < D; ++d)
                    vol_store8_partial((float8)(INVALID_COST), cost + VIDX(d, y, x0 + 8, h, w), nb);
            return;
        }
        float8 acc[8];
#pragma unroll
        for (int j = 0; j < 8; ++j)
            acc[j] = (float8)(0.0f);
        /* window i starts at right pixel x0 - da - i */
        if ((e & 1) == 0) {                      /* x0 - da is a multiple of 8 */
            const int base = -da - 8;            /* A = R[x0 - da - 8 ..], B = R[x0 - da ..] */
            QUARTER_BLOCK(B, SHF8(7), SHF8(6), SHF8(5))
        } else {                                 /* x0 - da - 4 is a multiple of 8 */
            const int base = -da - 4;
            QUARTER_BLOCK(SHF8(4), SHF8(3), SHF8(2), SHF8(1))
        }
#pragma unroll
        for (int i = 0; i < 4; ++i) {
            const int d = da + i;
            if (d >= 0 && d < D)
                vol_store8_partial(select(-acc[i], (float8)(INVALID_COST), xa < (int8)(d)),
                                   cost + VIDX(d, y, x0, h, w), na);
            if (nb > 0 && d + 8 >= 0 && d + 8 < D)
                vol_store8_partial(select(-acc[4 + i], (float8)(INVALID_COST), xbv < (int8)(d + 8)),
                                   cost + VIDX(d + 8, y, x0 + 8, h, w), nb);
        }
    }
}
