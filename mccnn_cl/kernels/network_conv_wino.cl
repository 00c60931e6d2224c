/* network_conv_wino.cl - one valid 3 x 3 convolution layer of the conv stack
 * (channel-last maps, as kernels/network_conv.cl, whose result it gives to
 * float32 rounding) by Winograd's F(2x2, 3x3): 16 multiplies per 2 x 2
 * outputs and channel pair instead of 36 (mccnn_cl/costs/features.py,
 * ConvStack; the "winograd" path of CPU devices, rule network_winograd).
 *
 * Work-item (g, quad, ty): output channels g*RN .. g*RN+RN-1 of RT consecutive
 * 2 x 2 output tiles of tile row ty.  The work-group (the NP/RN channel groups
 * of the same tiles) transforms the tiles' 4 x 4 input patches (all CIN
 * channels, B^T d B) once into local memory shared by the group (V[RT][16][CIN],
 * each tile padded, WINO_VT), each work-item RN channels at a time in turn,
 * then waits at one barrier; each work-item then runs the 16 products M_xi =
 * V_xi U_xi of its channels, XA of the 16 xi at a time over RT tiles (XA x RT
 * register accumulators of RN floats; U = G g G^T precomputed on the host,
 * [16][CIN][NP]), keeps M in its own local memory ([RT][16][RN]) and applies
 * the output transform (A^T M A), bias and ReLU.  Sharing the transform
 * spares the group NP/RN - 1 copies of it (BENCHMARKS.md, Machine C's
 * thirteenth session).  Launch: global (NP/RN, ceil(tw/RT), th), local
 * (NP/RN, 1, 1).
 *
 * Row anchor p (0 or 1): tile row ty covers output rows 2 ty - p and
 * 2 ty - p + 1, so a map cut from a larger one at an odd row (a band, a row
 * tile) is computed with p = 1 on the larger map's tile grid.  Row -1 is not
 * stored, and its input row (clamped to row 0) cannot change the row kept:
 * of the four transformed rows only the first reads a tile's first input
 * row, and only the first output row reads that one, so every output gets
 * the very operations of the whole map's computation (tests/test_winograd.py).
 * th = ceil((h_out + p) / 2), tw = ceil(w_out / 2).  Needs KS 3, CIN a
 * multiple of RN, and RT (16 CIN + 16 + (NP/RN) 16 RN) x 4 bytes of local
 * memory (~32 KiB for 64 -> 64 maps at RT 4: CPU devices, whose local memory
 * is ordinary memory).
 */
#include "common.h"
#include "vector.h"

#if !defined(CIN) || !defined(CS) || !defined(NP) || !defined(RN) || !defined(RELU) || !defined(RT) || !defined(XA)
#error "CIN, CS, NP, RN, RELU, RT and XA must be defined"
#endif
#if CIN % RN || NP % RN || 16 % XA
#error "CIN and NP must be multiples of RN, and XA must divide 16"
#endif
/* The products' operands, laid out so that the c loop's reads are not a
 * multiple of 4 KiB apart (where they were, 16 x 64 floats for 64 channels,
 * every read of a run fell into one L1 set and missed; the layer 64 -> 64 on
 * a KITTI-sized map took 181 against 141 ms on the Zen 3, the same bits):
 * U as [16][CIN][NP] (U(c, xi) at u + WINO_U(c, xi)), a run over c
 * contiguous; V's tiles WINO_VT floats apart, 16 floats more than their
 * 16 x CIN values. */
#define WINO_VT (16 * CIN + 16)
#define WINO_U(c, xi) (((size_t)(xi) * CIN + (c)) * NP)

