/* interpolate.cl - filling the pixels the left-right check rejected
 * (paper, "Interpolation").  Driven by mccnn_cl/stages/disparity.py
 * (class Interpolate); numpy twin: reference.disparity.interpolate.
 *
 * Both fills read the ORIGINAL D^L and labels (never values written by this
 * kernel), so the result does not depend on the order of the work-items.
 *
 * occlusion: the value of the first pixel labelled correct when moving left
 *   along the row; if there is none, moving right (the released code's
 *   fallback); if the row has no correct pixel, D^L(p) is kept.
 * mismatch: for each of the 16 direction vectors dir[k] (a table of float
 *   pairs, see stages/disparity.py), walk q_n = round(p + n * dir[k]),
 *   n = 1, 2, ... until q_n leaves the image; the first q_n that stops the
 *   walk contributes D^L(q_n).  The walk stops at a correct pixel
 *   (stop_at_any = 0, paper) or at any non-mismatch pixel (stop_at_any = 1,
 *   released code).  The result is the upper median (element n/2 of the
 *   ascending sort, 0-based) of the n <= 16 values, an integer; n = 0 keeps
 *   D^L(p).  round() is OpenCL's: half-way cases away from zero.
 *
 * Columns x < lo are not part of the image: the working frame's padding of a
 * range with M < 0 (mccnn_cl/disprange.py; lo = 0 on the real pair).  A walk
 * that reaches one ends as at the map's edge, so padding pixels neither stop
 * a walk nor give a value (a walk never comes back from the padding: its
 * steps keep the sign of dx), and q_n's column is rounded in the real
 * image's columns, lo + round(x - lo + n dx) (half-way cases at -0.5 round
 * away from zero there, not at lo - 0.5), so D_INT of the real columns is
 * the one of the real pair's maps.
 */
#include "common.h"

#define LABEL_CORRECT 0
#define LABEL_MISMATCH 1
#define LABEL_OCCLUSION 2
#define NUM_DIRECTIONS 16

/* Global size (W, H). */
__kernel void interpolate_fill(
    __global const int *disp,      /* D^L, H x W */
    __global const int *labels,    /* LABEL_* from disparity_lr_check, H x W */
    __global const float *dirs,    /* 16 (dx, dy) step vectors */
    __global int *out,             /* out: D_INT, H x W */
    const int H,                   /* rows */
    const int W,                   /* columns */
    const int stop_at_any,         /* 0: stop at correct (paper); 1: at non-mismatch (code) */
    const int lo)                  /* first real column (columns < lo: padding) */
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= W || y >= H)
        return;
    const size_t row = (size_t)y * W;
    const int label = labels[row + x];
    int value = disp[row + x];

    if (label == LABEL_OCCLUSION) {
        int xx = x - 1;
        while (xx >= lo && labels[row + xx] != LABEL_CORRECT)
            xx--;
        if (xx < lo) {
            xx = max(x, lo - 1) + 1;
            while (xx < W && labels[row + xx] != LABEL_CORRECT)
                xx++;
        }
        if (xx >= lo && xx < W)
            value = disp[row + xx];
    } else if (label == LABEL_MISMATCH) {
        int vals[NUM_DIRECTIONS];
        int n = 0;
        for (int k = 0; k < NUM_DIRECTIONS; k++) {
            const float dx = dirs[2 * k];
            const float dy = dirs[2 * k + 1];
            for (int s = 1;; s++) {
                /* rounded in the real image's columns (x - lo): half-way cases
                 * then round as they do there (lo = 0: the plain position) */
                const int qx = lo + (int)round((float)(x - lo) + (float)s * dx);
                const int qy = (int)round((float)y + (float)s * dy);
                if (qx < lo || qx >= W || qy < 0 || qy >= H)
                    break;
                const int lq = labels[(size_t)qy * W + qx];
                if (lq == LABEL_CORRECT || (stop_at_any && lq != LABEL_MISMATCH)) {
                    /* insertion into the sorted prefix vals[0..n) */
                    const int v = disp[(size_t)qy * W + qx];
                    int i = n;
                    while (i > 0 && vals[i - 1] > v) {
                        vals[i] = vals[i - 1];
                        i--;
                    }
                    vals[i] = v;
                    n++;
                    break;
                }
            }
        }
        if (n > 0)
            value = vals[n / 2];
    }
    out[row + x] = value;
}
