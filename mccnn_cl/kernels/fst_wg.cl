/* fst_wg.cl - MC-CNN-fst's cosine volume laid out for GPUs, driven by
 * mccnn_cl/stages/fst.py (FstCost, the "workgroup" path):
 *
 *   C(d, y, x) = -f_L(x, y) . f_R(x - d, y),   NaN where x - d < 0,
 *
 * on the planar, L2-normalised features that fst.cl's fst_normalise writes
 * ([hb][NK][wp], column x of plane k at PADL + x).
 *
 * fst_volume_wg: one work-group per (tile of TX columns, chunk of TD
 * disparities, row of the band).  The cells of the tile, x0 .. x0 + TX - 1
 * and d0 .. d0 + TD - 1, compare the left features of the TX columns with
 * the right features of the TX + TD - 1 columns x0 - d0 - (TD - 1) ..
 * x0 - d0 + TX - 1.  For each slice of TK consecutive maps the group stages
 * both in local memory (TK x TX and TK x (TX + TD - 1) floats), then every
 * work-item accumulates its RX x RD register block of cells from there; two
 * barriers per slice (after the blocks are filled, and after every
 * work-item has read them).  So each right feature is read from global
 * memory once per group, not once per disparity, and each left one once per
 * chunk of TD disparities.  Right columns outside [0, w) are staged as 0
 * (they only meet invalid cells, x - d < 0).
 *
 * Work-items: WX = TX / RX along the columns (local dimension 0), WD = TD /
 * RD along the disparities (dimension 1); work-item (ix, id) owns columns
 * x0 + ix + i WX (i < RX) and disparities d0 + id + j WD (j < RD), so
 * neighbouring work-items store neighbouring cells of a volume row and read
 * neighbouring words of the local blocks.  Groups whose TX columns all lie
 * left of d0 load and sum nothing (but pass the barriers) and store NaN.
 * Every cell of the band's rows is written (valid or NaN).
 *
 * Bit-identity with fst_volume / fst_volume_pairs: each cost is 0, then one
 * fma per map in increasing k, then negated, as those kernels form it on
 * their vector lanes, so all forms agree bit for bit.
 *
 * Defines: NK, PADL (as fst.cl), TX, TD (tile), TK (maps per slice), RX, RD
 * (register block; TX % RX == TD % RD == 0), VOL_HALF [0] (common.h).
 * Global size (ceil(w / TX) WX, ceil(D / TD) WD, hb), local (WX, WD, 1).
 */
#include "common.h"

#ifndef NK
#error "NK (feature maps) must be defined"
#endif
#ifndef PADL
#error "PADL (zero columns left of x = 0 in the planar features) must be defined"
#endif
#if !defined(TX) || !defined(TD) || !defined(TK) || !defined(RX) || !defined(RD)
#error "TX, TD (tile), TK (maps per slice) and RX, RD (register block) must be defined"
#endif
#if TX % RX != 0 || TD % RD != 0
#error "TX must be a multiple of RX and TD a multiple of RD"
#endif

#define WX (TX / RX)             /* work-items along the columns */
#define WD (TD / RD)             /* work-items along the disparities */
#define SPAN (TX + TD - 1)       /* right columns a tile needs */

__kernel void fst_volume_wg(
    __global const float *fl,   /* left planar features, [hb][NK][wp] */
    __global const float *fr,   /* right planar features, [hb][NK][wp] */
    __global vol_t *cost,       /* cost volume, [D][h][w] */
    int h,                      /* rows of the volume */
    int w,                      /* columns */
    int y0,                     /* volume row of the band's first row */
    int D,                      /* disparities 0 .. D-1 */
    int wp)                     /* plane row stride */
{
    __local float l_blk[TK * TX];     /* l_blk[kk * TX + xx] = f_L,k0+kk(x0 + xx) */
    __local float r_blk[TK * SPAN];   /* r_blk[kk * SPAN + s] = f_R,k0+kk(x0 - d0 - (TD - 1) + s) */

    const int ix = get_local_id(0);
    const int id = get_local_id(1);
    const int lid = id * WX + ix;
    const int nwi = WX * WD;
    const int x0 = (int)get_group_id(0) * TX;
    const int d0 = (int)get_group_id(1) * TD;
    const int yb = (int)get_group_id(2);
    const int y = y0 + yb;

    /* every cell of the tile invalid: no loads, no sums; the group still
     * passes the barriers (PoCL 3.1 computes wrong values and corrupts its
     * heap when the group returns here instead, uniform as that would be) */
    const bool skip = x0 + TX - 1 < d0;
    const int xr0 = x0 - d0 - (TD - 1);  /* right column of r_blk's slot 0 */
    __global const float *L = fl + (size_t)yb * NK * (size_t)wp + PADL;
    __global const float *R = fr + (size_t)yb * NK * (size_t)wp + PADL;

    float acc[RX][RD];
#pragma unroll
    for (int i = 0; i < RX; ++i)
#pragma unroll
        for (int j = 0; j < RD; ++j)
            acc[i][j] = 0.0f;

    for (int k0 = 0; k0 < NK; k0 += TK) {
        if (k0 > 0)
            barrier(CLK_LOCAL_MEM_FENCE);   /* the previous slice's blocks read */
        for (int e = skip ? TK * TX : lid; e < TK * TX; e += nwi) {
            const int kk = e / TX;
            const int x = x0 + (e - kk * TX);
            const int k = k0 + kk;
            l_blk[e] = (k < NK && x < w) ? L[(size_t)k * wp + x] : 0.0f;
        }
        for (int e = skip ? TK * SPAN : lid; e < TK * SPAN; e += nwi) {
            const int kk = e / SPAN;
            const int xr = xr0 + (e - kk * SPAN);
            const int k = k0 + kk;
            r_blk[e] = (k < NK && xr >= 0 && xr < w) ? R[(size_t)k * wp + xr] : 0.0f;
        }
        barrier(CLK_LOCAL_MEM_FENCE);       /* the blocks are filled */
        const int kn = skip ? 0 : min(TK, NK - k0);
        for (int kk = 0; kk < kn; ++kk) {
            __local const float *lk = l_blk + kk * TX + ix;
            /* cell (x0 + xx, d0 + dd) meets right slot xx - dd + TD - 1 */
            __local const float *rk = r_blk + kk * SPAN + ix - id + (TD - 1);
            float l[RX];
#pragma unroll
            for (int i = 0; i < RX; ++i)
                l[i] = lk[i * WX];
#pragma unroll
            for (int j = 0; j < RD; ++j)
#pragma unroll
                for (int i = 0; i < RX; ++i)
                    acc[i][j] = fma(l[i], rk[i * WX - j * WD], acc[i][j]);
        }
    }

#pragma unroll
    for (int j = 0; j < RD; ++j) {
        const int d = d0 + id + j * WD;
#pragma unroll
        for (int i = 0; i < RX; ++i) {
            const int x = x0 + ix + i * WX;
            if (x < w && d < D)
                VOL_SET(cost, VIDX(d, y, x, h, w), x < d ? INVALID_COST : -acc[i][j]);
        }
    }
}
