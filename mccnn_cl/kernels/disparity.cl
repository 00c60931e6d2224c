/* disparity.cl - winner-take-all and the left-right consistency check
 * (paper, "Computing the disparity image" and "Interpolation").
 * Driven by mccnn_cl/stages/disparity.py; numpy twins in
 * mccnn_cl/reference/disparity.py.
 *
 * Disparity maps are int32 [H][W] on the cropped domain of the volume.
 * Labels: 0 = correct, 1 = mismatch, 2 = occlusion (see LABEL_* below).
 */
#include "common.h"

#define LABEL_CORRECT 0
#define LABEL_MISMATCH 1
#define LABEL_OCCLUSION 2

/* D^L(x, y) = argmin_{0 <= d <= min(D-1, x)} C(d, y, x).
 * Ties go to the smallest d (strict '<' while d increases).  Invalid cells
 * (d > x) never take part.  One work-item per WTA_CHUNKS x 16 consecutive
 * pixels of a row (float16 lanes), global size (ceil(W / (16 WTA_CHUNKS)),
 * H); a lane's invalid cells are read (they hold NaN, never uninitialised
 * memory) but masked out.  With WTA_CHUNKS > 1 (the CPU rule) each step
 * over d reads WTA_CHUNKS adjacent lines of one plane instead of one line
 * per plane and step (planes H W floats apart), which the CPU's prefetchers
 * follow; every lane compares the same values in the same order of d, so
 * the map is the same. */
#ifndef WTA_CHUNKS
#define WTA_CHUNKS 1
#endif
__kernel void disparity_wta_left(
    __global const vol_t *cost, /* C_L, D x H x W */
    __global int *disp,         /* out: D^L, H x W */
    const int D,                /* disparity levels */
    const int H,                /* rows */
    const int W)                /* columns */
{
    const int xt = get_global_id(0) * (16 * WTA_CHUNKS);
    const int y = get_global_id(1);
    if (xt >= W || y >= H)
        return;
    const int nc = min(WTA_CHUNKS, (W - xt + 15) / 16); /* chunks in the row */
    float16 best[WTA_CHUNKS];
    int16 best_d[WTA_CHUNKS];
    for (int c = 0; c < nc; ++c) {
        best[c] = vol_load16_partial(cost + VIDX(0, y, xt + 16 * c, H, W), 0, min(16, W - xt - 16 * c), 0.0f);
        best_d[c] = (int16)(0);
    }
    const int dmax = min(D - 1, min(W, xt + 16 * WTA_CHUNKS) - 1);
    for (int d = 1; d <= dmax; d++) {
        for (int c = 0; c < nc; ++c) {
            const int x0 = xt + 16 * c;
            const int n = min(16, W - x0);
            if (x0 + n - 1 < d)
                continue; /* no valid cell of this chunk at d (nor beyond) */
            const int16 xs = (int16)(x0) + LANES;
            const float16 v = vol_load16_partial(cost + VIDX(d, y, x0, H, W), 0, n, 0.0f);
            const int16 take = (v < best[c]) & ((int16)(d) <= xs);
            best[c] = select(best[c], v, take);
            best_d[c] = select(best_d[c], (int16)(d), take);
        }
    }
    for (int c = 0; c < nc; ++c) {
        const int x0 = xt + 16 * c;
        const int n = min(16, W - x0);
        if (n == 16) {
            vstore16(best_d[c], 0, disp + (size_t)y * W + x0);
        } else {
            int t[16];
            vstore16(best_d[c], 0, t);
            for (int i = 0; i < n; ++i)
                disp[(size_t)y * W + x0 + i] = t[i];
        }
    }
}

/* D^R(x, y) = argmin_{0 <= d <= min(D-1, W-1-x)} C_R(d, y, x), with the
 * right-reference volume derived from the left one:
 * C_R(d, y, x) = C_L(d, y, x + d) (valid while x + d < W).
 * Ties go to the smallest d.  Global size (W, H). */
__kernel void disparity_wta_right(
    __global const vol_t *cost, /* C_L, D x H x W */
    __global int *disp,         /* out: D^R, H x W */
    const int D,                /* disparity levels */
    const int H,                /* rows */
    const int W)                /* columns */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    const int dmax = min(D - 1, W - 1 - x);
    int best_d = 0;
    float best = VOL_GET(cost, VIDX(0, y, x, H, W));
    for (int d = 1; d <= dmax; d++) {
        const float c = VOL_GET(cost, VIDX(d, y, x + d, H, W));
        if (c < best) {
            best = c;
            best_d = d;
        }
    }
    disp[(size_t)y * W + x] = best_d;
}

/* Left-right check (paper): with d = D^L(p) and pd = (x - d, y),
 *   correct   if |d - D^R(pd)| <= threshold,
 *   mismatch  if |d' - D^R(pd')| <= threshold for any other d' in [0, D)
 *             with 0 <= x - d' < Wr,
 *   occlusion otherwise.
 * Wr: columns of the real right image (pd' must lie inside it).  W for a map
 * of the real pair (x - d' < W always holds there); in the working frame of a
 * range with M < 0 (mccnn_cl/disprange.py) the real cropped width, so that
 * the right image's padding columns Wr .. W-1 are never searched: a pixel
 * whose only consistent candidates lie there is an occlusion, as in the
 * image's frame.  The paper's threshold is 1; the released code's "< 1.1"
 * selects the same pixels on integer maps.  A D^L(p) outside
 * [max(0, x - Wr + 1), x] is treated as not correct.  Global size (W, H). */
