"""Half-precision volume storage (``-D VOL_HALF=1``, kernels/common.h): every
kernel that reads or writes a cost volume, in its half variant, against the
numpy reference evaluated on the same half-rounded values.

Tolerances: storage rounds each stored value to the nearest half (relative
error <= 2^-11 = 4.9e-4); arithmetic stays float.  So a kernel that only
writes (network, census, right-reference volume) must equal the float
result rounded to half (exactly where the float kernel equals the reference,
within one half ulp otherwise); a kernel that only reads (WTA, subpixel)
must give the reference's answer on the half values (float-exact).
"""

import numpy as np
import pytest

from mccnn_cl.reference import disparity as ref
from mccnn_cl.reference import network as netref
from mccnn_cl.costs.census import CensusCost
from mccnn_cl.stages.disparity import RightReference, Subpixel, WinnerTakeAll
from mccnn_cl.costs.network import NetworkCost
from mccnn_cl.weights import Weights

from conftest import POISON

F16_POISON = np.float16(-65504.0)
I32_POISON = np.int32(-123456789)


def half_volume(rng, D, H, W, levels=None):
    C = rng.random((D, H, W), dtype=np.float32)
    if levels:
        C = np.floor(C * levels) / levels
    C = C.astype(np.float16)
    for d in range(D):
        C[d, :, :min(d, W)] = np.nan
    return C


def poisoned(ctx, nbytes, value, dtype):
    buf = ctx.empty(nbytes, "poisoned output")
    ctx.fill(buf, value, nbytes, dtype)
    return buf


@pytest.mark.gpu_check
def test_half_roundtrip_and_nan(ctx):
    """The storage format is IEEE binary16 as numpy's float16: values rounded to
    nearest even, NaN kept (the invalid cells)."""
    rng = np.random.default_rng(0)
    C = half_volume(rng, 5, 7, 11)
    rr = RightReference(ctx, half=True)
    dirty = C.copy()
    dirty[np.isnan(dirty)] = F16_POISON  # invalid cells the kernel must set to NaN
    d_in = ctx.to_device(dirty, writable=True)
    rr.volume(d_in, 5, 7, 11)  # in place
    got = ctx.from_device(d_in, C.shape, np.float16)
    expected = ref.right_cost_volume(C.astype(np.float32))[:, :, ::-1].astype(np.float16)
    np.testing.assert_array_equal(got, expected)  # NaN positions included
    rr.volume(d_in, 5, 7, 11)  # and back
    np.testing.assert_array_equal(ctx.from_device(d_in, C.shape, np.float16), C)


@pytest.mark.parametrize("levels", [None, 8])
@pytest.mark.gpu_check
def test_wta_half(ctx, levels):
    rng = np.random.default_rng(1 + (levels or 0))
    D, H, W = 13, 9, 40
    C = half_volume(rng, D, H, W, levels)
    wta = WinnerTakeAll(ctx, half=True)
    # invalid cells (x < d) as NaN, then holding -1000, 0 or +1000: validity by
    # index, so the maps stay the reference's of the NaN-filled volume
    for value in (np.nan, -1000.0, 0.0, 1000.0):
        d_c = ctx.to_device(np.where(np.isnan(C), np.float16(value), C))
        for fn, expected in ((wta.left, ref.wta_left(C.astype(np.float32))),
                             (wta.right, ref.wta_right(C.astype(np.float32)))):
            out = poisoned(ctx, H * W * 4, I32_POISON, np.int32)
            fn(d_c, D, H, W, out=out)
            np.testing.assert_array_equal(ctx.from_device(out, (H, W), np.int32), expected,
                                          err_msg=f"{fn.__name__}: invalid cells = {value}")


def test_subpixel_half(ctx):
    rng = np.random.default_rng(2)
    D, H, W = 11, 8, 30
    C = half_volume(rng, D, H, W)
    C32 = C.astype(np.float32)
    DINT = ref.wta_left(C32).astype(np.int32)
    out = poisoned(ctx, H * W * 4, POISON, np.float32)
    Subpixel(ctx, half=True)(ctx.to_device(C), ctx.to_device(DINT), D, H, W, out=out)
    np.testing.assert_allclose(ctx.from_device(out, (H, W)), ref.subpixel(C32, DINT), rtol=1e-6, atol=1e-6)


