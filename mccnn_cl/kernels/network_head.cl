/* network_head.cl - the per-disparity layers of the fc networks (L4-L8 and
 * the output), driven by mccnn_cl/stages/network.py (PaperCost, AcrtCost).
 *
 * With the L4 split precomputed once per pixel by network_conv.cl,
 *   A(p) = W4a . f_L(p) + b4,    B(q) = W4b . f_R(q),
 * a cell (d, y, x) of the cost volume C_CNN is
 *   h_0 = ReLU(A(x, y) + B(x - d, y))                     (L4)
 *   h_l = ReLU(W_l h_{l-1} + b_l),  l = 1 .. NHID         (L5 .. L7)
 *   z   = W_8 h_NHID + b_8                                (L8, NOUT outputs)
 *   NOUT 2 (paper): C = softmax(z)[0] = 1 / (1 + exp(z_1 - z_0))  (bad match)
 *   NOUT 1 (acrt):  C = sigmoid(z_0)  = 1 / (1 + exp(-z_0))
 *
 * network_head fuses that whole chain for a tile of TM cells of one
 * disparity: the activations of the tile live in local memory (ping-pong,
 * 2 x TM x HP floats) and only the cost is written to global memory.  The
 * image is processed in bands of rows [y0, y0 + hb) (A and B hold that band
 * only).  The cells of the band and of disparity d that are valid (x >= d)
 * are numbered i = (y - y0) (W - d) + (x - d), i in [0, hb (W - d)); tile t holds i in
 * [t TM, t TM + TM), so tiles run across image rows and only the last tile of
 * a disparity is partly empty.  Invalid cells (x < d) are never computed here;
 * network_mark_invalid writes NaN into them.
 *
 * Each dense layer is a TM x HP x HP matrix product; work-item
 * (rg, cg) of the group computes the register-blocked micro-tiles of rows
 * [rg RM, rg RM + RM) and outputs [c RN, c RN + RN) for c = cg, cg + ncgw, ...:
 * RM vector accumulators of RN floats, one weight vector load per k reused RM
 * times.  Weights are
 * stored k-major ([k][n], HP floats a row) and zero-padded to HP, so padded
 * units are exactly 0 and never change the result.
 *
 * Work-group size: NRG * ncgw work-items (NRG = TM / RM row groups, ncgw <=
 * HP / RN column groups), chosen on the host from the kernel's maximum
 * work-group size; local memory 2 TM HP floats, checked on the host against
 * the device's local memory.
 */
#include "common.h"

#ifndef HP
#error "HP (padded hidden width, a multiple of RN) must be defined"
#endif
#ifndef NHID
#error "NHID (number of hidden layers after L4, e.g. 3 for L5-L7) must be defined"
#endif
#ifndef TM
#error "TM (cells per tile, a multiple of RM) must be defined"
#endif
#ifndef RM
#error "RM (rows per work-item) must be defined"
#endif
#ifndef RN
#error "RN (outputs per work-item: 1, 2, 4, 8 or 16) must be defined"
#endif
#ifndef ROWS_FASTEST
#error "ROWS_FASTEST (1: consecutive work-items take consecutive row groups) must be defined"
#endif
#ifndef NOUT
#define NOUT 2
#endif

#include "vector.h"
#include "network_out.h"

#define NCG (HP / RN)          /* column groups */
#define NRG (TM / RM)          /* row groups */

#if HP % RN != 0 || TM % RM != 0
#error "HP must be a multiple of RN and TM a multiple of RM"
#endif

CELL_COST(__local, cell_cost)

/* One dense layer with ReLU on a tile: out[r][n] = ReLU(b[n] + sum_k in[r][k] w[k][n]),
 * for rows [rg RM, rg RM + RM) and output groups cg, cg + ncgw, ... < NCG. */
inline void dense_relu(__local const float *in, __local float *out,
                       __global const float *w, __global const float *b,
                       int rg, int cg, int ncgw)
{
    const int r0 = rg * RM;
    __local const float *a = in + r0 * HP;
    for (int c = cg; c < NCG; c += ncgw) {
        const int n0 = c * RN;
        VT acc[RM];
        const VT bv = VLOAD(b + n0);
#pragma unroll
        for (int r = 0; r < RM; ++r)
            acc[r] = bv;
        __global const float *wc = w + n0;
        for (int k = 0; k < HP; ++k) {
            const VT wv = VLOAD(wc + (size_t)k * HP);
#pragma unroll
            for (int r = 0; r < RM; ++r)
                acc[r] = fma((VT)(a[r * HP + k]), wv, acc[r]);
        }
#pragma unroll
        for (int r = 0; r < RM; ++r)
            VSTORE(fmax(acc[r], (VT)(0.0f)), out + (r0 + r) * HP + n0);
    }
}

