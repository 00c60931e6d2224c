/* sgm_int16.cl - a measurement prototype, not part of the package: the
 * structure of sgm.cl's paired sweeps (per row, 16-column chunks: the tiles'
 * vertical recurrence on 16-lane rows, a 16 x 16 transpose, the horizontal
 * recurrence over the levels, the transpose back, the sum written), one
 * work-item walking its rows top to bottom (left->right and top->bottom
 * paths only), in float16 lanes (PROTO_SHORT 0) or in short16 lanes
 * (PROTO_SHORT 1: costs and penalties as integers, C_r bounded by
 * C + P2, so they fit 16 bits).  FLOAT_IO 1 (with PROTO_SHORT 1): float
 * volumes in and out, the costs scaled by 512 and rounded on load.
 * Simplifications against sgm.cl (the same in both forms): W and D
 * multiples of 16 (the volumes' rows P >= W floats apart: P = W aligns
 * every tile line to 64 bytes, P = 1234 does not), no validity masks or NaN, penalties from one flag table
 * (bigs) instead of the images' gradients, no prefetches.  Driven by
 * sgm_int16.py, which checks the short form bit for bit against an integer
 * reference.  Clang-only constructs (PoCL): __builtin_shufflevector,
 * 2-byte-aligned vector typedefs for unaligned short16 loads and stores
 * (PoCL 3.1 compiles vload16 / vstore16 of shorts to 16 scalar moves) and
 * empty asm statements on x86. */
#ifndef MAXD
#define MAXD 256
#endif
#if PROTO_SHORT
typedef short T;
typedef short16 V;
typedef short16 MV;
typedef short MT;
#define BIG ((short)0x3000)
#define VMIN(a, b) select((a), (b), (b) < (a))
#define SMIN(a, b) ((b) < (a) ? (b) : (a))
#define H8 short8
typedef short16 __attribute__((aligned(2))) V_u;
typedef short16 __attribute__((aligned(2))) MV_u;
#define LD(o, p) (*(const __global V_u *)(p))
#define LDP(o, p) (*(const V_u *)(p))
#define LDM(o, p) (*(const __global MV_u *)(p))
#define ST(v, o, p) (*(__global V_u *)(p) = (v))
#define STP(v, o, p) (*(V_u *)(p) = (v))
#define H4 short4
#define H2 short2
#else
typedef float T;
typedef float16 V;
typedef int16 MV;
typedef int MT;
#define BIG INFINITY
#define VMIN(a, b) select((a), (b), (b) < (a))
#define SMIN(a, b) fmin((a), (b))
#define H8 float8
#define LD(o, p) vload16(o, p)
#define LDP(o, p) vload16(o, p)
#define STP(v, o, p) vstore16(v, o, p)
#define LDM(o, p) vload16(o, p)
#define ST(v, o, p) vstore16(v, o, p)
#define H4 float4
#define H2 float2
#endif

static inline __attribute__((always_inline)) V step(V c, V m, V lo, V d, V hi, V p1, V mp2)
{
#if PROTO_SHORT
    const V best = VMIN(VMIN(d, mp2), VMIN(lo, hi) + p1);
#else
    const V best = VMIN(select(d, mp2, !(d <= mp2)), fmin(lo, hi) + p1);
#endif
    return c - m + best;
}

/* the 16 x 16 transpose of shorts (q16_transpose), with its asm barriers on
 * x86 with AVX: the package's header (kernels/q16.h), as sgm_paired_q16 uses it */
#define Q16_CPU_ASM 1
#include "q16.h"

/* float16: the even/odd form of MCCNN_TRANSPOSE (kernels/common.h) */
static inline __attribute__((always_inline)) void tr16(V *r)
{
#if PROTO_SHORT
    q16_transpose(r);
    return;
#endif
    __attribute__((opencl_unroll_hint))
    for (int s = 0; s < 4; ++s) {
        V t[16];
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < 8; ++i) {
            t[i] = (V)(r[2 * i].even, r[2 * i + 1].even);
            t[i + 8] = (V)(r[2 * i].odd, r[2 * i + 1].odd);
        }
        __attribute__((opencl_unroll_hint))
        for (int i = 0; i < 16; ++i)
            r[i] = t[i];
    }
}

static inline T hmin(V v)
{
    H8 a = SMIN(v.lo, v.hi);
    H4 b = SMIN(a.lo, a.hi);
    H2 c = SMIN(b.lo, b.hi);
    return SMIN(c.x, c.y);
}

#if PROTO_SHORT && FLOAT_IO
typedef float CT;
/* x * 512 rounded to nearest even by the 1.5 * 2^23 trick (|x * 512| < 2^22):
 * PoCL 3.1's convert_short16_sat_rte and rint are ~10 instructions per 8
 * lanes (masks and blends), this is a multiply, an add and an integer
 * subtract; NaN gives 0. */
