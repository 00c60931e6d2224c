/* refine.cl - refinement (paper, "Refinement"): enlarge to the input size,
 * median filter, bilateral filter.  Driven by mccnn_cl/stages/refine.py;
 * numpy twins in mccnn_cl/reference/disparity.py.
 *
 * Required define: MEDIAN_SIZE (odd side of the median window; sizes the
 * private array of the median kernel).  Optional: MEDIAN_NET, a selection
 * network for MEDIAN_SIZE^2 values as a list of MEDIAN_CE(i, j) steps
 * (mccnn_cl/stages/refine.py, median_network), which the vector median
 * kernel requires.
 */
#include "common.h"

#ifndef MEDIAN_SIZE
#error "MEDIAN_SIZE (odd median window side) must be defined"
#endif
#define MEDIAN_COUNT (MEDIAN_SIZE * MEDIAN_SIZE)
#define MEDIAN_RADIUS (MEDIAN_SIZE / 2)

/* out(x, y) = in(clamp(x - margin, 0, W-1), clamp(y - margin, 0, H-1)):
 * the cropped map placed at (margin, margin) of the image, the border rows
 * and columns copied outwards.  Global size (Wo, Ho). */
__kernel void refine_enlarge(
    __global const float *in, /* D_SE on the cropped domain, H x W */
    __global float *out,      /* out: Ho x Wo */
    const int H,              /* cropped rows */
    const int W,              /* cropped columns */
    const int Ho,             /* image rows */
    const int Wo,             /* image columns */
    const int margin)         /* offset of the cropped domain in the image */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= Wo || y >= Ho)
        return;
    const int xs = clamp(x - margin, 0, W - 1);
    const int ys = clamp(y - margin, 0, H - 1);
    out[(size_t)y * Wo + x] = in[(size_t)ys * W + xs];
}

/* MEDIAN_SIZE x MEDIAN_SIZE median; pixels outside the map are replaced by
 * the nearest border pixel (clamp-to-edge, as cv2.medianBlur), so every
 * window holds MEDIAN_COUNT (odd) values and the median is the middle one.
 * Global size (W, H). */
__kernel void refine_median(
    __global const float *in, /* H x W */
    __global float *out,      /* out: H x W */
    const int H,              /* rows */
    const int W)              /* columns */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    float v[MEDIAN_COUNT];
    int n = 0;
    for (int dy = -MEDIAN_RADIUS; dy <= MEDIAN_RADIUS; dy++) {
        const int yy = clamp(y + dy, 0, H - 1);
        for (int dx = -MEDIAN_RADIUS; dx <= MEDIAN_RADIUS; dx++) {
            const int xx = clamp(x + dx, 0, W - 1);
            const float a = in[(size_t)yy * W + xx];
            int i = n;
            while (i > 0 && v[i - 1] > a) {
                v[i] = v[i - 1];
                i--;
            }
            v[i] = a;
            n++;
        }
    }
    out[(size_t)y * W + x] = v[MEDIAN_COUNT / 2];
}

/* The same median, 16 consecutive pixels of a row per work-item on float16
 * lanes, through a selection network (MEDIAN_NET: compare-exchange steps
 * MEDIAN_CE(i, j) leaving the middle value of v[0 .. MEDIAN_COUNT - 1] in
 * v[MEDIAN_COUNT / 2]; generated and checked by mccnn_cl/stages/refine.py).
 * Min and max move values without arithmetic, so the result is the same
 * value the sorting kernel above picks.  Global size (ceil(W / 16), H). */
#ifdef MEDIAN_NET
#define MEDIAN_CE(i, j)                  \
    {                                    \
        const float16 a_ = v[i];         \
        v[i] = fmin(a_, v[j]);           \
        v[j] = fmax(a_, v[j]);           \
    }
__kernel void refine_median16(
    __global const float *in, /* H x W */
    __global float *out,      /* out: H x W */
    const int H,              /* rows */
    const int W)              /* columns */
{
    const int xc = get_global_id(0) * 16;
    const int y = get_global_id(1);
    if (xc >= W || y >= H)
        return;
    const int16 xs = (int16)(xc) + LANES;
    const bool interior = xc - MEDIAN_RADIUS >= 0 && xc + 16 + MEDIAN_RADIUS <= W;
    float16 v[MEDIAN_COUNT];
    int n = 0;
#pragma unroll
    for (int dy = -MEDIAN_RADIUS; dy <= MEDIAN_RADIUS; dy++) {
        __global const float *row = in + (size_t)clamp(y + dy, 0, H - 1) * W;
#pragma unroll
        for (int dx = -MEDIAN_RADIUS; dx <= MEDIAN_RADIUS; dx++) {
            if (interior) {
                v[n++] = vload16(0, row + xc + dx);
            } else { /* clamp to the border per lane */
                int xx[16];
                vstore16(clamp(xs + (int16)(dx), (int16)(0), (int16)(W - 1)), 0, xx);
                float t[16];
                for (int i = 0; i < 16; ++i)
                    t[i] = row[xx[i]];
                v[n++] = vload16(0, t);
            }
        }
    }
    MEDIAN_NET
    store16_partial(v[MEDIAN_COUNT / 2], out + (size_t)y * W + xc, min(16, W - xc));
}
#endif

