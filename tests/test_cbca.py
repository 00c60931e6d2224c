"""CBCA: kernels/cbca.cl against mccnn_cl.reference.aggregation.cbca.

Tolerance: the reference averages in float64; the kernels use compensated
float32 prefix sums, so each window sum is exact to a few ulp of its own
magnitude and one iteration's mean to ~1e-7 relative; after 4 iterations the
error stays below 1e-6 of the cost range.  We allow 1e-5 of the cost range
(atol), far below any cost difference that matters and far above the
observed error; an off-by-one window or a NaN cell entering a sum would
exceed it by orders of magnitude.  NaN positions must match exactly.
"""

import cv2
import numpy as np
import pytest

from conftest import POISON
from helpers import ad_volume, blocky_image, invalid_mask, random_volume  # noqa: F401
from mccnn_cl.reference.aggregation import cbca, cross_arms
from mccnn_cl.pipeline import Hyperparameters
from mccnn_cl.stages.cbca import CBCA, MULTI_K, SHORT_MAX, path_scratch_bytes
from mccnn_cl.stages.cross import CrossArms, arms_to_device, max_arm


#: The implementations: (short-arm vector kernels allowed, fused short-arm
#: kernel allowed, multi-iteration fused kernel allowed, max_arm); None = the
#: tight bound of the arms at hand.  Short + fused + multi + tight is the CPU
#: default (up to MULTI_K iterations per launch), short + fused + tight the
#: one-iteration fused kernel, short + tight the two-pass short-arm kernels;
#: generic with 255 and with the tight bound (ring wrap-around) is the
#: running-sum path.
IMPLS = [(True, True, True, None), (True, True, False, None), (True, False, False, None),
         (False, False, False, None), (False, False, False, 255)]


def run_cbca(ctx, cost, arms_l, arms_r, iterations=4, short=True, max_arm=None, fused=True, multi=True):
    D, H, W = cost.shape
    if max_arm is None:
        max_arm = int(max(arms_l.max(), arms_r.max()))
    d_out = ctx.empty(cost.nbytes)
    ctx.fill(d_out, POISON, cost.nbytes)
    d_cost = ctx.to_device(cost)
    CBCA(ctx, short=short, fused=fused, multi=multi)(d_cost, arms_to_device(ctx, arms_l), arms_to_device(ctx, arms_r),
                                                     D, H, W, iterations=iterations, max_arm=max_arm, out=d_out)
    got = ctx.from_device(d_out, cost.shape)
    np.testing.assert_array_equal(ctx.from_device(d_cost, cost.shape), cost)  # input untouched
    return got


def compare(got, want, cost):
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_array_equal(np.isnan(got), invalid_mask(*cost.shape))
    rng_ = np.nanmax(cost) - np.nanmin(cost)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * max(rng_, 1e-30))


def check(ctx, cost, img_l, img_r, iterations=4, eta=4, include_neighbor=False):
    """Every implementation against the reference; returns (fast path, reference)."""
    arms_l = cross_arms(img_l, eta=eta, include_neighbor=include_neighbor)
    arms_r = cross_arms(img_r, eta=eta, include_neighbor=include_neighbor)
    want = cbca(cost, arms_l, arms_r, iterations)
    results = []
    for short, fused, multi, bound in IMPLS:
        got = run_cbca(ctx, cost, arms_l, arms_r, iterations, short, bound, fused, multi)
        compare(got, want, cost)
        results.append(got)
    if max(arms_l.max(), arms_r.max()) <= SHORT_MAX:
        # both fused kernels do the two short passes' float operations in the
        # same order: bit-identical (NaN payloads included)
        np.testing.assert_array_equal(results[0].view(np.uint32), results[2].view(np.uint32))
        np.testing.assert_array_equal(results[1].view(np.uint32), results[2].view(np.uint32))
    return results[0], want


@pytest.mark.gpu_check
@pytest.mark.slow
def test_random_odd_size(ctx):
    rng = np.random.default_rng(1)
    D, H, W = 16, 37, 53
    cost = random_volume(rng, D, H, W)
    img_l, img_r = blocky_image(rng, H, W), blocky_image(rng, H, W)
    got, _ = check(ctx, cost, img_l, img_r)
    # non-trivial: aggregation changed the costs, and not into one constant
    valid = ~np.isnan(got)
    assert np.abs(got[valid] - cost[valid]).max() > 0.05
    assert got[valid].std() > 0.01