__kernel void network_head(
    __global const float *fa,   /* A = W4a f_L + b4, [H * W][HP] (pixel-major) */
    __global const float *fb,   /* B = W4b f_R, [H * W][HP] */
    __global const float *wh,   /* hidden layers L5.., [NHID][HP][HP], k-major */
    __global const float *bh,   /* their biases, [NHID][HP] */
    __global const float *w8,   /* last layer, [NOUT][HP] (row = output) */
    __global const float *b8,   /* its bias, [NOUT] */
    __global vol_t *cost,       /* cost volume, [D][H][W] */
    int h,                      /* H: cropped height (volume rows) */
    int w,                      /* W: cropped width (volume columns) */
    int y0,                     /* first volume row of this band (fa, fb hold rows y0 ..) */
    int hb,                     /* rows in this band */
    int d0)                     /* first disparity of this launch (d = d0 + group id 1) */
{
    __local float act[2 * TM * HP];

    const int d = d0 + (int)get_group_id(1);
    const int nx = w - d;                       /* valid cells per row */
    if (nx <= 0)
        return;                                 /* uniform over the group */
    const int n_valid = hb * nx;
    const int first = (int)get_group_id(0) * TM;
    if (first >= n_valid)
        return;                                 /* uniform over the group */

    const int lid = get_local_id(0);
    const int nwi = get_local_size(0);          /* a multiple of NRG, at most NRG * NCG */
    const int ncgw = nwi / NRG;                 /* work-items along the outputs */
#if ROWS_FASTEST
    const int rg = lid % NRG;
    const int cg = lid / NRG;
#else
    const int cg = lid % ncgw;
    const int rg = lid / ncgw;
#endif

    /* L4: act[r] = ReLU(A(x, y) + B(x - d, y)) */
    for (int i = lid; i < TM * NCG; i += nwi) {
        const int r = i / NCG;
        const int kv = i - r * NCG;
        const int m = min(first + r, n_valid - 1);   /* past-the-end rows: repeat, not stored */
        const int y = m / nx;                   /* row within the band */
        const int x = d + (m - y * nx);
        const size_t p = (size_t)y * (size_t)w + (size_t)x;
        const VT s = VLOAD(fa + p * HP + kv * RN) + VLOAD(fb + (p - (size_t)d) * HP + kv * RN);
        VSTORE(fmax(s, (VT)(0.0f)), act + r * HP + kv * RN);
    }
    barrier(CLK_LOCAL_MEM_FENCE);

    /* L5 .. L(4 + NHID) */
    for (int l = 0; l < NHID; ++l) {
        __local const float *src = act + (l & 1) * (TM * HP);
        __local float *dst = act + ((l + 1) & 1) * (TM * HP);
        dense_relu(src, dst, wh + (size_t)l * HP * HP, bh + (size_t)l * HP, rg, cg, ncgw);
        barrier(CLK_LOCAL_MEM_FENCE);
    }

    /* L8 and softmax (C = P(bad match) = 1 / (1 + exp(z1 - z0))) or sigmoid: network_out.h */
    __local const float *fin = act + (NHID & 1) * (TM * HP);
    for (int r = lid; r < TM; r += nwi) {
        const int m = first + r;
        if (m >= n_valid)
            continue;
        const float c = cell_cost(fin + r * HP, w8, b8);
        const int y = m / nx;
        const int x = d + (m - y * nx);
        VOL_SET(cost, VIDX(d, y0 + y, x, h, w), c);
    }
}

/* NaN into the invalid cells (x < d) of disparities [d0, d0 + get_global_size(2)). */
__kernel void network_mark_invalid(
    __global vol_t *cost,       /* cost volume, [D][H][W] */
    int h,                      /* H */
    int w,                      /* W */
    int d0)                     /* first disparity of this launch */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    const int d = d0 + (int)get_global_id(2);
    if (x < w && y < h && x < d)
        VOL_SET(cost, VIDX(d, y, x, h, w), INVALID_COST);
}
