/* q16.h - a 16 x 16 transpose of shorts, shared by sgm.cl's 16-bit paired
 * sweeps (sgm_paired_q16) and the prototype they came from
 * (tools/benchmarks/sgm_int16.cl).
 *
 * The AVX2 unpack form: 16-, 32- and 64-bit interleaves within 128-bit halves
 * (vpunpck[lh]wd / dq / qdq), then the halves across (vperm2i128): 64
 * shuffles per tile, written with __builtin_shufflevector (PoCL 3.1 makes
 * shuffle2 on short16 a library call).  Q_OPAQUE, an empty asm statement
 * where the includer sets Q16_CPU_ASM 1 and the target is x86 with AVX, keeps
 * LLVM from merging the steps into worse ones (as T8_OPAQUE in common.h);
 * elsewhere (GPUs, Oclgrind) it is nothing.
 */
#ifndef MCCNN_Q16_H
#define MCCNN_Q16_H

#if defined(Q16_CPU_ASM) && (defined(__x86_64__) || defined(__i386__)) && defined(__AVX__)
#if Q16_CPU_ASM
#define Q_OPAQUE(v) __asm__("" : "+x"(v))
#endif
#endif
#ifndef Q_OPAQUE
#define Q_OPAQUE(v) ((void)0)
#endif

/* r[i] = row i of a 16 x 16 tile of shorts; on return r[i] = column i */
static inline __attribute__((always_inline)) void q16_transpose(short16 *r)
{
    short16 A[16], B[16];
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < 16; ++i)
        Q_OPAQUE(r[i]);
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < 8; ++i) {
        A[2 * i] = __builtin_shufflevector(r[2 * i], r[2 * i + 1], 0, 16, 1, 17, 2, 18, 3, 19, 8, 24, 9, 25, 10, 26,
                                           11, 27);
        A[2 * i + 1] = __builtin_shufflevector(r[2 * i], r[2 * i + 1], 4, 20, 5, 21, 6, 22, 7, 23, 12, 28, 13, 29,
                                               14, 30, 15, 31);
        Q_OPAQUE(A[2 * i]);
        Q_OPAQUE(A[2 * i + 1]);
    }
    __attribute__((opencl_unroll_hint))
    for (int q = 0; q < 4; ++q) {
        __attribute__((opencl_unroll_hint))
        for (int e = 0; e < 2; ++e) {
            B[4 * q + 2 * e] = __builtin_shufflevector(A[4 * q + e], A[4 * q + 2 + e], 0, 1, 16, 17, 2, 3, 18, 19, 8,
                                                       9, 24, 25, 10, 11, 26, 27);
            B[4 * q + 2 * e + 1] = __builtin_shufflevector(A[4 * q + e], A[4 * q + 2 + e], 4, 5, 20, 21, 6, 7, 22,
                                                           23, 12, 13, 28, 29, 14, 15, 30, 31);
            Q_OPAQUE(B[4 * q + 2 * e]);
            Q_OPAQUE(B[4 * q + 2 * e + 1]);
        }
    }
    __attribute__((opencl_unroll_hint))
    for (int h = 0; h < 2; ++h) {
        __attribute__((opencl_unroll_hint))
        for (int j = 0; j < 4; ++j) {
            A[8 * h + 2 * j] = __builtin_shufflevector(B[8 * h + j], B[8 * h + 4 + j], 0, 1, 2, 3, 16, 17, 18, 19, 8,
                                                       9, 10, 11, 24, 25, 26, 27);
            A[8 * h + 2 * j + 1] = __builtin_shufflevector(B[8 * h + j], B[8 * h + 4 + j], 4, 5, 6, 7, 20, 21, 22,
                                                           23, 12, 13, 14, 15, 28, 29, 30, 31);
            Q_OPAQUE(A[8 * h + 2 * j]);
            Q_OPAQUE(A[8 * h + 2 * j + 1]);
        }
    }
    __attribute__((opencl_unroll_hint))
    for (int c = 0; c < 8; ++c) {
        r[c] = __builtin_shufflevector(A[c], A[8 + c], 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23);
        r[c + 8] = __builtin_shufflevector(A[c], A[8 + c], 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30,
                                           31);
    }
}

#endif /* MCCNN_Q16_H */
