"""SGM's paired sweeps in 16-bit lanes (sgm_paired_q16, SGM(int16=True)).

The kernel computes SGM of the costs and penalties rounded to steps of 1 / s
(s a power of two, mccnn_cl.stages.sgm.q16_scale), in integers that never
overflow; the result is exactly float SGM of those rounded inputs, so the
reference (float64, mccnn_cl.reference.aggregation.sgm) on the rounded inputs
must give the same bits: no tolerance.  A wrong penalty, an off-by-one in a
minimum or an overflow moves values by whole steps.
"""

import numpy as np
import pytest

import mccnn_cl.reference.aggregation as agg
from conftest import POISON
from helpers import blocky_image, invalid_mask, kitti_crop, random_volume
from mccnn_cl.stages.sgm import SGM, penalty_table, q16_scale
from test_sgm import mirrored, with_invalid

KW = dict(pi1=1.3, pi2=18.1, tau_so=0.08, q1=4.0, q2=2.0, v=1.5, variant="code")


def run_q16(ctx, cost, img_l, img_r, bound, mirror=False, **kw):
    D, H, W = cost.shape
    d_out = ctx.empty(cost.nbytes)
    ctx.fill(d_out, POISON, cost.nbytes)
    stage = SGM(ctx, paired=True)
    stage(ctx.to_device(cost), ctx.to_device(img_l), ctx.to_device(img_r), D, H, W, out=d_out, mirror=mirror,
          cost_bound=bound, **kw)
    assert stage.last_scale is not None
    return ctx.from_device(d_out, cost.shape), stage.last_scale


@pytest.mark.parametrize("D,H,W", [(20, 9, 37), (40, 6, 70), (37, 5, 45), (5, 1, 40), (4, 12, 1), (1, 1, 1),
                                   (33, 4, 64), (64, 3, 48)])
def test_q16_is_float_sgm_of_the_rounded_inputs(ctx, D, H, W):
    """Odd sizes, D > W, a single row or column, partial chunks and tiles: the same bits as the
    reference on the rounded inputs, NaN exactly where x < d."""
    rng = np.random.default_rng(D * 131 + H * 7 + W)
    cost = random_volume(rng, D, H, W, scale=2.0) - np.float32(1.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
    for kw in (KW, dict(pi1=4.0, pi2=55.72, tau_so=0.02, q1=3.0, q2=2.5, v=1.5, variant="code"),
               dict(pi1=1.0, pi2=32.0, tau_so=0.0625, q1=4.0, q2=10.0, v=2.0, variant="paper")):
        got, s = run_q16(ctx, cost, img_l, img_r, 1.0, **kw)
        want = agg.sgm_q16(cost, img_l, img_r, 1.0, s, **kw)
        np.testing.assert_array_equal(np.isnan(got), invalid_mask(D, H, W))
        np.testing.assert_array_equal(got[~np.isnan(got)], want[~np.isnan(want)], err_msg=str(kw))


def test_q16_mirrored_reads_are_the_explicit_mirror(ctx):
    """mirror=True on C gives the bits of the 16-bit sweeps on C_R' made explicitly (C's cells x < d
    hold +1000 and must not be read)."""
    for D, H, W in ((16, 9, 53), (40, 5, 70), (9, 2, 8)):
        rng = np.random.default_rng(D + H + W)
        cost = random_volume(rng, D, H, W, scale=2.0) - np.float32(1.0)
        img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
        want, _ = run_q16(ctx, mirrored(cost), img_l, img_r, 1.0, **KW)
        got, _ = run_q16(ctx, with_invalid(cost, 1000.0), img_l, img_r, 1.0, mirror=True, **KW)
        np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))


def test_q16_clamps_costs_beyond_the_bound_and_nan_counts_as_the_bound(ctx):
    """A cost beyond the declared bound is the bound (both signs); a NaN cost in a valid cell too."""
    rng = np.random.default_rng(5)
    D, H, W = 24, 6, 40
    cost = random_volume(rng, D, H, W, scale=2.0) - np.float32(1.0)
    img_l, img_r = blocky_image(rng, H, W), blocky_image(rng, H, W)
    wild = cost.copy()
    wild[3, 2, 30], wild[5, 4, 20], wild[0, 1, 10] = 7.5, -9.0, np.nan
    tame = cost.copy()
    tame[3, 2, 30], tame[5, 4, 20], tame[0, 1, 10] = 1.0, -1.0, 1.0
    a, _ = run_q16(ctx, wild, img_l, img_r, 1.0, **KW)
    b, _ = run_q16(ctx, tame, img_l, img_r, 1.0, **KW)
    np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))


