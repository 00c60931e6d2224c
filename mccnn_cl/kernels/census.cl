/* census.cl - a classical matching cost (census transform + Hamming
 * distance), so that the stereo method runs without trained weights.
 * Driven by mccnn_cl/stages/census.py; numpy twins:
 * reference.disparity.census_transform / census_cost.
 *
 * The 9 x 9 window matches the network's patch, so the cost lives on the same
 * cropped domain (margin 4: volume pixel (x, y) is image pixel (x+4, y+4))
 * and the two cost volumes are interchangeable.  Each of the 80 neighours q
 * of the centre p (row-major order over dy, dx = -4..4, the centre skipped)
 * sets bit k when I(q) < I(p); bit k lives in word k / 32 at bit k % 32, the
 * three words of a pixel in planes [3][H][W].
 * Cost(d, y, x) = popcount(census_L(x, y) ^ census_R(x - d, y)) / 80 in
 * [0, 1]; NaN for invalid cells (x - d < 0).
 */
#include "common.h"

#define CENSUS_RADIUS 4
#define CENSUS_BITS 80
#define CENSUS_WORDS 3
/* RN(1 / 80).  A count n / 80 is computed as q = n * CENSUS_RCP corrected once
 * with fma (q + fma(-q, 80, n) * CENSUS_RCP): the correctly rounded quotient for
 * every n in 0..80 (tests/test_census.py checks all 81 exactly), on every
 * device.  A plain `/` may be 2.5 ulp off in OpenCL (NVIDIA's is, without
 * -cl-fp32-correctly-rounded-divide-sqrt), and the plain product is 1 ulp off
 * for 15 counts. */
#define CENSUS_RCP 0x1.99999ap-7f

/* Global size (W, H) of the cropped domain. */
__kernel void census_transform(
    __global const float *img, /* gray image, (H + 8) x (W + 8) */
    __global uint *bits,       /* out: 3 x H x W words */
    const int H,               /* cropped rows */
    const int W)               /* cropped columns */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    const int Wi = W + 2 * CENSUS_RADIUS;
    const float c = img[(size_t)(y + CENSUS_RADIUS) * Wi + x + CENSUS_RADIUS];
    /* fully unrolled, so that every bit's word and position is a constant
     * (a run-time index into words[] kept it in memory and the work-items
     * unvectorised: 3x slower on PoCL) */
    uint w0 = 0u, w1 = 0u, w2 = 0u;
    __attribute__((opencl_unroll_hint))
    for (int i = 0; i < 2 * CENSUS_RADIUS + 1; i++) {
        const int dy = i - CENSUS_RADIUS;
        const size_t row = (size_t)(y + CENSUS_RADIUS + dy) * Wi + x + CENSUS_RADIUS;
        __attribute__((opencl_unroll_hint))
        for (int j = 0; j < 2 * CENSUS_RADIUS + 1; j++) {
            const int dx = j - CENSUS_RADIUS;
            /* bit k: the neighbours in row-major order, the centre skipped */
            const int k = i * (2 * CENSUS_RADIUS + 1) + j - (i * (2 * CENSUS_RADIUS + 1) + j > CENSUS_BITS / 2);
            if (dx == 0 && dy == 0)
                continue;
            const uint bit = (uint)(img[row + dx] < c) << (k % 32);
            if (k < 32)
                w0 |= bit;
            else if (k < 64)
                w1 |= bit;
            else
                w2 |= bit;
        }
    }
    const size_t plane = (size_t)H * W;
    bits[(size_t)y * W + x] = w0;
    bits[plane + (size_t)y * W + x] = w1;
    bits[2 * plane + (size_t)y * W + x] = w2;
}

/* Bits set per byte of each lane of v (each byte's count, 0..8, in that
 * byte): the first steps of a SWAR population count.  Used instead of
 * popcount(uint16), which PoCL (LLVM 15, for x86 without AVX512-VPOPCNTDQ)
 * runs lane by lane: the census cost took ~3x as long with it. */
static inline uint16 census_byte_counts(uint16 v)
{
    v = v - ((v >> 1) & (uint16)(0x55555555u));
    v = (v & (uint16)(0x33333333u)) + ((v >> 2) & (uint16)(0x33333333u));
    return (v + (v >> 4)) & (uint16)(0x0F0F0F0Fu);
}

/* The census words of 16 pixels x0 .. x0 + 15 of one row of a 3 x H x W
 * census (plane words apart); pixels outside 0 .. W - 1 read as 0. */
static inline void census_load16(__global const uint *bits, const size_t plane, const size_t row, const int x0,
                                 const int W, uint16 *w0, uint16 *w1, uint16 *w2)
{
    if (x0 >= 0 && x0 + 16 <= W) {
        *w0 = vload16(0, bits + row + x0);
        *w1 = vload16(0, bits + plane + row + x0);
        *w2 = vload16(0, bits + 2 * plane + row + x0);
        return;
    }
    uint t0[16], t1[16], t2[16];
    for (int i = 0; i < 16; ++i) {
        const int in = x0 + i >= 0 && x0 + i < W;
        t0[i] = in ? bits[row + x0 + i] : 0u;
        t1[i] = in ? bits[plane + row + x0 + i] : 0u;
        t2[i] = in ? bits[2 * plane + row + x0 + i] : 0u;
    }
    *w0 = vload16(0, t0);
    *w1 = vload16(0, t1);
    *w2 = vload16(0, t2);
}

/* Global size (ceil(W / 16), H, ceil(D / levels)): a work-item computes 16
 * adjacent columns x0 .. x0 + 15 (uint16 lanes; the left words loaded once)
 * at `levels` consecutive levels (the host: all D on CPU-shaped devices, so
 * a work-item writes one 64-byte line per plane; 1 elsewhere). */
__kernel void census_cost(
    __global const uint *bits_l, /* census of the left image, 3 x H x W */
    __global const uint *bits_r, /* census of the right image, 3 x H x W */
    __global vol_t *cost,        /* out: D x H x W */
    const int D,                 /* disparity levels */
    const int H,                 /* cropped rows */
    const int W,                 /* cropped columns */
    const int levels)            /* levels per work-item */
{
    const int x0 = get_global_id(0) * 16;
    const int y = get_global_id(1);
    const int d0 = get_global_id(2) * levels;
    if (x0 >= W || y >= H || d0 >= D)
        return;
    const int n = min(16, W - x0);
    const size_t plane = (size_t)H * W;
    const size_t row = (size_t)y * W;
    uint16 l0, l1, l2;
    census_load16(bits_l, plane, row, x0, W, &l0, &l1, &l2);
    const int16 xs = (int16)(x0) + LANES;
    const int dend = min(D, d0 + levels);
    for (int d = d0; d < dend; ++d) {
        uint16 r0, r1, r2;
        census_load16(bits_r, plane, row, x0 - d, W, &r0, &r1, &r2);
        /* per-byte counts of the three words (<= 24 per byte), summed by one multiply */
        const uint16 bytes = census_byte_counts(l0 ^ r0) + census_byte_counts(l1 ^ r1) + census_byte_counts(l2 ^ r2);
        const uint16 cnt = (bytes * (uint16)(0x01010101u)) >> 24;
        const float16 n16 = convert_float16(cnt);
        const float16 q = n16 * (float16)(CENSUS_RCP);
        const float16 c = fma(fma(-q, (float16)((float)CENSUS_BITS), n16), (float16)(CENSUS_RCP), q);
        vol_store16_partial(select((float16)(INVALID_COST), c, xs >= (int16)(d)), cost + VIDX(d, y, x0, H, W), n);
    }
}
