"""Numpy twins of the cost-refinement stages: cross arms, cross-based cost
aggregation (CBCA) and semi-global matching (SGM) - paper, "Stereo method".

Written for clarity (loops, sets), not speed; they are the executable
specification the OpenCL stages (:mod:`mccnn_cl.stages.cross`,
:mod:`mccnn_cl.stages.cbca`, :mod:`mccnn_cl.stages.sgm`) are tested against.
Usable on volumes of about 30 x 40 x 16 in a few seconds.

Conventions (see ``kernels/common.h``): cost volumes are float32 [d][y][x] on
the cropped domain; cell (d, y, x) compares left (x, y) with right (x - d, y)
and is INVALID when x - d < 0 (it holds NaN; validity is decided by index,
never by value).  Images are gray float32 in [0, 1], cropped to the volume's
H x W, so right pixel pd = (x - d, y) is ``img_r[y, x - d]``.

Arms are uint8 arrays [H][W][4] holding the lengths (left, right, up, down),
"up" meaning towards smaller y.
"""

from __future__ import annotations

import numpy as np

LEFT, RIGHT, UP, DOWN = 0, 1, 2, 3
#: (dx, dy) of each arm direction, in the order stored.
ARM_STEPS = ((-1, 0), (1, 0), (0, -1), (0, 1))


# ---------------------------------------------------------------- cross arms
def cross_arms(img, tau=0.0442, eta=4, include_neighbor=False):
    """Arm lengths (left, right, up, down) of every pixel, uint8 [H][W][4].

    Paper: the arm from p towards p_l = p + k*step extends for k = 1, 2, ...
    as long as |I(p) - I(p_l)| < tau, k < eta and p_l is inside the image; the
    length is the largest such k (0 if k = 1 already fails).  It stops at the
    first k that fails.

    ``include_neighbor`` (released code, off by default): the +-1 neighbour is
    always part of the arm when it is inside the image, whatever tau and eta.
    """
    img = np.asarray(img, dtype=np.float32)
    H, W = img.shape
    tau = np.float32(tau)
    out = np.zeros((H, W, 4), np.uint8)
    for y in range(H):
        for x in range(W):
            for a, (dx, dy) in enumerate(ARM_STEPS):
                k = 0
                while True:
                    n = k + 1
                    xx, yy = x + n * dx, y + n * dy
                    if not (0 <= xx < W and 0 <= yy < H):
                        break
                    if not (include_neighbor and n == 1):
                        # the comparison in float32, exactly as the kernel does it
                        if not (n < eta and np.abs(img[y, x] - img[yy, xx]) < tau):
                            break
                    k = n
                    if k == 255:
                        break
                out[y, x, a] = k
    return out


# ---------------------------------------------------------------------- CBCA
def support_region(arms, x, y):
    """U(p) for p = (x, y): the union of the horizontal arms of all pixels q
    on p's vertical arm, as a set of (x', y')."""
    region = set()
    for yy in range(y - int(arms[y, x, UP]), y + int(arms[y, x, DOWN]) + 1):
        for xx in range(x - int(arms[yy, x, LEFT]), x + int(arms[yy, x, RIGHT]) + 1):
            region.add((xx, yy))
    return region


def combined_support(arms_l, arms_r, x, y, d, cache_l=None, cache_r=None):
    """U_d(p) = {q | q in U^L(p), qd in U^R(pd)} as a sorted list of (x', y').

    Built literally from the set definition: enumerate q in U^L(p) and keep
    those whose partner qd = q - (d, 0) lies in the right image's U^R(pd).
    """
    ul = cache_l[(x, y)] if cache_l is not None else support_region(arms_l, x, y)
    ur = cache_r[(x - d, y)] if cache_r is not None else support_region(arms_r, x - d, y)
    return sorted((qx, qy) for (qx, qy) in ul if (qx - d, qy) in ur)


def cbca(cost, arms_l, arms_r, iterations=4):
    """Cross-based cost aggregation, ``iterations`` times.

    C^i(p, d) = mean of C^{i-1}(q, d) over q in U_d(p); invalid cells
    (d > x) stay NaN.  For arms that stay inside the image every q of U_d(p)
    of a valid p is itself valid (q's partner qd lies in the right image); the
    validity check below only makes that explicit.  Returns float32.
    """
    cost = np.asarray(cost, dtype=np.float32)
    D, H, W = cost.shape
    cache_l = {(x, y): support_region(arms_l, x, y) for y in range(H) for x in range(W)}
    cache_r = {(x, y): support_region(arms_r, x, y) for y in range(H) for x in range(W)}
    # The support U_d(p) does not change between iterations: collect it once
    # as flat index arrays.
    regions = {}
    for d in range(D):
        for y in range(H):
            for x in range(d, W):
                q = combined_support(arms_l, arms_r, x, y, d, cache_l, cache_r)
                qs = [(qx, qy) for (qx, qy) in q if qx - d >= 0]  # valid by index
                regions[(d, y, x)] = (np.array([qy for _, qy in qs]), np.array([qx for qx, _ in qs]))
    cur = cost.astype(np.float64)
    for _ in range(iterations):
        nxt = np.full_like(cur, np.nan)
        for (d, y, x), (qy, qx) in regions.items():
            nxt[d, y, x] = cur[d, qy, qx].mean()
        cur = nxt
    return cur.astype(np.float32)