@pytest.mark.slow
def test_random_long_arms_neighbor_variant_and_tight_bound(ctx):
    rng = np.random.default_rng(2)
    D, H, W = 9, 23, 31
    cost = random_volume(rng, D, H, W, scale=50.0) - 20.0  # negative costs too
    img_l, img_r = blocky_image(rng, H, W, 6, 0.01), blocky_image(rng, H, W, 5, 0.01)
    arms_l = cross_arms(img_l, eta=9, include_neighbor=True)
    assert arms_l.max() == max_arm(9, True) == 8  # the longest arms the short kernels take
    check(ctx, cost, img_l, img_r, iterations=2, eta=9, include_neighbor=True)
    # arms beyond the short kernels' reach: the running-sum kernels (tight ring and 255)
    img = np.full((H, W), 0.5, np.float32)
    img[:, 17] = 0.9
    got, _ = check(ctx, cost, img, img, iterations=1, eta=15)
    assert cross_arms(img, eta=15).max() == 14


@pytest.mark.parametrize("rel_l,rel_r,y0,x0", [
    ("middlebury/Cones/im0.png", "middlebury/Cones/im1.png", 150, 200),
    ("kitti2015/training/image_2/000000_10.png", "kitti2015/training/image_3/000000_10.png", 200, 500),
])
@pytest.mark.gpu_check
def test_real_images_ad_volume(ctx, shared_data, rel_l, rel_r, y0, x0):
    H, W, D = 24, 41, 16
    imgs = []
    for rel in (rel_l, rel_r):
        img = cv2.imread(str(shared_data / rel), cv2.IMREAD_GRAYSCALE)
        assert img is not None, rel
        imgs.append(img[y0:y0 + H, x0:x0 + W].astype(np.float32) / 255.0)
    assert imgs[0].std() > 0.02
    cost = ad_volume(imgs[0], imgs[1], D)
    check(ctx, cost, imgs[0], imgs[1])


@pytest.mark.gpu_check
@pytest.mark.slow
def test_d_at_least_w_single_row_single_column(ctx):
    rng = np.random.default_rng(3)
    for D, H, W in [(20, 7, 12), (5, 1, 40), (4, 30, 1), (1, 1, 1), (3, 2, 2), (7, 5, 300), (40, 3, 70)]:
        cost = random_volume(rng, D, H, W)
        check(ctx, cost, blocky_image(rng, H, W), blocky_image(rng, H, W), iterations=3)


def test_constant_images_arms_hit_eta_and_borders(ctx):
    rng = np.random.default_rng(4)
    D, H, W = 6, 15, 19
    cost = random_volume(rng, D, H, W)
    img = np.full((H, W), 0.3, np.float32)
    got, _ = check(ctx, cost, img, img, iterations=1)
    # with full arms (3 px) one iteration is a 7x7 box mean clipped to the valid cells
    d, y, x = 2, 7, 9
    np.testing.assert_allclose(got[d, y, x], cost[d, 4:11, 6:13].mean(), rtol=1e-6)
    d, y, x = 4, 0, 5  # top border, first valid column
    np.testing.assert_allclose(got[d, y, x], cost[d, 0:4, 4:9].mean(), rtol=1e-6)


def test_constant_volume_stays_constant_and_zero_iterations(ctx):
    rng = np.random.default_rng(5)
    D, H, W = 8, 21, 26
    cost = np.full((D, H, W), 0.7, np.float32)
    cost[invalid_mask(D, H, W)] = np.nan
    img_l, img_r = blocky_image(rng, H, W), blocky_image(rng, H, W)
    arms_l, arms_r = cross_arms(img_l), cross_arms(img_r)
    valid = ~invalid_mask(D, H, W)
    for short, fused, multi, bound in IMPLS:
        got = run_cbca(ctx, cost, arms_l, arms_r, 4, short, bound, fused, multi)
        np.testing.assert_allclose(got[valid], 0.7, rtol=1e-6)
        assert np.isnan(got[~valid]).all()
        np.testing.assert_array_equal(run_cbca(ctx, cost, arms_l, arms_r, 0, short, bound, fused, multi), cost)


