/* network_conv_wg.cl - the per-pixel layers of every network laid out for
 * GPUs: the GEMM of network_conv.cl (the tied conv stack, and the L4 split
 * of the fc networks as a 1 x 1 convolution) with local-memory tiles.
 * Driven by mccnn_cl/stages/features.py (ConvStack, the "local tiles" path).
 *
 * The same product as network_conv.cl,
 *
 *   out[m][n] = act(bias[n] + sum_k A[m][k] * Wt[k][n]),
 *   A[m][k] = in[(y + ky) * w_in + x + kx][c],  k = (ky * KS + kx) * CIN + c,
 *
 * m = y * w_out + x the output pixel, K = KS * KS * CIN, act = ReLU when RELU
 * is 1.  A work-group computes a TM x TN tile of outputs (TM pixels, TN
 * channels): for each slice of TK consecutive k it stages A's TM x TK block
 * (gathered from the input map: im2col on the fly) and Wt's TK x TN block in
 * local memory, then every work-item accumulates its RM x RN register block
 * from there; two barriers per slice (after the blocks are filled, and after
 * every work-item has read them, before the next slice overwrites them).
 * Each input value and weight a group needs is read from global memory once
 * per group instead of once per work-item that uses it.
 *
 * Work-items: WN = TN / RN along the channels (local dimension 0), WM = TM /
 * RM along the pixels (dimension 1).  Work-item (tn, tm) owns channels
 * n0 + tn + j WN (j < RN) and pixels m0 + tm + i WM (i < RM): neighbouring
 * work-items store neighbouring channels of a pixel (the output is
 * channel-last) and read neighbouring words of the local blocks.  Partial
 * tiles: pixels >= M and channels >= NP are staged as 0 and never stored;
 * the last slice runs only its K - k0 real terms.
 *
 * Bit-identity with network_conv: each output is bias[n], then one fma per
 * k in increasing k, then the ReLU, exactly as network_conv forms it (the
 * register and local tiles change where the operands come from, not the
 * operations), so the two kernels agree bit for bit.
 *
 * Defines: KS, CIN, CS, NP, RELU as network_conv.cl; TM, TN, TK (the tile and
 * the slice), RM, RN (the register block; TM % RM == TN % RN == 0).
 * Local memory: TK (TM + TN) floats and TM longs (the pixels' input offsets).
 * Global size (ceil(NP / TN) WN, ceil(M / TM) WM), local size (WN, WM).
 */
#include "common.h"

#ifndef KS
#error "KS (kernel size) must be defined"
#endif
#ifndef CIN
#error "CIN (input channels read) must be defined"
#endif
#ifndef CS
#error "CS (input channel stride) must be defined"
#endif
#ifndef NP
#error "NP (padded output channels) must be defined"
#endif
#ifndef RELU
#error "RELU (0 or 1) must be defined"
#endif
#if !defined(TM) || !defined(TN) || !defined(TK) || !defined(RM) || !defined(RN)
#error "TM, TN, TK (tile, slice) and RM, RN (register block) must be defined"
#endif
#if TM % RM != 0 || TN % RN != 0
#error "TM must be a multiple of RM and TN a multiple of RN"
#endif

#define KTOT (KS * KS * CIN)   /* the GEMM's inner dimension */
#define WM (TM / RM)           /* work-items along the pixels */
#define WN (TN / RN)           /* work-items along the channels */

/* Offset of term k of a pixel's sum from the pixel's first input value. */
static inline long conv_offset(const int k, const int w_in)
{
    const int c = k % CIN;
    const int t = k / CIN;
    const int ky = t / KS;
    return ((long)ky * (long)w_in + (long)(t - ky * KS)) * CS + c;
}

__kernel void network_conv_wg(
    __global const float *in,   /* input map, [h_in][w_in][CS] (channels used: CIN) */
    int w_in,                   /* input width in pixels */
    __global const float *wt,   /* weights, [KTOT][NP], k-major, zero-padded */
    __global const float *bias, /* bias, [NP], zero-padded */
    __global float *out,        /* output map, [M][NP] with M = h_out * w_out */
    int w_out,                  /* output width = w_in - KS + 1 */
    int m_total)                /* number of output pixels M */
{
    __local float a_blk[TK * TM];   /* a_blk[kk * TM + mm] = A[m0 + mm][k0 + kk] */
    __local float w_blk[TK * TN];   /* w_blk[kk * TN + nn] = Wt[k0 + kk][n0 + nn] */
    __local long pix[TM];           /* input offset of pixel m0 + mm (-1: past M) */

    const int tn = get_local_id(0);
    const int tm = get_local_id(1);
    const int lid = tm * WN + tn;
    const int nwi = WM * WN;
    const int n0 = (int)get_group_id(0) * TN;
    const int m0 = (int)get_group_id(1) * TM;

    for (int mm = lid; mm < TM; mm += nwi) {
        const int m = m0 + mm;
        const int y = m / w_out;
        pix[mm] = m < m_total ? ((long)y * (long)w_in + (long)(m - y * w_out)) * CS : -1;
    }

    float acc[RM][RN];
#pragma unroll
    for (int j = 0; j < RN; ++j) {
        const int n = n0 + tn + j * WN;
        const float b = n < NP ? bias[n] : 0.0f;
#pragma unroll
        for (int i = 0; i < RM; ++i)
            acc[i][j] = b;
    }

    for (int k0 = 0; k0 < KTOT; k0 += TK) {
        barrier(CLK_LOCAL_MEM_FENCE);   /* pix written; the previous slice's blocks read */
        /* k fastest: neighbouring work-items read neighbouring channels of a pixel */
        for (int e = lid; e < TK * TM; e += nwi) {
            const int mm = e / TK;
            const int kk = e - mm * TK;
            const int k = k0 + kk;
            const long p = pix[mm];
            a_blk[kk * TM + mm] = (k < KTOT && p >= 0) ? in[p + conv_offset(k, w_in)] : 0.0f;
        }
        for (int e = lid; e < TK * TN; e += nwi) {
            const int kk = e / TN;
            const int nn = e - kk * TN;
            const int k = k0 + kk;
            const int n = n0 + nn;
            w_blk[e] = (k < KTOT && n < NP) ? wt[(size_t)k * NP + n] : 0.0f;
        }
        barrier(CLK_LOCAL_MEM_FENCE);   /* the blocks are filled */
        const int kn = min(TK, KTOT - k0);
        for (int kk = 0; kk < kn; ++kk) {
            float a[RM], b[RN];
#pragma unroll
            for (int i = 0; i < RM; ++i)
                a[i] = a_blk[kk * TM + tm + i * WM];
#pragma unroll
            for (int j = 0; j < RN; ++j)
                b[j] = w_blk[kk * TN + tn + j * WN];
#pragma unroll
            for (int i = 0; i < RM; ++i)
#pragma unroll
                for (int j = 0; j < RN; ++j)
                    acc[i][j] = fma(a[i], b[j], acc[i][j]);
        }
    }

#pragma unroll
    for (int i = 0; i < RM; ++i) {
        const int m = m0 + tm + i * WM;
        if (m >= m_total)
            continue;
#pragma unroll
        for (int j = 0; j < RN; ++j) {
            const int n = n0 + tn + j * WN;
            if (n < NP)
#if RELU
                out[(size_t)m * NP + n] = fmax(acc[i][j], 0.0f);
#else
                out[(size_t)m * NP + n] = acc[i][j];
#endif
        }
    }
}
