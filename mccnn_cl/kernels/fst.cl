/* fst.cl - the MC-CNN-fst matching cost after the conv stack, driven by
 * mccnn_cl/stages/fst.py (FstCost).
 *
 * fst_normalise: the conv stack's last map (pixel-major [m][CS], NK maps
 * used) -> L2-normalised features in a planar layout, one plane per map and
 * row:  out[(y NK + k) WP + PADL + x] = f_k(x, y) / sqrt(|f(x, y)|^2 + EPS)
 * (EPS = 1e-5 as in the released code's Normalize2).  The PADL columns
 * left of x = 0 and the columns from x = w to WP - PADL hold 0, so the volume
 * kernel reads whole 16-wide vectors without bounds tests.  Two forms: one
 * pixel per work-item (beside the GPU-shaped volume, fst_wg.cl) and
 * fst_normalise16, 16 pixels per work-item (beside fst_volume_pairs).
 *
 * fst_volume_pairs: the cosine volume  C(d, y, x) = -f_L(x, y) . f_R(x - d, y),
 * NaN where x - d < 0 (each cost is 0, one fma per map in increasing order,
 * negated).  One work-item per 2 FST_VW consecutive pixels of a row (two
 * vectors of FST_VW = 16 or 8 floats), walking the disparities in blocks of
 * FST_VW / 2; the shifted right vectors are made from two aligned loads by
 * constant shuffles and shared by both vectors (details above the kernel).  Blocks whose pixels are
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
#if PADL % 16
#error "PADL must be a multiple of 16 (fst_normalise16's blocks)"
#endif

#define EPS 1e-5f


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

/* fst_normalise16: fst_normalise for 16 consecutive columns xp0 .. xp0 + 15
 * of a planar row per work-item (global size (wp / 16, hb)), the CPU-shaped
 * form: the per-pixel kernel above reads each pixel's maps CS floats apart
 * across its work-items (a gather per map when a CPU compiler vectorises over
 * work-items; 30 ms per KITTI image on a 2-core Zen 3).  Here the 16 pixels'
 * maps are loaded in blocks of 16 (one vector per pixel) and transposed in
 * registers (transpose16, common.h), so that the sums of squares and the
 * stores run on 16 pixels at once, one aligned vector per plane (19-26 ms
 * for that image, same machine).  Every lane
 * does the same operations as one work-item of fst_normalise (the fma chain
 * over k = 0 .. NK - 1 in order, the same square root and division), so
 * the features are the same bits.  The transposed blocks wait in private
 * memory (16 NK floats) between the sums and the stores (reading the maps
 * again instead measured the same). */
#define NB ((NK + 15) / 16) /* blocks of 16 maps */
static inline __attribute__((always_inline)) void fst_map_block(
    __global const float *f, const int kb, const int nv, float16 *r)
{
    /* r[j] = maps kb .. kb + 15 of pixel j (0 for pixels j >= nv and maps >= NK), transposed:
     * afterwards r[j] = map kb + j of the 16 pixels */
    __attribute__((opencl_unroll_hint))
    for (int j = 0; j < 16; ++j) {
        if (j < nv)
            r[j] = kb + 16 <= NK ? vload16(0, f + (size_t)j * CS + kb)
                                 : load16_partial(f + (size_t)j * CS + kb, 0, NK - kb, 0.0f);
        else
            r[j] = (float16)(0.0f);
    }
    transpose16(r);
}