@pytest.mark.parametrize("fused,multi", [(True, True), (True, False), (False, False)])
def test_in_place(ctx, fused, multi):
    rng = np.random.default_rng(6)
    D, H, W = 7, 13, 37
    cost = random_volume(rng, D, H, W)
    img_l, img_r = blocky_image(rng, H, W), blocky_image(rng, H, W)
    arms_l, arms_r = cross_arms(img_l), cross_arms(img_r)
    d_cost = ctx.empty(cost.nbytes)
    ctx.cl.enqueue_copy(ctx.queue, d_cost, cost)
    # arms straight from the CrossArms stage this time
    d_al = CrossArms(ctx)(ctx.to_device(img_l), H, W)
    d_ar = CrossArms(ctx)(ctx.to_device(img_r), H, W)
    stage = CBCA(ctx, fused=fused, multi=multi)
    out = stage(d_cost, d_al, d_ar, D, H, W, max_arm=max_arm(4), out=d_cost)
    assert out is d_cost
    compare(ctx.from_device(d_cost, cost.shape), cbca(cost, arms_l, arms_r, 4), cost)
    assert CBCA.scratch_volumes == 0


@pytest.mark.parametrize("multi", [True, False])
def test_scratch_reused_across_sizes(ctx, multi):
    """The fused paths' scratch rings grow for a wider/deeper volume and are
    reused for a smaller one (stale ring contents must not leak into sums)."""
    rng = np.random.default_rng(7)
    stage = CBCA(ctx, fused=True, multi=multi)
    # one-iteration kernel: D x (2A + 1) x W float row sums + byte counts
    assert path_scratch_bytes(228, 1232, max_arm(4), "fused") == 5 * 228 * 7 * 1232
    # multi-iteration kernel (MULTI_K = 4, A = 3, W rounded up to 16 = 1232):
    # per plane 4 x 7 float rows, 3 x 3 + 1 ushort rows (5 float rows), 5 x (4 x 3 + 1) byte rows,
    # 3 rows of 1232 + 32 floats: 58.8 MB, 14.3 % of a 228 x 367 x 1232 float32 volume
    assert MULTI_K == 4
    assert path_scratch_bytes(228, 1232, max_arm(4), "multi") == 228 * (4 * 33 * 1232 + 65 * 1232 + 4 * 3 * 1264)
    assert path_scratch_bytes(228, 1232, 255, "running") == 0
    assert path_scratch_bytes(228, 1232, max_arm(4), "short") == 0
    # the stage's own figure follows its path: the planner's question
    params = Hyperparameters()
    assert stage.scratch_bytes(228, 1232, params) == path_scratch_bytes(228, 1232, 3, "multi" if multi else "fused")
    assert CBCA(ctx, fused=False).scratch_bytes(228, 1232, params) == 0
    assert stage.scratch_bytes(228, 1232, Hyperparameters(cbca_eta=10)) == 0  # arms up to 9 px: running sums
    for D, H, W in [(6, 9, 40), (11, 12, 70), (5, 8, 33)]:
        cost = random_volume(rng, D, H, W)
        img_l, img_r = blocky_image(rng, H, W), blocky_image(rng, H, W)
        arms_l, arms_r = cross_arms(img_l), cross_arms(img_r)
        d_out = ctx.empty(cost.nbytes)
        ctx.fill(d_out, POISON, cost.nbytes)
        stage(ctx.to_device(cost), arms_to_device(ctx, arms_l), arms_to_device(ctx, arms_r), D, H, W,
              iterations=2, max_arm=max_arm(4), out=d_out)
        compare(ctx.from_device(d_out, cost.shape), cbca(cost, arms_l, arms_r, 2), cost)
    sizes = (stage._multi or stage._ring)[0]  # what the stage really allocated, for the largest volume
    allocated = sum(sizes) if multi else sizes
    assert allocated == path_scratch_bytes(11, 70, max_arm(4), "multi" if multi else "fused")


def multi_vs_single(ctx, cost, arms_l, arms_r, iterations, in_place, select_add=None):
    """The multi-iteration kernel's result (out of place into a poisoned
    buffer, or in place; its masked terms in the form ``select_add``) and the
    one-iteration fused kernel's, iterated."""
    D, H, W = cost.shape
    A = int(max(arms_l.max(), arms_r.max()))
    d_l, d_r = arms_to_device(ctx, arms_l), arms_to_device(ctx, arms_r)
    res = []
    for multi, inp in ((True, in_place), (False, False)):
        d_cost = ctx.to_device(cost)
        if inp:
            out = d_cost
        else:
            out = ctx.empty(cost.nbytes)
            ctx.fill(out, POISON, cost.nbytes)
        stage = CBCA(ctx, fused=True, multi=multi, select_add=select_add)
        assert stage.fused and stage.multi == multi
        assert stage(d_cost, d_l, d_r, D, H, W, iterations=iterations, max_arm=A, out=out) is out
        res.append(ctx.from_device(out, cost.shape))
    return res