__kernel void disparity_lr_check(
    __global const int *disp_l, /* D^L, H x W */
    __global const int *disp_r, /* D^R, H x W */
    __global int *labels,       /* out: LABEL_*, H x W */
    const int D,                /* disparity levels */
    const int H,                /* rows */
    const int W,                /* columns */
    const float threshold,      /* max |d - D^R(pd)| of a consistent pair */
    const int Wr)               /* columns of the real right image (<= W) */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    const size_t row = (size_t)y * W;
    const int d = disp_l[row + x];
    const int dmin = max(0, x - Wr + 1); /* smallest d' with x - d' < Wr */
    int label = LABEL_OCCLUSION;
    if (d >= dmin && d <= x && fabs((float)(d - disp_r[row + x - d])) <= threshold) {
        label = LABEL_CORRECT;
    } else {
        const int dmax = min(D - 1, x);
        for (int e = dmin; e <= dmax; e++) {
            if (e != d && fabs((float)(e - disp_r[row + x - e])) <= threshold) {
                label = LABEL_MISMATCH;
                break;
            }
        }
    }
    labels[row + x] = label;
}

/* The right-reference volume, mirrored so that it follows the left-reference
 * conventions of every stage (cell (d, y, x) valid iff d <= x), made in place
 * from C_L:
 *   C_R'(d, y, x) = C_R(d, y, W-1-x) = C_L(d, y, W-1-x+d)   for d <= x,
 *   NaN otherwise (x + d >= W in the unmirrored right volume).
 * Cell (d, y, x) then compares the mirrored right image at x with the
 * mirrored left image at x - d, so running the stereo method on it with the
 * mirrored images as (left, right) treats the right image as the reference;
 * disparity_mirror maps the resulting map back.
 *
 * On each (d, y) line this reverses the cells d .. W-1 (cell d + i swaps with
 * cell W-1-i) and sets the cells 0 .. d-1, invalid on both sides, to NaN; so
 * a second call turns C_R' back into C_L (its invalid cells as NaN), and the
 * pipeline needs no third volume for the right reference.  Work-item k of a
 * line swaps the pairs i = 16k .. 16k+15 (i < (W-d) / 2), by two 16-cell
 * loads reversed in registers when all 16 pairs are whole (the two blocks
 * cannot overlap then), else cell by cell, and sets the cells 16k .. 16k+15
 * below d to NaN; each cell has one owner, so no two work-items touch the
 * same cell.  Global size (ceil(W / 16), H, D), or (H, D) with MIRROR_LINES
 * (rule ``mirror_lines``: a work-item per line on CPUs), which sets the
 * cells below d, swaps the line's whole blocks, then the pairs left. */
#ifndef MIRROR_LINES
#define MIRROR_LINES 0
#endif
/* Swap the whole block of pairs k0 .. k0 + 15 of a line (cells d + k0 .. d + k0 + 15 and
 * W - 16 - k0 .. W - 1 - k0), reversed in registers: the two blocks cannot overlap. */
static inline void mirror_block(__global vol_t *line, const int d, const int k0, const int W)
{
    const float16 a = VOL_LOAD16(line + d + k0);
    const float16 b = VOL_LOAD16(line + W - 16 - k0);
    vol_store16_partial(b.sFEDCBA9876543210, line + d + k0, 16);
    vol_store16_partial(a.sFEDCBA9876543210, line + W - 16 - k0, 16);
}

/* Swap the pairs i0 .. npairs - 1 of a line (cell d + i with cell W - 1 - i) one by one. */
static inline void mirror_pairs(__global vol_t *line, const int d, const int i0, const int npairs, const int W)
{
    for (int i = i0; i < npairs; ++i) {
        const float a = VOL_GET(line, d + i);
        VOL_SET(line, d + i, VOL_GET(line, W - 1 - i));
        VOL_SET(line, W - 1 - i, a);
    }
}

__kernel void disparity_right_volume(
    __global vol_t *cost, /* in: C_L, out: mirrored C_R; D x H x W */
    const int D,          /* disparity levels */
    const int H,          /* rows */
    const int W)          /* columns */
{
    /* MIRROR_LINES 1: one work-item walks its whole line (global size (H, D)):
     * the cells below d, the whole blocks, then the pairs left one by one; a
     * KITTI-sized volume on 2 Zen 3 cores, 28-34 ms (the tuner's run: 18
     * against 25 ms a work-item per block; BENCHMARKS.md), the same bits */
    const int y = get_global_id(MIRROR_LINES ? 0 : 1);
    const int d = get_global_id(MIRROR_LINES ? 1 : 2);
    const int kfirst = MIRROR_LINES ? 0 : (int)get_global_id(0) * 16;
    if (kfirst >= W || y >= H || d >= D)
        return;
    __global vol_t *line = cost + VIDX(d, y, 0, H, W);
    const int npairs = (W - d) / 2; /* pairs on the line */
#if MIRROR_LINES
    for (int x = 0; x < min(d, W); ++x) /* below d: invalid */
        VOL_SET(line, x, INVALID_COST);
    int k0 = 0;
    for (; k0 + 16 <= npairs; k0 += 16)
        mirror_block(line, d, k0, W);
    mirror_pairs(line, d, k0, npairs, W);
#else
    const int k0 = kfirst;
    for (int x = k0; x < min(k0 + 16, min(d, W)); ++x) /* below d: invalid */
        VOL_SET(line, x, INVALID_COST);
    if (k0 + 16 <= npairs)
        mirror_block(line, d, k0, W);
    else
        mirror_pairs(line, d, k0, npairs, W);
#endif
}

/* out(y, x) = in(y, W-1-x) for an int32 map.  Global size (W, H). */
__kernel void disparity_mirror(
    __global const int *in, /* H x W */
    __global int *out,      /* out: H x W */
    const int H,            /* rows */
    const int W)            /* columns */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    out[(size_t)y * W + x] = in[(size_t)y * W + (W - 1 - x)];
}