@pytest.mark.gpu_check
def test_census_half(ctx, shared_data):
    import cv2
    d = shared_data / "middlebury" / "Tsukuba"
    left = cv2.imread(str(d / "im0.png"), cv2.IMREAD_GRAYSCALE)[100:160, 100:220].astype(np.float32)
    right = cv2.imread(str(d / "im1.png"), cv2.IMREAD_GRAYSCALE)[100:160, 100:220].astype(np.float32)
    D = 16
    cost = CensusCost(ctx, half=True)
    H, W = left.shape[0] - 8, left.shape[1] - 8
    out = poisoned(ctx, D * H * W * 2, F16_POISON, np.float16)
    cost(left, right, D, out=out)
    got = ctx.from_device(out, (D, H, W), np.float16)
    np.testing.assert_array_equal(got, ref.census_cost(left, right, D).astype(np.float16))


@pytest.mark.gpu_check
@pytest.mark.slow
def test_network_half(ctx):
    w = Weights.random(seed=5)
    rng = np.random.default_rng(6)
    left = rng.random((21, 37)).astype(np.float32)
    right = rng.random((21, 37)).astype(np.float32)
    D = 9
    net = NetworkCost(ctx, w, half=True)
    h, wd = 21 - 8, 37 - 8
    out = poisoned(ctx, D * h * wd * 2, F16_POISON, np.float16)
    net(left, right, D, out=out)
    got = ctx.from_device(out, (D, h, wd), np.float16).astype(np.float32)
    expected = netref.cost_volume(w, left, right, D)
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    ok = ~np.isnan(expected)
    # float kernel within 1e-4 of the reference (tests/test_network.py), then rounded to half
    np.testing.assert_allclose(got[ok], expected[ok], rtol=2 ** -11, atol=1e-4)
    # and the host-resident path stores the same half values
    np.testing.assert_array_equal(net.to_host(left, right, D, max_bytes=3 * D * wd * 2),
                                  got.astype(np.float16))


def real_crop(shared_data, rows, cols):
    import cv2
    d = shared_data / "middlebury" / "Tsukuba"
    L = cv2.imread(str(d / "im0.png"), cv2.IMREAD_GRAYSCALE)[rows, cols].astype(np.float32) / 255
    R = cv2.imread(str(d / "im1.png"), cv2.IMREAD_GRAYSCALE)[rows, cols].astype(np.float32) / 255
    return L, R


@pytest.mark.parametrize("short,fused,multi,bound", [(True, True, True, None), (True, True, False, None),
                                                     (True, False, False, None), (False, False, False, 255)])
@pytest.mark.slow
def test_cbca_half(ctx, shared_data, short, fused, multi, bound):
    """Half CBCA (every implementation) against the reference on the half input.
    Each iteration stores its result as half (the two-pass kernels also their
    row sums of up to 7 costs), so per iteration up to 2 roundings of
    2^-11 relative: rtol = 2 x iterations x 2^-11."""
    from mccnn_cl.reference.aggregation import cbca, cross_arms
    from mccnn_cl.stages.cbca import CBCA
    from mccnn_cl.stages.cross import arms_to_device

    L, R = real_crop(shared_data, slice(120, 150), slice(100, 170))
    D, (H, W) = 12, L.shape
    rng = np.random.default_rng(8)
    C = half_volume(rng, D, H, W)
    arms_l, arms_r = cross_arms(L), cross_arms(R)
    bound = int(max(arms_l.max(), arms_r.max())) if bound is None else bound
    it = 4
    out = poisoned(ctx, C.nbytes, F16_POISON, np.float16)
    d_c = ctx.to_device(C)
    CBCA(ctx, short=short, fused=fused, half=True, multi=multi)(d_c, arms_to_device(ctx, arms_l),
                                                                arms_to_device(ctx, arms_r),
                                                                D, H, W, iterations=it, max_arm=bound, out=out)
    got = ctx.from_device(out, C.shape, np.float16).astype(np.float32)
    want = cbca(C.astype(np.float32), arms_l, arms_r, it)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got, want, rtol=2 * it * 2 ** -11, atol=1e-7)
    # in place gives the same bits
    d_in = ctx.empty(C.nbytes)
    ctx.cl.enqueue_copy(ctx.queue, d_in, C)
    CBCA(ctx, short=short, fused=fused, half=True, multi=multi)(d_in, arms_to_device(ctx, arms_l),
                                                                arms_to_device(ctx, arms_r),
                                                                D, H, W, iterations=it, max_arm=bound, out=d_in)
    np.testing.assert_array_equal(ctx.from_device(d_in, C.shape, np.float16).astype(np.float32), got)


