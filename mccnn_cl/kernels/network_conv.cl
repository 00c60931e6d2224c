/* network_conv.cl - the per-pixel layers of every network: the tied conv
 * stack (mccnn_cl/stages/features.py, ConvStack; any depth, maps, kernel
 * size; RELU per layer, so the fst stack runs its last layer with RELU 0) and
 * the L4 split of the fc networks (mccnn_cl/stages/network.py, split_l4).
 *
 * One kernel, network_conv, computes a valid KS x KS convolution of a
 * channel-last map as a GEMM over output pixels:
 *
 *   out[m][n] = act(bias[n] + sum_{ky,kx,c} Wt[(ky*KS + kx)*CIN + c][n]
 *                                           * in[(y+ky)*w_in + x+kx][c])
 *
 * with m = y*w_out + x the flattened output pixel, act = ReLU when RELU is 1,
 * identity otherwise.  Weights are stored transposed (k-major, NP outputs per
 * row, zero-padded), so one vector load gives RN consecutive outputs.  Padded
 * output channels have zero weights and zero bias, so they hold exactly 0.
 *
 * Register blocking: each work-item computes RM consecutive output pixels x
 * RN consecutive output channels (RM vector accumulators of RN floats); every
 * weight vector loaded is used RM times, every input scalar RN times.  No
 * local memory, no barriers.  Global size: (NP / RN, ceil(M / RM)).
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
#error "NP (padded output channels, multiple of RN) must be defined"
#endif
#ifndef RM
#error "RM (output pixels per work-item) must be defined"
#endif
#ifndef RN
#error "RN (output channels per work-item: 1, 2, 4, 8 or 16) must be defined"
#endif
#ifndef RELU
#error "RELU (0 or 1) must be defined"
#endif

#include "vector.h"

__kernel void network_conv(
    __global const float *in,   /* input map, [h_in][w_in][CS] (channels used: CIN) */
    int w_in,                   /* input width in pixels */
    __global const float *wt,   /* weights, [KS*KS*CIN][NP], k-major, zero-padded */
    __global const float *bias, /* bias, [NP], zero-padded */
    __global float *out,        /* output map, [M][NP] with M = h_out * w_out */
    int w_out,                  /* output width = w_in - KS + 1 */
    int m_total)                /* number of output pixels M */
{
    const int cg = get_global_id(0);      /* output channel group */
    const int rg = get_global_id(1);      /* output pixel group */
    if (cg >= NP / RN || rg * RM >= m_total)
        return;
    const int n0 = cg * RN;

    size_t base[RM];
    VT acc[RM];
    const VT b = VLOAD(bias + n0);
#pragma unroll
    for (int r = 0; r < RM; ++r) {
        /* rows past the end repeat the last pixel; they are never stored */
        const int m = min(rg * RM + r, m_total - 1);
        const int y = m / w_out;
        const int x = m - y * w_out;
        base[r] = ((size_t)y * (size_t)w_in + (size_t)x) * CS;
        acc[r] = b;
    }
    for (int ky = 0; ky < KS; ++ky) {
        for (int kx = 0; kx < KS; ++kx) {
            const size_t off = ((size_t)ky * (size_t)w_in + (size_t)kx) * CS;
            __global const float *wrow = wt + (size_t)((ky * KS + kx) * CIN) * NP + n0;
            for (int c = 0; c < CIN; ++c) {
                const VT w = VLOAD(wrow + (size_t)c * NP);
#pragma unroll
                for (int r = 0; r < RM; ++r)
                    acc[r] = fma((VT)(in[base[r] + off + c]), w, acc[r]);
            }
        }
    }
#pragma unroll
    for (int r = 0; r < RM; ++r) {
        const int m = rg * RM + r;
        if (m < m_total) {
#if RELU
            VSTORE(fmax(acc[r], (VT)(0.0f)), out + (size_t)m * NP + n0);
#else
            VSTORE(acc[r], out + (size_t)m * NP + n0);
#endif
        }
    }
}