__kernel void fst_normalise16(
    __global const float *feat, /* conv stack output, [hb * w][CS] */
    __global float *out,        /* planar features, [hb][NK][wp] */
    int w,                      /* pixels per row */
    int wp)                     /* row stride of a plane (PADL + w rounded up to 32) */
{
    const int xp0 = get_global_id(0) * 16;
    const int y = get_global_id(1);
    if (xp0 >= wp)
        return;
    const int x0 = xp0 - PADL; /* PADL is a multiple of 16: a block is all padding or starts at x0 >= 0 */
    __global float *o = out + (size_t)y * NK * (size_t)wp + xp0;
    const int nv = x0 < 0 ? 0 : clamp(w - x0, 0, 16); /* pixels of the row in this block */
    if (nv == 0) {
        for (int k = 0; k < NK; ++k)
            vstore16((float16)(0.0f), 0, o + (size_t)k * wp);
        return;
    }
    __global const float *f = feat + ((size_t)y * (size_t)w + (size_t)x0) * CS;
    float16 r[16 * NB];
    float16 s = (float16)(0.0f);
    for (int b = 0; b < NB; ++b) {
        fst_map_block(f, 16 * b, nv, r + 16 * b);
        __attribute__((opencl_unroll_hint))
        for (int j = 0; j < 16; ++j)
            if (16 * b + j < NK)
                s = fma(r[16 * b + j], r[16 * b + j], s);
    }
    const float16 inv = (float16)(1.0f) / sqrt(s + (float16)(EPS));
    const int16 in_row = LANES < (int16)(nv); /* columns x >= w hold 0 */
    for (int k = 0; k < NK; ++k)
        vstore16(select((float16)(0.0f), r[k] * inv, in_row), 0, o + (size_t)k * wp);
}
#undef NB

/* fst_volume_pairs: one work-item per 2 FST_VW pixels of a row: two FST_VW-
 * pixel vectors xa = x0 and xb = x0 + FST_VW.  The right vectors that xa needs
 * at disparity d are the ones xb needs at d + FST_VW, so each block e of
 * BD = FST_VW / 2 disparities (xa: d = BD e + i, xb: d = BD e + FST_VW + i,
 * i = 0 .. BD - 1, e >= -2) makes its BD shifted vectors once for 2 BD FMAs.
 * FST_VW 16 (the default): 16 float16 accumulators, which fit AVX-512's 32
 * registers, the shifted vectors loaded unaligned from the right row; FST_VW
 * 8, for CPUs whose vectors hold 8 floats (AVX2, where the 16-wide form
 * spills): 8 float8 accumulators, the shifted vectors made from two aligned
 * loads by constant shuffles (which shuffles depends on the parity of e).
 * Each width has the faster form, measured on the KITTI volume (general-fst's
 * 64 maps, one process, best of 3 in 5 rounds, Zen 4): 16 wide, unaligned
 * loads 108-118 ms against 122-133 for shuffles with AVX-512 code, 171-176
 * against 184-198 with AVX2 code (POCL_KERNELLIB_NAME=avx2); 8 wide with AVX2
 * code, shuffles 151-155 ms against 163-168 for unaligned loads (split
 * lines).  Both widths and forms compute every cost by the same fma chain
 * over the maps, so the same bits.  Global size (ceil(w / (2 FST_VW)), hb). */
#ifndef FST_VW
#define FST_VW 16
#endif
#define BD (FST_VW / 2)
#if FST_VW == 16
#define FV float16
#define IV int16
#define FV_LOAD vload16
#define FV_LANES LANES
#define FV_STORE vol_store16_partial
/* the 16 floats from offset s of the 32 in A (16) then B (16), as one unaligned
 * load of the right row (faster than a two-source permutation here: header) */
#define SHF(s) FV_LOAD(0, R + o + base + (s))
/* window i of block e starts at right pixel x0 - BD e - i: for even e at B
 * (x0 - BD e a multiple of FST_VW), then one float further left per i */
#define BLOCK_EVEN FMA2(0, B) FMA2(1, SHF(15)) FMA2(2, SHF(14)) FMA2(3, SHF(13)) \
                   FMA2(4, SHF(12)) FMA2(5, SHF(11)) FMA2(6, SHF(10)) FMA2(7, SHF(9))
#define BLOCK_ODD  FMA2(0, SHF(8)) FMA2(1, SHF(7)) FMA2(2, SHF(6)) FMA2(3, SHF(5)) \
                   FMA2(4, SHF(4)) FMA2(5, SHF(3)) FMA2(6, SHF(2)) FMA2(7, SHF(1))