@pytest.mark.parametrize("in_place", [False, True])
@pytest.mark.slow
def test_multi_iteration_counts_random(ctx, in_place):
    """cbca_fused_multi_short (MULTI_K iterations per launch, then a shorter
    launch) is bit-identical to iterating cbca_fused_short, for iteration
    counts below, at and above MULTI_K, arms up to SHORT_MAX and 0, D >= W,
    one row, W not a multiple of 16; and within the reference tolerance."""
    rng = np.random.default_rng(11)
    for (D, H, W), eta, nb, block, its in [((9, 29, 45), 4, False, 3, (1, 2, 3, 4, 5, 9)),
                                           ((7, 19, 37), 9, True, 6, (3, 6)),
                                           ((12, 5, 10), 4, False, 3, (4,)),
                                           ((3, 1, 70), 4, False, 3, (2,)),
                                           ((4, 11, 21), 1, False, 3, (5,))]:
        cost = random_volume(rng, D, H, W)
        img_l, img_r = blocky_image(rng, H, W, block, 0.01), blocky_image(rng, H, W, block, 0.01)
        arms_l = cross_arms(img_l, eta=eta, include_neighbor=nb)
        arms_r = cross_arms(img_r, eta=eta, include_neighbor=nb)
        if H * W > 100:  # the longest arms the bound allows occur (0 for eta = 1)
            assert max(arms_l.max(), arms_r.max()) == max_arm(eta, nb)
        for it in its:
            got, single = multi_vs_single(ctx, cost, arms_l, arms_r, it, in_place)
            np.testing.assert_array_equal(got.view(np.uint32), single.view(np.uint32))
            compare(got, cbca(cost, arms_l, arms_r, it), cost)


@pytest.mark.parametrize("select_add", [False, True])
def test_multi_masked_term_forms_same_bits(ctx, select_add):
    """Both forms of the multi kernel's masked terms (CBCA_SELECT_ADD: a select
    of s and s + v, or s plus a select of 0 and v) give the one-iteration fused
    kernel's bits, arms 0 .. SHORT_MAX - 1 and NaN cells included."""
    rng = np.random.default_rng(23)
    D, H, W = 6, 21, 39
    cost = random_volume(rng, D, H, W)
    img_l, img_r = blocky_image(rng, H, W, 6, 0.01), blocky_image(rng, H, W, 6, 0.01)
    arms_l, arms_r = cross_arms(img_l, eta=8, include_neighbor=True), cross_arms(img_r, eta=8, include_neighbor=True)
    assert max(arms_l.max(), arms_r.max()) == max_arm(8, True) and min(arms_l.min(), arms_r.min()) == 0
    for it, in_place in ((4, False), (5, True)):
        got, single = multi_vs_single(ctx, cost, arms_l, arms_r, it, in_place, select_add)
        assert not np.any(got == POISON)
        np.testing.assert_array_equal(got.view(np.uint32), single.view(np.uint32))


@pytest.mark.gpu_check
@pytest.mark.slow
def test_multi_iteration_counts_kitti_crop(ctx, shared_data):
    """The same on a real KITTI crop (AD volume, arms from the images)."""
    H, W, D = 40, 75, 20
    imgs = []
    for side in ("image_2", "image_3"):
        img = cv2.imread(str(shared_data / "kitti2015/training" / side / "000000_10.png"), cv2.IMREAD_GRAYSCALE)
        imgs.append(img[180:180 + H, 600:600 + W].astype(np.float32) / 255.0)
    cost = ad_volume(imgs[0], imgs[1], D)
    arms_l, arms_r = cross_arms(imgs[0]), cross_arms(imgs[1])
    for it, in_place in ((4, True), (4, False), (5, True), (2, False), (8, True)):
        got, single = multi_vs_single(ctx, cost, arms_l, arms_r, it, in_place)
        np.testing.assert_array_equal(got.view(np.uint32), single.view(np.uint32))
        compare(got, cbca(cost, arms_l, arms_r, it), cost)


def test_bad_input(ctx):
    from mccnn_cl.errors import InputError
    d_cost = ctx.to_device(np.zeros((2, 3, 4), np.float32))
    d_arms = ctx.to_device(np.zeros((4, 3, 4), np.uint8))
    with pytest.raises(InputError):
        CBCA(ctx)(d_cost, d_arms, d_arms, 2, 3, 4, iterations=-1)
    with pytest.raises(InputError):
        CBCA(ctx)(d_cost, d_arms, d_arms, 2, 3, 4, max_arm=256)
    with pytest.raises(InputError):
        CBCA(ctx)(d_cost, d_arms, d_arms, 0, 3, 4)
    with pytest.raises(InputError):
        arms_to_device(ctx, np.zeros((3, 4, 4), np.int32))