@pytest.mark.gpu_check
def test_cbca_half_multi_matches_single(ctx, shared_data):
    """Half volumes: the multi-iteration fused kernel (each iteration's output
    row rounded to half before the next reads it) gives the same half bits as
    iterating the one-iteration fused kernel, for iteration counts below, at
    and above MULTI_K, in place and out of place."""
    from mccnn_cl.stages.cbca import CBCA
    from mccnn_cl.reference.aggregation import cross_arms
    from mccnn_cl.stages.cross import arms_to_device

    L, R = real_crop(shared_data, slice(100, 131), slice(80, 133))
    D, (H, W) = 10, L.shape
    C = half_volume(np.random.default_rng(12), D, H, W)
    arms_l, arms_r = arms_to_device(ctx, cross_arms(L)), arms_to_device(ctx, cross_arms(R))
    for it, in_place in ((1, False), (3, True), (4, False), (6, True)):
        res = []
        for multi in (True, False):
            d_c = ctx.to_device(C)
            out = d_c if (in_place and multi) else poisoned(ctx, C.nbytes, F16_POISON, np.float16)
            CBCA(ctx, half=True, multi=multi)(d_c, arms_l, arms_r, D, H, W, iterations=it, max_arm=3, out=out)
            res.append(ctx.from_device(out, C.shape, np.float16))
        np.testing.assert_array_equal(res[0].view(np.uint16), res[1].view(np.uint16))
        assert not np.array_equal(res[0], C)  # it aggregated


def half_sgm_bound(C32, L, R, paired):
    """The reference C_SGM of the half input (float64) and a per-cell bound of
    |half SGM - reference| from the roundings to half.

    The recurrences run in float on exactly the reference's inputs; only the
    partial sums stored in the half output are rounded, to nearest (relative
    error <= u = 2^-11 of the value stored; all costs >= 0).  The one-direction
    kernels (and SGMWorkGroup, bit for bit the same) store C_lr, C_lr + C_rl,
    C_lr + C_rl + C_tb and finally (.. + C_bt) / 4: error <= u ((C_lr +
    (C_lr + C_rl) + (C_lr + C_rl + C_tb)) / 4 + C_SGM).  The paired sweeps store
    one pair's sum (C_lr + C_tb or C_rl + C_bt, by row) and then the sum of
    all four / 4: error <= u (max of the pairs / 4 + C_SGM).  That is 2 u to 4 u
    of C_SGM (the old absolute bound, 7 u of the largest |C_r| of any
    direction, allowed errors 20 times those observed).  Plus 2^-20 of C_SGM
    for float32 against float64 arithmetic (measured <= 2^-21) and 2^-23 for
    stores below half's normal range (absolute error <= 2^-25 each).  Measured
    on PoCL (Tsukuba and KITTI crops): the largest error is 0.92 of this bound;
    with the stores rounded toward zero (vstore_half_rtz) 1.37 to 1.78."""
    from mccnn_cl.reference.aggregation import SGM_DIRECTIONS, sgm_direction

    lr, rl, tb, bt = (sgm_direction(C32, L, R, r).astype(np.float64) for r in SGM_DIRECTIONS)
    want = (lr + rl + tb + bt) / 4
    stored = np.maximum(lr + tb, rl + bt) if paired else lr + (lr + rl) + (lr + rl + tb)
    u = 2.0 ** -11
    return want, u * (stored / 4 + want) + 2.0 ** -20 * want + 2.0 ** -23


def check_half_sgm(got, want, bound):
    """got (half output as float64) within the per-cell bound of want; NaN exactly where want's."""
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    v = ~np.isnan(want)
    assert (want[v] >= 0).all()  # the bound is relative to non-negative costs
    ratio = np.abs(got[v] - want[v]) / bound[v]
    assert ratio.max() <= 1.0, (f"{np.sum(ratio > 1)} cells beyond the rounding bound, worst "
                                f"{ratio.max():.3f} x the bound (value {want[v][ratio.argmax()]:.5g})")
    assert np.abs(got[v] - want[v]).max() > 0  # rounding did happen: the half path really ran