#define LOADC(p) convert_short16(as_int16(vload16(0, (p)) * 512.0f + 12582912.0f) - 0x4B400000)
#define STOREC(v, p) vstore16(convert_float16(v) * (1.0f / 512.0f), 0, (p))
#else
typedef T CT;
#define LOADC(p) LD(0, (p))
#define STOREC(v, p) ST((v), 0, (p))
#endif
__kernel void proto(__global const CT *cost, __global CT *out, __global T *state, __global const MT *bigs,
                    const int D, const int H, const int W, const T p1a, const T p1b, const T p2a, const T p2b,
                    const int rows_per, const int P)
{
    const int role = get_global_id(0);
    const int y0 = role * rows_per, y1 = min(H, y0 + rows_per);
    __global T *st = state + (size_t)role * (size_t)(W / 16) * (size_t)(D + 2) * 16;
    T blk[16 * MAXD];
    T bufa[MAXD + 2 + 16], bufb[MAXD + 2 + 16];
    const size_t plane = (size_t)H * (size_t)P;
    V r[16];
    for (int y = y0; y < y1; ++y) {
        const int vfirst = y == y0;
        T *pv = bufa, *cv = bufb;
        for (int i = 0; i < MAXD + 2 + 16; ++i) {
            bufa[i] = BIG;
            bufb[i] = BIG;
        }
        T m = BIG;
        for (int x0 = 0; x0 < W; x0 += 16) {
            __global T *sg = st + (size_t)(x0 / 16) * (D + 2) * 16;
            V mv = vfirst ? (V)(BIG) : LD(0, sg + (D + 1) * 16);
            V pd = vfirst ? (V)(BIG) : LD(0, sg);
            V pm1 = (V)(BIG);
            const V mp2a = mv + (V)(p2a), mp2b = mv + (V)(p2b);
            V newmv = (V)(BIG);
            for (int d0 = 0; d0 < D; d0 += 16) {
                __global const CT *src = cost + (size_t)d0 * plane + (size_t)y * P + x0;
                __attribute__((opencl_unroll_hint))
                for (int i = 0; i < 16; ++i)
                    r[i] = LOADC(src + i * plane);
                __attribute__((opencl_unroll_hint))
                for (int i = 0; i < 16; ++i) {
                    const int d = d0 + i;
                    V val;
                    if (vfirst) {
                        val = r[i];
                    } else {
                        const MV big = LDM(0, bigs + x0 + 256 - d);
                        const V pn = LD(0, sg + (d + 1) * 16);
                        val = step(r[i], mv, pm1, pd, pn, select((V)(p1a), (V)(p1b), big), select(mp2a, mp2b, big));
                        pm1 = pd;
                        pd = pn;
                    }
                    ST(val, 0, sg + d * 16);
                    newmv = VMIN(newmv, val);
                }
                tr16(r);
                __attribute__((opencl_unroll_hint))
                for (int k = 0; k < 16; ++k)
                    STP(r[k], 0, blk + k * MAXD + d0);
            }
            ST(newmv, 0, sg + (D + 1) * 16);
            if (vfirst)
                ST((V)(BIG), 0, sg + D * 16);
            for (int k = 0; k < 16; ++k) {
                const int x = x0 + k;
                const int first = x == 0;
#if PROTO_PREFETCH /* the next chunk's cost and output lines, spread over the pixels (as sgm.cl) */
                if (x0 + 16 < W) {
                    const int per = (D + 15) / 16;
                    for (int d = k * per; d < min(D, k * per + per); ++d) {
                        __builtin_prefetch(cost + (size_t)d * plane + (size_t)y * P + x0 + 16, 0, 2);
                        __builtin_prefetch(out + (size_t)d * plane + (size_t)y * P + x0 + 16, 0, 2);
                    }
                }
#endif
                const T mm = m;
                const T mp2ha = mm + p2a, mp2hb = mm + p2b;
                V newm = (V)(BIG);
                for (int d0 = 0; d0 < D; d0 += 16) {
                    T *bp = blk + k * MAXD + d0;
                    const V c = LDP(0, bp);
                    V val;
                    if (first) {
                        val = c;
                    } else {
                        const MV big = LDM(0, bigs + 512 + x - d0);
                        val = step(c, (V)(mm), LDP(0, pv + d0), LDP(0, pv + d0 + 1), LDP(0, pv + d0 + 2),
                                   select((V)(p1a), (V)(p1b), big), select((V)(mp2ha), (V)(mp2hb), big));
                    }
                    STP(val, 0, cv + d0 + 1);
                    STP(val, 0, bp);
                    newm = VMIN(newm, val);
                }
                m = hmin(newm);
                T *t = pv;
                pv = cv;
                cv = t;
            }
            for (int d0 = 0; d0 < D; d0 += 16) {
                __attribute__((opencl_unroll_hint))
                for (int k = 0; k < 16; ++k)
                    r[k] = LDP(0, blk + k * MAXD + d0);
                tr16(r);
                __global CT *dst = out + (size_t)d0 * plane + (size_t)y * P + x0;
                __attribute__((opencl_unroll_hint))
                for (int i = 0; i < 16; ++i)
                    STOREC(r[i] + LD(0, sg + (d0 + i) * 16), dst + i * plane);
            }
        }
    }
}