# ----------------------------------------------------------------------- SGM
#: The four paths r of the paper, as (dx, dy): p - r is the previous pixel.
SGM_DIRECTIONS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def sgm_penalties(d1, d2, pi1=1.0, pi2=32.0, tau_so=0.0625, q1=4.0, q2=10.0, v=2.0,
                  vertical=False, variant="paper", p2_times_pi1=False, step_scale=None):
    """(P1, P2) for gradients D1 (left image) and D2 (right image).

    ``variant="paper"``: divide both by q1 when exactly one gradient is
    >= tau_so, by q2 when both are.  ``variant="code"`` (released code): by q1
    when one is, by q1*q2 when both are.  ``p2_times_pi1``: P2 = Pi1*Pi2
    instead of Pi2 (same at Pi1 = 1).  P1 is divided by v on vertical paths.
    ``step_scale`` s: each penalty rounded to a step of 1 / s (its float32 times
    s rounded to nearest even, as the 16-bit sweeps' host rounds the table).
    """
    big = int(not (d1 < tau_so)) + int(not (d2 < tau_so))
    if big == 0:
        f = 1.0
    elif big == 1:
        f = q1
    else:
        f = q2 if variant == "paper" else q1 * q2
    p1 = pi1 / f
    p2 = (pi1 * pi2 if p2_times_pi1 else pi2) / f
    if vertical:
        p1 = p1 / v
    if step_scale is not None:
        p1, p2 = (float(np.round(np.float32(p) * step_scale) / step_scale) for p in (p1, p2))
    return p1, p2


def sgm_direction(cost, img_l, img_r, r, outside_large=True, **penalties):
    """C_r for one path direction r = (dx, dy), float64 [D][H][W] (NaN where invalid).

    C_r(p, d) = C(p, d) - min_k C_r(p-r, k)
                + min{C_r(p-r, d), C_r(p-r, d-1) + P1, C_r(p-r, d+1) + P1,
                      min_k C_r(p-r, k) + P2}
    over valid cells only: at p the disparities d <= x exist; terms naming a
    cell of p - r that is invalid (or d - 1 < 0, d + 1 >= D) are left out of
    the minima.  The first pixel of each path (p - r outside the volume) has
    C_r = C.  D2 = |I^R(pd) - I^R(pd - r)|; when pd - r is outside the right
    image D2 counts as large (>= tau_so) if ``outside_large`` (the released
    code's choice, default) and as small otherwise.
    """
    cost = np.asarray(cost, dtype=np.float32)
    img_l = np.asarray(img_l, dtype=np.float32)
    img_r = np.asarray(img_r, dtype=np.float32)
    D, H, W = cost.shape
    dx, dy = r
    vertical = dy != 0
    out = np.full((D, H, W), np.nan)
    xs = range(W) if dx >= 0 else range(W - 1, -1, -1)
    ys = range(H) if dy >= 0 else range(H - 1, -1, -1)
    for y in ys:
        for x in xs:
            px, py = x - dx, y - dy  # p - r
            dmax = min(D - 1, x)
            if not (0 <= px < W and 0 <= py < H):
                for d in range(dmax + 1):
                    out[d, y, x] = cost[d, y, x]
                continue
            pmax = min(D - 1, px)  # valid disparities at p - r
            prev = out[:, py, px]
            m = min(prev[k] for k in range(pmax + 1))
            # float32 gradients, so the tau_so decisions match the kernel exactly
            d1 = np.abs(img_l[y, x] - img_l[py, px])
            for d in range(dmax + 1):
                xr, xrp = x - d, px - d  # pd and pd - r in the right image
                if 0 <= xrp < W:
                    d2 = np.abs(img_r[y, xr] - img_r[py, xrp])
                else:
                    d2 = np.float32(np.inf if outside_large else 0.0)
                p1, p2 = sgm_penalties(d1, d2, vertical=vertical, **penalties)
                cands = [m + p2]
                if d <= pmax:
                    cands.append(prev[d])
                if 0 <= d - 1 <= pmax:
                    cands.append(prev[d - 1] + p1)
                if d + 1 <= pmax:
                    cands.append(prev[d + 1] + p1)
                out[d, y, x] = float(cost[d, y, x]) - m + min(cands)
    return out


def sgm(cost, img_l, img_r, pi1=1.0, pi2=32.0, tau_so=0.0625, q1=4.0, q2=10.0, v=2.0,
        variant="paper", p2_times_pi1=False, outside_large=True, step_scale=None):
    """C_SGM = mean of C_r over the four directions (float32, NaN where invalid);
    ``step_scale``: the penalties rounded (:func:`sgm_penalties`)."""
    pen = dict(pi1=pi1, pi2=pi2, tau_so=tau_so, q1=q1, q2=q2, v=v, variant=variant,
               p2_times_pi1=p2_times_pi1, step_scale=step_scale)
    total = sum(sgm_direction(cost, img_l, img_r, r, outside_large, **pen) for r in SGM_DIRECTIONS)
    return (total / 4.0).astype(np.float32)


def sgm_q16(cost, img_l, img_r, bound, s, **kw):
    """What SGM's 16-bit sweeps (sgm_paired_q16, scale ``s``, costs bounded by
    ``bound``) compute: float SGM of the costs clamped to [-bound, bound] and
    rounded to steps of 1 / s, with every penalty rounded likewise."""
    s32 = np.float32(s)
    c = np.round(np.clip(np.asarray(cost, dtype=np.float32), -bound, bound) * s32) / s32
    return sgm(c.astype(np.float32), img_l, img_r, step_scale=s, **kw)