@pytest.mark.parametrize("W", [45, 100])
@pytest.mark.gpu_check
@pytest.mark.slow
def test_sgm_half(ctx, shared_data, W):
    """Half SGM against the reference on the half input, within the per-cell
    bound of the roundings to half (:func:`half_sgm_bound`), for the paired
    sweeps and the one-direction kernels."""
    from mccnn_cl.stages.sgm import SGM

    L, R = real_crop(shared_data, slice(150, 170), slice(60, 60 + W))
    D, H = 24, L.shape[0]
    C = np.full((D, H, W), np.nan, np.float32)
    for d in range(D):
        C[d, :, d:] = np.abs(L[:, d:] - R[:, :W - d])
    C = C.astype(np.float16)
    C32 = C.astype(np.float32)
    for paired in (True, False):
        out = poisoned(ctx, C.nbytes, F16_POISON, np.float16)
        SGM(ctx, half=True, paired=paired)(ctx.to_device(C), ctx.to_device(L), ctx.to_device(R), D, H, W, out=out)
        got = ctx.from_device(out, C.shape, np.float16).astype(np.float64)
        want, bound = half_sgm_bound(C32, L, R, paired)
        check_half_sgm(got, want, bound)


@pytest.mark.slow
def test_pipeline_half_storage(ctx, shared_data):
    """StereoMatcher(volume_dtype="float16"): half the volume memory, the same
    disparities within the stated tolerance (>= 99.5 % of pixels within 0.5 px
    of the float32 run; measured on whole pairs: 99.91-100 %, docs/method.md)."""
    import cv2
    from mccnn_cl.errors import InputError
    from mccnn_cl.pipeline import StereoMatcher

    d = shared_data / "middlebury" / "Cones"
    left = cv2.imread(str(d / "im0.png"), cv2.IMREAD_GRAYSCALE)[:200, :300]
    right = cv2.imread(str(d / "im1.png"), cv2.IMREAD_GRAYSCALE)[:200, :300]
    full = StereoMatcher(cost="census", max_disparity=48, device=ctx)
    half = StereoMatcher(cost="census", max_disparity=48, device=ctx, volume_dtype="float16")
    a = full.compute(left, right, return_intermediates=True)
    b = half.compute(left, right, return_intermediates=True)
    assert b.plan.volume_bytes * 2 == a.plan.volume_bytes
    # the volumes alive at once (a.plan.volumes) take half the bytes; the other buffers do not change
    assert a.peak_device_bytes - b.peak_device_bytes >= a.plan.volumes * b.plan.volume_bytes
    for name in ("C_CNN", "C_CBCA", "C_SGM", "C", "C_R"):
        assert b.intermediates[name].dtype == np.float16 and a.intermediates[name].dtype == np.float32
    np.testing.assert_array_equal(b.intermediates["C_CNN"], a.intermediates["C_CNN"].astype(np.float16))
    diff = np.abs(a.disparity - b.disparity)
    assert float(np.mean(diff <= 0.5)) >= 0.995, float(np.mean(diff <= 0.5))
    with pytest.raises(InputError, match="volume_dtype"):
        StereoMatcher(cost="census", max_disparity=48, device=ctx, volume_dtype="float64")


@pytest.mark.slow
def test_cbca_half_default_path_tall_image(ctx, shared_data):
    """The CBCA path the pipeline takes by default (fused on CPU devices; the
    two-pass kernels on Rusticl, whose fused half kernel computed wrong sums
    beyond ~170 rows) on a 192 x 292 volume: within half rounding of the
    reference on every implementation."""
    from mccnn_cl.reference.aggregation import cbca, cross_arms
    from mccnn_cl.stages.cbca import CBCA
    from mccnn_cl.stages.cross import arms_to_device

    L, R = real_crop(shared_data, slice(4, 196), slice(4, 296))
    D, (H, W) = 2, L.shape
    C = half_volume(np.random.default_rng(9), D, H, W)
    arms_l, arms_r = cross_arms(L), cross_arms(R)
    stage = CBCA(ctx, half=True)
    out = poisoned(ctx, C.nbytes, F16_POISON, np.float16)
    stage(ctx.to_device(C), arms_to_device(ctx, arms_l), arms_to_device(ctx, arms_r), D, H, W,
          iterations=2, max_arm=3, out=out)
    got = ctx.from_device(out, C.shape, np.float16).astype(np.float32)
    want = cbca(C.astype(np.float32), arms_l, arms_r, 2)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got, want, rtol=2 * 2 * 2 ** -11, atol=1e-7)