def test_q16_on_a_kitti_crop_is_close_to_float_sgm(ctx, shared_data):
    """Real images, an fst-like cost (absolute differences mapped to [-1, 1]): exact against the rounded
    reference, and within a few steps of 1 / s of float SGM of the unrounded costs."""
    img_l, img_r = kitti_crop(shared_data, 150, 400, 12, 60)
    D = 32
    H, W = img_l.shape
    cost = np.full((D, H, W), np.nan, np.float32)
    for d in range(D):
        cost[d, :, d:] = 2.0 * np.abs(img_l[:, d:] - img_r[:, :W - d]) - 1.0
    got, s = run_q16(ctx, cost, img_l, img_r, 1.0, **KW)
    want = agg.sgm_q16(cost, img_l, img_r, 1.0, s, **KW)
    np.testing.assert_array_equal(got[~np.isnan(got)], want[~np.isnan(want)])
    exact = agg.sgm(cost, img_l, img_r, **KW)
    assert np.nanmax(np.abs(got - exact)) < 8.0 / s


def test_q16_scale():
    """s: the largest power of two with (2 B + 2 P2) s <= 32000; None where B s would give fewer than
    64 steps or the bound is unusable; the float sweeps run then."""
    kitti_fst = penalty_table(4.0, 55.72, 3.0, 2.5, 1.5, False, "code"), \
        penalty_table(4.0, 55.72, 3.0, 2.5, 1.5, True, "code")
    assert q16_scale(1.0, *kitti_fst) == 256.0  # 32000 / (2 + 2 * 55.72) = 282.1
    census = penalty_table(1.0, 32.0), penalty_table(1.0, 32.0, vertical=True)
    assert q16_scale(80.0, *census) == 128.0  # 32000 / 224 = 142.9
    assert q16_scale(0.5, *kitti_fst) == 256.0  # 128 steps
    assert q16_scale(0.2, *kitti_fst) is None  # 51 steps
    for bad in (None, 0.0, -1.0, float("nan"), float("inf")):
        assert q16_scale(bad, *census) is None


def test_magnitude_bound_of_each_cost():
    """cost_bound of the 16-bit sweeps: max |floor|, |ceiling| of the cost; None without a ceiling."""
    from mccnn_cl.costs.base import MatchingCost
    from mccnn_cl.costs.census import CensusCost
    from mccnn_cl.costs.fst import FstCost
    from mccnn_cl.costs.network import PaperCost

    assert CensusCost.magnitude_bound(CensusCost.__new__(CensusCost)) == 80.0
    assert FstCost.magnitude_bound(FstCost.__new__(FstCost)) == 1.0
    assert PaperCost.magnitude_bound(PaperCost.__new__(PaperCost)) == 1.0
    assert MatchingCost().magnitude_bound() is None


def test_q16_falls_back_to_float_without_a_bound(ctx):
    """No cost_bound: the float sweeps, bit for bit."""
    rng = np.random.default_rng(2)
    D, H, W = 8, 4, 20
    cost = random_volume(rng, D, H, W)
    img = blocky_image(rng, H, W)
    stage = SGM(ctx, paired=True)
    out = stage(ctx.to_device(cost), ctx.to_device(img), ctx.to_device(img), D, H, W, **KW)
    assert stage.last_scale is None
    float_out = SGM(ctx, paired=True)(ctx.to_device(cost), ctx.to_device(img), ctx.to_device(img), D, H, W, **KW)
    np.testing.assert_array_equal(ctx.from_device(out, cost.shape).view(np.uint32),
                                  ctx.from_device(float_out, cost.shape).view(np.uint32))


def test_pipeline_sgm_int16_on_tsukuba(ctx, shared_data):
    """StereoMatcher(sgm_int16=True): the census pipeline on Tsukuba runs SGM's 16-bit sweeps on both
    references (cost bound 80 bits: s = 128) and its map differs from the float one in few pixels,
    by little; the errors against the ground truth stay within 0.3 points."""
    from test_pipeline import bad_rate, load_pair

    from mccnn_cl.pipeline import StereoMatcher

    left, right, gt, mask, ndisp = load_pair(shared_data, "Tsukuba")
    maps, scales = {}, {}
    for q16 in (False, True):
        m = StereoMatcher(cost="census", max_disparity=ndisp, device=ctx, sgm_int16=q16)
        if not m.sgm.paired:
            pytest.skip("the device's SGM stage has no paired sweeps (the 16-bit form is theirs)")
        maps[q16] = m.compute(left, right)
        scales[q16] = m.sgm.last_scale
    assert scales == {False: None, True: 128.0}
    differ = np.abs(maps[True] - maps[False]) > 0.5
    assert differ.mean() < 0.02, differ.mean()
    assert abs(bad_rate(maps[True], gt, mask) - bad_rate(maps[False], gt, mask)) < 0.3