#elif FST_VW == 8
#define FV float8
#define IV int8
#define FV_LOAD vload8
#define FV_LANES LANES8
#define FV_STORE vol_store8_partial
#define SHF(s) __builtin_shufflevector(A, B, s, s + 1, s + 2, s + 3, s + 4, s + 5, s + 6, s + 7)
#define BLOCK_EVEN FMA2(0, B) FMA2(1, SHF(7)) FMA2(2, SHF(6)) FMA2(3, SHF(5))
#define BLOCK_ODD  FMA2(0, SHF(4)) FMA2(1, SHF(3)) FMA2(2, SHF(2)) FMA2(3, SHF(1))
#else
#error "FST_VW must be 16 or 8"
#endif
#define FMA2(j, S) v = (S); acc[j] = fma(la, v, acc[j]); acc[BD + j] = fma(lb, v, acc[BD + j]);
#define BLOCK(BODY)                                                             \
    for (int k = 0; k < NK; ++k) {                                              \
        const size_t o = (size_t)k * (size_t)wp;                                \
        const FV la = FV_LOAD(0, L + o), lb = FV_LOAD(0, L + o + FST_VW);       \
        const FV A = FV_LOAD(0, R + o + base), B = FV_LOAD(0, R + o + base + FST_VW); \
        FV v;                                                                   \
        BODY                                                                    \
    }

__kernel void fst_volume_pairs(
    __global const float *fl, __global const float *fr, __global vol_t *cost,
    int h, int w, int y0, int D, int wp)
{
    const int x0 = get_global_id(0) * (2 * FST_VW);
    const int yb = get_global_id(1);
    if (x0 >= w)
        return;
    const int na = min(FST_VW, w - x0), nb = min(FST_VW, w - x0 - FST_VW);   /* nb <= 0: no xb */
    const int y = y0 + yb;
    __global const float *L = fl + (size_t)yb * NK * (size_t)wp + PADL + x0;
    __global const float *R = fr + (size_t)yb * NK * (size_t)wp + PADL + x0;
    const IV xa = FV_LANES + (IV)(x0), xbv = xa + (IV)(FST_VW);
    for (int e = -2; BD * e < D; ++e) {
        const int da = BD * e;
        if (x0 + 2 * FST_VW - 1 < da + FST_VW) { /* both vectors invalid from here on */
            for (int d = max(da, 0); d < D; ++d)
                FV_STORE((FV)(INVALID_COST), cost + VIDX(d, y, x0, h, w), na);
            if (nb > 0)
                for (int d = max(da + FST_VW, 0); d < D; ++d)
                    FV_STORE((FV)(INVALID_COST), cost + VIDX(d, y, x0 + FST_VW, h, w), nb);
            return;
        }
        FV acc[2 * BD];
#pragma unroll
        for (int j = 0; j < 2 * BD; ++j)
            acc[j] = (FV)(0.0f);
        if ((e & 1) == 0) {                      /* x0 - da is a multiple of FST_VW */
            const int base = -da - FST_VW;       /* A = R[x0 - da - FST_VW ..], B = R[x0 - da ..] */
            BLOCK(BLOCK_EVEN)
        } else {                                 /* x0 - da - BD is a multiple of FST_VW */
            const int base = -da - BD;           /* A = R[x0 - da - BD ..], B = R[x0 - da - BD + FST_VW ..] */
            BLOCK(BLOCK_ODD)
        }
#pragma unroll
        for (int i = 0; i < BD; ++i) {
            const int d = da + i;
            if (d >= 0 && d < D)
                FV_STORE(select(-acc[i], (FV)(INVALID_COST), xa < (IV)(d)), cost + VIDX(d, y, x0, h, w), na);
            if (nb > 0 && d + FST_VW >= 0 && d + FST_VW < D)
                FV_STORE(select(-acc[BD + i], (FV)(INVALID_COST), xbv < (IV)(d + FST_VW)),
                         cost + VIDX(d + FST_VW, y, x0 + FST_VW, h, w), nb);
        }
    }
}
