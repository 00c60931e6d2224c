/* network_head_wg.cl - the per-disparity layers of the fc networks laid out
 * for GPUs, layer by layer, driven by mccnn_cl/stages/network.py (PaperCost,
 * AcrtCost, the "gemm" head).
 *
 * network_head.cl fuses L4 .. L8 for a tile of TM cells whose activations
 * stay in local memory (2 TM HP floats: a few cells per group on a GPU,
 * each re-reading every weight).  Here the cells of one disparity are
 * processed in runs of up to n cells whose activations live in global
 * memory ([n][HP], pixel-major like a conv map), so each hidden layer is one
 * large GEMM, run by the conv stack's GEMM kernel as a 1 x 1 convolution
 * (network_conv_wg.cl's local-memory tiles on GPUs):
 *
 *   network_head_l4    h_0[r] = ReLU(A(x, y) + B(x - d, y))           (L4)
 *   network_conv(_wg)  h_l = ReLU(W_l h_{l-1} + b_l), l = 1 .. NHID    (L5 ..)
 *   network_head_out   C(d, y, x) = the last layer (network_out.h)
 *
 * Cell r of a run is valid cell m = c0 + r of disparity d in the band,
 * numbered as in network_head: y = m / (w - d), x = d + m % (w - d).
 * Invalid cells (x < d) are not computed (network_mark_invalid writes NaN).
 *
 * Bit-identity with network_head: the same L4 vector sum and ReLU, each
 * hidden unit formed as dense_relu forms it (the bias, one fma per input in
 * order, ReLU: the GEMM kernels do exactly that), and the same last layer
 * (network_out.h, the same RN), so the volumes are equal bit for bit.
 *
 * Defines: HP, RN, NOUT (as network_head.cl), VOL_HALF [0] (common.h).
 */
#include "common.h"

#ifndef HP
#error "HP (padded hidden width, a multiple of RN) must be defined"
#endif
#ifndef RN
#error "RN (vector width: 1, 2, 4, 8 or 16) must be defined"
#endif
#ifndef NOUT
#define NOUT 2
#endif
#if HP % RN != 0
#error "HP must be a multiple of RN"
#endif

#include "vector.h"
#include "network_out.h"

CELL_COST(__global, cell_cost)

/* L4 of a run of cells.  Global size (HP / RN, n). */
__kernel void network_head_l4(
    __global const float *fa,   /* A = W4a f_L + b4, [hb * w][HP] (the band, pixel-major) */
    __global const float *fb,   /* B = W4b f_R, [hb * w][HP] */
    __global float *act,        /* out: h_0, [n][HP] */
    int w,                      /* volume columns */
    int d,                      /* disparity */
    int c0,                     /* first valid cell of the run */
    int n)                      /* cells in the run */
{
    const int kv = get_global_id(0);
    const int r = get_global_id(1);
    if (kv >= HP / RN || r >= n)
        return;
    const int nx = w - d;
    const int m = c0 + r;
    const int y = m / nx;
    const size_t p = (size_t)y * (size_t)w + (size_t)(d + (m - y * nx));
    const VT s = VLOAD(fa + p * HP + kv * RN) + VLOAD(fb + (p - (size_t)d) * HP + kv * RN);
    VSTORE(fmax(s, (VT)(0.0f)), act + (size_t)r * HP + kv * RN);
}

/* The last layer of a run of cells into the volume.  Global size (n). */
__kernel void network_head_out(
    __global const float *act,  /* h_NHID, [n][HP] */
    __global const float *w8,   /* last layer, [NOUT][HP] (row = output) */
    __global const float *b8,   /* its bias, [NOUT] */
    __global vol_t *cost,       /* cost volume, [D][h][w] */
    int h,                      /* volume rows */
    int w,                      /* volume columns */
    int y0,                     /* volume row of the band's first row */
    int d,                      /* disparity */
    int c0,                     /* first valid cell of the run */
    int n)                      /* cells in the run */
{
    const int r = get_global_id(0);
    if (r >= n)
        return;
    const int nx = w - d;
    const int m = c0 + r;
    const int y = m / nx;
    VOL_SET(cost, VIDX(d, y0 + y, d + (m - y * nx), h, w), cell_cost(act + (size_t)r * HP, w8, b8));
}