def mirrored_right(cost):
    """The mirrored right-reference volume (RightReference.volume):
    out(d, y, x) = cost(d, y, W - 1 - x + d), NaN for x < d."""
    from mccnn_cl.reference.disparity import right_cost_volume
    return np.ascontiguousarray(right_cost_volume(cost)[:, :, ::-1])


@pytest.mark.parametrize("source,eta,nb", [("random", 4, False), ("random", 9, True), ("kitti", 4, False)])
@pytest.mark.slow
def test_right_reference_aggregation_is_the_left_one_shifted(ctx, shared_data, source, eta, nb):
    """The pipeline takes the right reference's first CBCA from the left one:
    CBCA of the mirrored right-reference volume, with the mirrored right and
    left images' arms, equals the mirrored right-reference volume of the left
    CBCA (U_d of right pixel x is U_d of left pixel x + d, shifted by -d).
    Checked on the references (float64, so to rounding) and through the
    kernels (CBCA, then RightReference.volume) against the reference."""
    from mccnn_cl.stages.disparity import RightReference
    rng = np.random.default_rng(11)
    if source == "random":
        D, H, W = 12, 29, 47
        img_l, img_r = blocky_image(rng, H, W, 4, 0.01), blocky_image(rng, H, W, 3, 0.01)
        cost = random_volume(rng, D, H, W)
    else:
        H, W, D = 40, 75, 20
        img_l, img_r = (cv2.imread(str(shared_data / "kitti2015/training" / side / "000000_10.png"),
                                   cv2.IMREAD_GRAYSCALE)[180:180 + H, 600:600 + W].astype(np.float32) / 255.0
                        for side in ("image_2", "image_3"))
        cost = ad_volume(img_l, img_r, D)
    arms_l = cross_arms(img_l, eta=eta, include_neighbor=nb)
    arms_r = cross_arms(img_r, eta=eta, include_neighbor=nb)
    arms_ml = cross_arms(np.ascontiguousarray(img_r[:, ::-1]), eta=eta, include_neighbor=nb)
    arms_mr = cross_arms(np.ascontiguousarray(img_l[:, ::-1]), eta=eta, include_neighbor=nb)
    want = cbca(mirrored_right(cost), arms_ml, arms_mr, 4)  # the right reference aggregated itself
    shifted = mirrored_right(cbca(cost, arms_l, arms_r, 4))
    compare(shifted, want, cost)
    assert np.nanmax(np.abs(shifted - want)) < 1e-6 * np.nanmax(np.abs(cost))
    # through the kernels, as the pipeline does it
    got_l = run_cbca(ctx, cost, arms_l, arms_r, 4)
    d_vol = ctx.to_device(got_l, writable=True)
    RightReference(ctx).volume(d_vol, D, H, W)  # in place
    compare(ctx.from_device(d_vol, cost.shape), want, cost)


@pytest.mark.slow
def test_large_volume_default_path(ctx):
    """This device's default CBCA on a volume of KITTI height and half its
    width equals the two-pass short kernels (which the tests above check
    against the reference) bit for bit.  Rusticl/llvmpipe computes both
    fused kernels wrongly at this size (exact at 64 x 96), so CBCA's
    default there is the two-pass kernels; run with --cl-impl rusticl to
    check that choice."""
    rng = np.random.default_rng(12)
    D, H, W = 16, 367, 632
    cost = random_volume(rng, D, H, W)
    arms_l, arms_r = cross_arms(blocky_image(rng, H, W)), cross_arms(blocky_image(rng, H, W))
    d_l, d_r = arms_to_device(ctx, arms_l), arms_to_device(ctx, arms_r)
    results = []
    for cbca_ in (CBCA(ctx), CBCA(ctx, fused=False, multi=False)):
        d_out = ctx.empty(cost.nbytes)
        ctx.fill(d_out, POISON, cost.nbytes)
        cbca_(ctx.to_device(cost), d_l, d_r, D, H, W, iterations=4, max_arm=3, out=d_out)
        results.append(ctx.from_device(d_out, cost.shape))
    np.testing.assert_array_equal(np.isnan(results[0]), invalid_mask(D, H, W))
    np.testing.assert_array_equal(results[0].view(np.uint32), results[1].view(np.uint32))
