/* network_out.h - the last layer of the fc networks (L8 and the softmax or
 * sigmoid), one copy for both head kernels: network_head (activations in
 * local memory, network_head.cl) and network_head_out (in global memory,
 * network_head_wg.cl).  Include after HP, RN, NOUT and vector.h.
 *
 *   z   = W_8 h + b_8                                        (NOUT outputs)
 *   NOUT 2 (paper): C = softmax(z)[0] = 1 / (1 + exp(z_1 - z_0))  (bad match)
 *   NOUT 1 (acrt):  C = sigmoid(z_0)  = 1 / (1 + exp(-z_0))
 *
 * Each z is summed in RN lanes over the HP / RN vectors of h (one fma per
 * vector, in order), then the lanes by vsum's fixed tree, then the bias.
 * CELL_COST(AS, name) defines `float name(AS const float *h, w8, b8)` for
 * the address space AS of h (OpenCL 1.2 has no generic one).
 */
#ifndef MCCNN_NETWORK_OUT_H
#define MCCNN_NETWORK_OUT_H

#if !defined(HP) || !defined(RN) || !defined(NOUT)
#error "network_out.h needs HP, RN and NOUT"
#endif
#if NOUT != 1 && NOUT != 2
#error "NOUT (outputs of the last layer) must be 1 (sigmoid) or 2 (softmax)"
#endif

/* Horizontal sum of a VT. */
static inline float vsum(VT v)
{
#if RN == 1
    return v;
#elif RN == 2
    return v.s0 + v.s1;
#elif RN == 4
    return (v.s0 + v.s1) + (v.s2 + v.s3);
#elif RN == 8
    return ((v.s0 + v.s1) + (v.s2 + v.s3)) + ((v.s4 + v.s5) + (v.s6 + v.s7));
#else
    const float8 t = v.lo + v.hi;
    return ((t.s0 + t.s1) + (t.s2 + t.s3)) + ((t.s4 + t.s5) + (t.s6 + t.s7));
#endif
}

#define CELL_COST(AS, name)                                                           \
    static inline float name(AS const float *h, __global const float *w8,            \
                             __global const float *b8)                                \
    {                                                                                 \
        VT s0 = (VT)(0.0f), s1 = (VT)(0.0f);                                          \
        for (int kv = 0; kv < HP / RN; ++kv) {                                        \
            const VT a = VLOAD(h + kv * RN);                                          \
            s0 = fma(a, VLOAD(w8 + kv * RN), s0);                                     \
            if (NOUT == 2)                                                            \
                s1 = fma(a, VLOAD(w8 + HP + kv * RN), s1);                            \
        }                                                                             \
        const float z0 = vsum(s0) + b8[0];                                            \
        if (NOUT == 2) {                                                              \
            const float z1 = vsum(s1) + b8[1];                                        \
            return 1.0f / (1.0f + exp(z1 - z0));                                      \
        }                                                                             \
        return 1.0f / (1.0f + exp(-z0));                                              \
    }

#endif /* MCCNN_NETWORK_OUT_H */
