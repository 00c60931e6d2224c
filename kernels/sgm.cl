/* sgm.cl - semi-global matching along one direction (paper, "Semiglobal
 * matching").  Driven by mccnn_cl/stages/sgm.py, which launches sgm_scan
 * once per direction and accumulates C_SGM = (1/4) sum_r C_r in the output.
 *
 * Required define: MAX_DISP >= D; it sizes the private array holding
 * C_r(p - r, .) of the scanline being walked.
 *
 * One work-item walks one scanline (a row for r = (+-1, 0), a column for
 * r = (0, +-1)) and keeps C_r(p - r, k) for k = 0..MAX_DISP in a private
 * array.  Entries of p - r beyond its valid range (k > x of p - r, k >= D)
 * hold +INFINITY, so they drop out of every minimum: validity is decided by
 * index (the NaN of invalid cost cells is never read).
 */
#include "common.h"

#ifndef MAX_DISP
#error "sgm.cl needs -D MAX_DISP=<upper bound of the disparity levels D>"
#endif

__kernel void sgm_scan(__global const float *cost,  /* D x H x W cost volume (NaN invalid) */
                       __global const float *img_l, /* H x W left image, gray in [0, 1] */
                       __global const float *img_r, /* H x W right image, gray in [0, 1] */
                       __global float *out,         /* D x H x W accumulated C_SGM */
                       const int D,                 /* disparity levels, <= MAX_DISP */
                       const int H,                 /* height */
                       const int W,                 /* width */
                       const int dx,                /* direction r = (dx, dy): p - r precedes p */
                       const int dy,
                       const float p1_small,        /* P1 when 0, 1, 2 gradients are large */
                       const float p1_one,
                       const float p1_both,
                       const float p2_small,        /* P2 likewise */
                       const float p2_one,
                       const float p2_both,
                       const float tau_so,          /* gradient threshold (paper 0.0625) */
                       const int outside_large,     /* 1: pd - r outside the right image = large D2 */
                       const int mode)              /* 0: out = C_r, 1: out += C_r, 2: out = (out + C_r) / 4 */
{
    const int line = get_global_id(0);
    const int vertical = dy != 0;
    if (line >= (vertical ? W : H))
        return;
    const int len = vertical ? H : W;
    float prev[MAX_DISP + 1];
    for (int k = 0; k <= MAX_DISP; ++k)
        prev[k] = INFINITY;
    float m = INFINITY; /* min_k C_r(p - r, k) */
    int pmax = -1;      /* largest valid disparity at p - r */
    for (int j = 0; j < len; ++j) {
        int x, y;
        if (vertical) {
            x = line;
            y = dy > 0 ? j : H - 1 - j;
        } else {
            y = line;
            x = dx > 0 ? j : W - 1 - j;
        }
        const int dmax = min(D - 1, x);
        float newm = INFINITY;
        if (j == 0) { /* first pixel of the path: C_r = C */
            for (int d = 0; d <= dmax; ++d) {
                const size_t i = VIDX(d, y, x, H, W);
                const float val = cost[i];
                prev[d] = val;
                newm = fmin(newm, val);
                if (mode == 0)
                    out[i] = val;
                else if (mode == 1)
                    out[i] += val;
                else
                    out[i] = (out[i] + val) * 0.25f;
            }
        } else {
            const int px = x - dx;
            const int py = y - dy;
            const int big_l = !(fabs(img_l[y * W + x] - img_l[py * W + px]) < tau_so);
            float pm1 = INFINITY; /* C_r(p - r, d - 1), before it was overwritten */
            for (int d = 0; d <= dmax; ++d) {
                const int xr = x - d;   /* pd */
                const int xrp = px - d; /* pd - r */
                const int big_r = xrp >= 0 && xrp < W
                                      ? !(fabs(img_r[y * W + xr] - img_r[py * W + xrp]) < tau_so)
                                      : outside_large;
                const int nbig = big_l + big_r;
                const float p1 = nbig == 0 ? p1_small : (nbig == 1 ? p1_one : p1_both);
                const float p2 = nbig == 0 ? p2_small : (nbig == 1 ? p2_one : p2_both);
                const float pd = prev[d];
                const float best = fmin(fmin(pd, m + p2), fmin(pm1, prev[d + 1]) + p1);
                const size_t i = VIDX(d, y, x, H, W);
                const float val = cost[i] - m + best;
                pm1 = pd;
                prev[d] = val;
                newm = fmin(newm, val);
                if (mode == 0)
                    out[i] = val;
                else if (mode == 1)
                    out[i] += val;
                else
                    out[i] = (out[i] + val) * 0.25f;
            }
            for (int d = dmax + 1; d <= pmax; ++d) /* p - r had more valid disparities than p */
                prev[d] = INFINITY;
        }
        if (mode == 0)
            for (int d = dmax + 1; d < D; ++d)
                out[VIDX(d, y, x, H, W)] = INVALID_COST;
        m = newm;
        pmax = dmax;
    }
}