/* Bilateral filter (paper):
 *   D_BF(p) = sum_q D(q) g(|p - q|) 1{|G(p) - G(q)| < tau} / W(p)
 * over the (2 radius + 1)^2 window clipped to the map (pixels outside are
 * not part of N_p), W(p) the sum of the same weights.  The Gaussian is
 * separable: g(|p - q|) = g1(dx) g1(dy) with g1 given as a table of
 * 2 radius + 1 values (its normalising constant cancels).  The guide G is
 * the left image (paper; tau in the image's units) or the disparity map
 * itself (released code; tau in pixels): pass the same buffer for both.
 * W(p) > 0 whenever tau > 0 (q = p always counts); otherwise D(p) is kept.
 *
 * One work-item filters 16 consecutive pixels of a row on float16 lanes
 * (a scalar work-item per pixel did not vectorise on CPU compilers and was
 * ~15x slower on PoCL).  Per lane the sums run in the scalar order: for
 * each window row, the row sum over dx = -radius..radius, then weighted by
 * g1(dy).  Window cells outside the map are left out of the sums: near the
 * left and right borders their guide lanes are loaded as NaN, so the
 * comparison with tau is false.  Global size (ceil(W / 16), H). */
#define BF_VW 16
__kernel void refine_bilateral(
    __global const float *disp,  /* D (median-filtered), H x W */
    __global const float *guide, /* I^L in [0,1] (paper) or D itself (code), H x W */
    __global const float *g1,    /* 1-D Gaussian, 2 radius + 1 taps */
    __global float *out,         /* out: D_BF, H x W */
    const int H,                 /* rows */
    const int W,                 /* columns */
    const int radius,            /* window half-side */
    const float tau)             /* guide difference threshold (strict <) */
{
    const int xc = get_global_id(0) * BF_VW;
    const int y = get_global_id(1);
    if (xc >= W || y >= H)
        return;
    const int n = min(BF_VW, W - xc);
    const float16 gp = load16_partial(guide + (size_t)y * W, xc, n, 0.0f);
    const float16 vtau = (float16)(tau);
    const int y0 = max(y - radius, 0), y1 = min(y + radius, H - 1);
    /* every tap of every lane inside the row: plain vector loads */
    const bool interior = xc - radius >= 0 && xc + BF_VW + radius <= W;
    float16 sum = (float16)(0.0f);
    float16 wsum = (float16)(0.0f);
    for (int yy = y0; yy <= y1; yy++) {
        const float gy = g1[yy - y + radius];
        __global const float *grow = guide + (size_t)yy * W;
        __global const float *drow = disp + (size_t)yy * W;
        float16 rsum = (float16)(0.0f);
        float16 rw = (float16)(0.0f);
        if (interior) {
            for (int k = -radius; k <= radius; k++) {
                const int16 take = fabs(gp - vload16(0, grow + xc + k)) < vtau;
                const float w = g1[k + radius];
                rsum += select((float16)(0.0f), w * vload16(0, drow + xc + k), take);
                rw += select((float16)(0.0f), (float16)(w), take);
            }
        } else {
            for (int k = -radius; k <= radius; k++) {
                const int first = xc + k;
                const int m = min(BF_VW, W - first); /* lanes inside on the right (may be <= 0) */
                const int16 take = fabs(gp - load16_partial(grow, first, m, NAN)) < vtau;
                const float w = g1[k + radius];
                rsum += select((float16)(0.0f), w * load16_partial(drow, first, m, 0.0f), take);
                rw += select((float16)(0.0f), (float16)(w), take);
            }
        }
        sum += gy * rsum;
        wsum += gy * rw;
    }
    const float16 dp = load16_partial(disp + (size_t)y * W, xc, n, 0.0f);
    store16_partial(select(dp, sum / wsum, wsum > (float16)(0.0f)), out + (size_t)y * W + xc, n);
}