__kernel void network_conv_wino(__global const float *in, int w_in, int h_in,
                             __global const float *u, /* [16][CIN][NP] */
                             __global const float *bias, __global float *out, int w_out, int h_out, int tw, int th,
                             int p)
{
    __local float V[RT * WINO_VT];                /* the group's transformed patches */
    __local float mloc[NP / RN][RT * 16 * RN];    /* each work-item's products */
    const int g = get_global_id(0), qd = get_global_id(1), ty = get_global_id(2);
    const int nq = (tw + RT - 1) / RT;
    /* the whole group has one (qd, ty): it reaches the barrier together or not at all */
    if (qd >= nq || ty >= th) return;
    __local float *Mq = mloc[get_local_id(0)];
    for (int t = 0; t < RT; ++t) {
        const int tx = min(RT * qd + t, tw - 1);
        for (int c0 = g * RN; c0 < CIN; c0 += NP) { /* RN channels per group member in turn */
            VT d[4][4];
#pragma unroll
            for (int i = 0; i < 4; ++i)
#pragma unroll
                for (int j = 0; j < 4; ++j) {
                    const int y = clamp(2 * ty - p + i, 0, h_in - 1), x = min(2 * tx + j, w_in - 1);
                    d[i][j] = VLOAD(in + ((size_t)y * w_in + x) * CS + c0);
                }
            VT r[4][4];
#pragma unroll
            for (int j = 0; j < 4; ++j) {
                r[0][j] = d[0][j] - d[2][j]; r[1][j] = d[1][j] + d[2][j];
                r[2][j] = d[2][j] - d[1][j]; r[3][j] = d[1][j] - d[3][j];
            }
            __local float *vt = V + (size_t)t * WINO_VT + c0;
#pragma unroll
            for (int i = 0; i < 4; ++i) {
                VSTORE(r[i][0] - r[i][2], vt + (4 * i + 0) * CIN);
                VSTORE(r[i][1] + r[i][2], vt + (4 * i + 1) * CIN);
                VSTORE(r[i][2] - r[i][1], vt + (4 * i + 2) * CIN);
                VSTORE(r[i][1] - r[i][3], vt + (4 * i + 3) * CIN);
            }
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    const int n0 = g * RN;
    for (int h = 0; h < 16 / XA; ++h) {
        VT acc[XA][RT];
#pragma unroll
        for (int a = 0; a < XA; ++a)
#pragma unroll
            for (int t = 0; t < RT; ++t) acc[a][t] = (VT)(0.0f);
        __global const float *up = u + n0;
        __local const float *vh = V + (size_t)(XA * h) * CIN;
        for (int c = 0; c < CIN; ++c) {
#pragma unroll
            for (int a = 0; a < XA; ++a) {
                const VT w = VLOAD(up + WINO_U(c, XA * h + a));
#pragma unroll
                for (int t = 0; t < RT; ++t)
                    acc[a][t] = fma((VT)(vh[(size_t)t * WINO_VT + a * CIN + c]), w, acc[a][t]);
            }
        }
#pragma unroll
        for (int a = 0; a < XA; ++a)
#pragma unroll
            for (int t = 0; t < RT; ++t) VSTORE(acc[a][t], Mq + ((size_t)t * 16 + XA * h + a) * RN);
    }
    const VT b = VLOAD(bias + n0);
    for (int t = 0; t < RT; ++t) {
        const int tx = RT * qd + t;
        if (tx >= tw) break;
        __local const float *mt = Mq + (size_t)t * 16 * RN;
        VT s[2][4];
#pragma unroll
        for (int j = 0; j < 4; ++j) {
            const VT m0 = VLOAD(mt + j * RN), m1 = VLOAD(mt + (4 + j) * RN);
            const VT m2 = VLOAD(mt + (8 + j) * RN), m3 = VLOAD(mt + (12 + j) * RN);
            s[0][j] = m0 + m1 + m2;
            s[1][j] = m1 - m2 - m3;
        }
#pragma unroll
        for (int i = 0; i < 2; ++i) {
            const int y = 2 * ty - p + i;
            if (y >= 0 && y < h_out) {
                VT o0 = b + (s[i][0] + s[i][1] + s[i][2]), o1 = b + (s[i][1] - s[i][2] - s[i][3]);
#if RELU
                o0 = fmax(o0, (VT)(0.0f)); o1 = fmax(o1, (VT)(0.0f));
#endif
                const int x = 2 * tx;
                VSTORE(o0, out + ((size_t)y * w_out + x) * NP + n0);
                if (x + 1 < w_out) VSTORE(o1, out + ((size_t)y * w_out + x + 1) * NP + n0);
            }
        }
    }
}
