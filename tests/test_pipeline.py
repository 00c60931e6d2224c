"""StereoMatcher end to end: accuracy on a real Middlebury pair, intermediates
consistent with the numpy references stage by stage, input checking."""

import os

import cv2
import numpy as np
import pytest

import mccnn_cl
from mccnn_cl.errors import InputError, WeightsError
from mccnn_cl.io import read_pfm
from mccnn_cl.pipeline import Hyperparameters, StereoMatcher, StereoResult, to_gray
from mccnn_cl.reference import disparity as ref
from mccnn_cl.costs.census import CensusCost
from mccnn_cl.stages.disparity import WinnerTakeAll
from mccnn_cl.stages.refine import bilateral_radius
from mccnn_cl.stages.sgm import SGM
from mccnn_cl.weights import Weights, default_weights_path

BAD = 2.0  # Middlebury "bad 2.0": a pixel is wrong when |d - gt| > 2 px


def load_pair(shared_data, scene):
    d = shared_data / "middlebury" / scene
    left = cv2.imread(str(d / "im0.png"), cv2.IMREAD_COLOR)
    right = cv2.imread(str(d / "im1.png"), cv2.IMREAD_COLOR)
    gt = read_pfm(d / "disp0GT.pfm")
    mask = cv2.imread(str(d / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE) == 255
    ndisp = int([ln for ln in open(d / "calib.txt") if ln.startswith("ndisp")][0].split("=")[1])
    return left, right, gt, mask & np.isfinite(gt), ndisp


def bad_rate(disp, gt, mask):
    return float(np.mean(np.abs(disp[mask] - gt[mask]) > BAD)) * 100


@pytest.fixture(scope="module")
def census_matcher(ctx):
    return StereoMatcher(cost="census", max_disparity=32, device=ctx)


def test_census_pipeline_beats_wta_on_tsukuba(ctx, shared_data, census_matcher):
    left, right, gt, mask, ndisp = load_pair(shared_data, "Tsukuba")
    assert ndisp == 32 and mask.mean() > 0.5
    res = census_matcher.compute(left, right, return_intermediates=True)
    disp = res.disparity
    assert disp.shape == gt.shape and disp.dtype == np.float32 and np.isfinite(disp).all()
    # plain WTA on the same census cost, enlarged the same way (border copied)
    gl, gr = to_gray(left, "l"), to_gray(right, "r")
    d_cost = CensusCost(ctx)(gl, gr, 32)
    H, W = gl.shape[0] - 8, gl.shape[1] - 8
    wta = ctx.from_device(WinnerTakeAll(ctx).left(d_cost, 32, H, W), (H, W), np.int32)
    wta_full = ref.enlarge(wta.astype(np.float32), 4, gl.shape)
    e_pipe, e_wta = bad_rate(disp, gt, mask), bad_rate(wta_full, gt, mask)
    msg = f"bad-{BAD:g} on Tsukuba non-occluded: pipeline {e_pipe:.2f} %, census WTA {e_wta:.2f} %"
    print("\n" + msg)
    assert e_pipe < 0.6 * e_wta, msg
    assert e_pipe < 8.0, msg
    # every stage timed, in the order run: the right reference (on the cost volume read mirrored by
    # the paired sweeps, else mirrored in place: right_volume, there and back), then the left one
    mirror = [] if census_matcher.sgm.reads_mirrored else ["right_volume"]
    assert list(res.timings) == ["C_CNN", "cross", "C_CBCA", *mirror, "cross_R", "C_R_SGM", "C_R", "D_R",
                                 "C_SGM", "C", "D_L", "labels", "D_INT", "D_SE", "D_E",
                                 "D_median", "D_BF"]
    assert all(t >= 0 for t in res.timings.values())


@pytest.mark.slow
def test_intermediates_follow_the_references(ctx, shared_data):
    """On a small crop every intermediate equals the reference stage applied to
    the previous intermediate, and the plain call returns the same map."""
    left, right, _, _, _ = load_pair(shared_data, "Cones")
    left, right = left[100:151, 150:231], right[100:151, 150:231]  # 81 x 51, colour
    m = StereoMatcher(cost="census", max_disparity=24, device=ctx, lr_threshold=1.0,
                      blur_sigma=2.0, median_size=5)
    res = m.compute(left, right, return_intermediates=True)
    assert isinstance(res, StereoResult) and res.margin == 4
    it = res.intermediates
    assert set(it) == {"C_CNN", "C_CBCA", "C_SGM", "C", "C_R", "D_L", "D_R", "labels", "D_INT", "D_SE", "D_E",
                       "D_median", "D_BF"}
    gl, gr = to_gray(left, "l"), to_gray(right, "r")
    assert gl.std() > 0.05
    np.testing.assert_array_equal(np.isnan(it["C_CNN"]), np.isnan(ref.census_cost(gl, gr, 24)))
    np.testing.assert_array_equal(np.nan_to_num(it["C_CNN"], nan=-1),
                                  np.nan_to_num(ref.census_cost(gl, gr, 24), nan=-1))
    C = it["C"]
    assert C.shape == (24, 43, 73)
    np.testing.assert_array_equal(it["D_L"], ref.wta_left(C))
    # right image as the reference: the WTA of the (mirrored) right-reference volume, mirrored back
    np.testing.assert_array_equal(it["D_R"], ref.wta_left(it["C_R"])[:, ::-1])
    np.testing.assert_array_equal(it["labels"], ref.lr_check(it["D_L"], it["D_R"], 24, 1.0))
    np.testing.assert_array_equal(it["D_INT"], ref.interpolate(it["D_L"], it["labels"]))
    np.testing.assert_allclose(it["D_SE"], ref.subpixel(C, it["D_INT"], clamp_step=True), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(it["D_E"], ref.enlarge(it["D_SE"], 4, gl.shape))
    np.testing.assert_array_equal(it["D_median"], ref.median_filter(it["D_E"], 5))
    expect = ref.bilateral(it["D_median"], gl, 2.0, bilateral_radius(2.0), np.float32(5 / 255))
    np.testing.assert_allclose(it["D_BF"], expect, rtol=1e-5, atol=1e-4)
    np.testing.assert_array_equal(res.disparity, it["D_BF"])
    np.testing.assert_array_equal(m.compute(left, right), res.disparity)  # same path, no copies


@pytest.mark.parametrize("settings", [dict(cost="census", max_disparity=24),
                                      dict(cost="census", max_disparity=40, cbca_iterations=2, volume_dtype="float16")])
def test_right_reference_read_mirrored_equals_the_mirrored_volume(ctx, shared_data, settings):
    """The right reference with SGM's paired sweeps reading C_CBCA mirrored
    gives the bits of the pipeline that mirrors C_CBCA in place (there and
    back: two volume passes fewer), intermediates included; with CBCA before
    SGM too and on half volumes."""
    left, right, _, _, _ = load_pair(shared_data, "Cones")
    left, right = left[100:161, 150:251], right[100:161, 150:251]
    m = StereoMatcher(device=ctx, **settings)
    m.sgm = SGM(ctx, paired=True, half=m.half, mirror_reads=True)  # whatever the device's rule
    read = m.compute(left, right, return_intermediates=True)
    assert "right_volume" not in read.timings
    m.sgm.mirror_reads = False  # the rule sgm_mirror_reads off, as the tuner may choose
    assert not m.sgm.reads_mirrored
    made = m.compute(left, right, return_intermediates=True)
    assert "right_volume" in made.timings
    assert set(read.intermediates) == set(made.intermediates)
    for name, a in made.intermediates.items():
        np.testing.assert_array_equal(read.intermediates[name], a, err_msg=name)
    np.testing.assert_array_equal(read.disparity, made.disparity)


def test_right_reference_derived(ctx, shared_data):
    left, right, _, _, _ = load_pair(shared_data, "Cones")
    left, right = left[100:151, 150:231], right[100:151, 150:231]
    m = StereoMatcher(cost="census", max_disparity=24, device=ctx, right_reference="derived")
    it = m.compute(left, right, return_intermediates=True).intermediates
    assert "C_R" not in it
    np.testing.assert_array_equal(it["D_R"], ref.wta_right(it["C"]))
    np.testing.assert_array_equal(it["labels"], ref.lr_check(it["D_L"], it["D_R"], 24, 1.0))


def test_code_variants_run_and_differ(ctx, shared_data):
    left, right, gt, mask, _ = load_pair(shared_data, "Tsukuba")
    left, right = left[60:160, 100:260], right[60:160, 100:260]
    paper = StereoMatcher(cost="census", max_disparity=24, device=ctx)
    code = StereoMatcher(cost="census", max_disparity=24, device=ctx, lr_threshold=1.1, interpolation="code",
                         subpixel_min_denominator=1e-5, subpixel_clamp=True, bilateral_guide="disparity",
                         blur_tau=2.0)
    a, b = paper.compute(left, right), code.compute(left, right)
    assert np.isfinite(a).all() and np.isfinite(b).all()
    assert not np.array_equal(a, b)


def test_input_conversion():
    rng = np.random.default_rng(0)
    u8 = rng.integers(0, 256, (12, 15, 3), dtype=np.uint8)
    g = to_gray(u8, "x")
    np.testing.assert_array_equal(g, cv2.cvtColor(u8, cv2.COLOR_BGR2GRAY).astype(np.float32) / 255)
    np.testing.assert_array_equal(to_gray(u8[:, :, 0], "x"), u8[:, :, 0].astype(np.float32) / 255)
    u16 = u8[:, :, 0].astype(np.uint16) * 257
    np.testing.assert_array_equal(to_gray(u16, "x"), to_gray(u8[:, :, 0], "x"))
    f = u8[:, :, 0].astype(np.float64) / 255
    np.testing.assert_allclose(to_gray(f, "x"), to_gray(u8[:, :, 0], "x"), atol=1e-7)
    assert to_gray(f[:, :, None], "x").shape == (12, 15)


@pytest.mark.parametrize("bad,match", [
    (np.zeros((20, 30), np.int32), "dtype"),
    (np.zeros((20, 30), bool), "dtype"),
    (np.zeros(30, np.uint8), "shape"),
    (np.zeros((20, 30, 2), np.uint8), "shape"),
    (np.full((20, 30), 1.5, np.float32), r"\[0, 1\]"),
    (np.full((20, 30), -0.1, np.float32), r"\[0, 1\]"),
    (np.full((20, 30), np.nan, np.float32), "NaN"),
])
def test_bad_image_rejected(census_matcher, bad, match):
    good = np.zeros((20, 30), np.float32)
    with pytest.raises(InputError, match=match):
        census_matcher.compute(bad, good)


def test_bad_sizes_rejected(ctx, census_matcher):
    a = np.zeros((40, 50), np.uint8)
    with pytest.raises(InputError, match="differ"):
        census_matcher.compute(a, np.zeros((40, 51), np.uint8))
    with pytest.raises(InputError, match="smaller than"):
        census_matcher.compute(np.zeros((8, 50), np.uint8), np.zeros((8, 50), np.uint8))
    with pytest.raises(InputError, match="width"):
        census_matcher.compute(np.zeros((40, 32), np.uint8), np.zeros((40, 32), np.uint8))
    for D in (0, -3, 2.5):
        with pytest.raises(InputError):
            StereoMatcher(cost="census", max_disparity=D, device=ctx)
    with pytest.raises(InputError):
        StereoMatcher(cost="sad", device=ctx)
    with pytest.raises(InputError):
        StereoMatcher(cost="census", device=ctx, interpolation="nearest")
    # a network with the census cost would be ignored: refused, whatever form the weights take
    for w in (Weights.random(conv_layers=[[4, 3]] * 4, fc_layers=[8, 2], seed=1), "some-net.npz"):
        with pytest.raises(InputError, match="cost='census' uses no network"):
            StereoMatcher(weights=w, cost="census", device=ctx)


@pytest.mark.slow
def test_smallest_and_constant_images(census_matcher):
    # 9 x 33: a single-row cost volume; constant: every cost ties -> d = 0
    c = np.full((9, 33), 128, np.uint8)
    out = census_matcher.compute(c, c)
    assert out.shape == (9, 33) and np.isfinite(out).all()
    np.testing.assert_array_equal(out, 0)


def test_unknown_hyperparameter_lists_names(ctx):
    with pytest.raises(TypeError) as exc:
        StereoMatcher(cost="census", device=ctx, sgm_p1=3)
    assert "sgm_p1" in str(exc.value) and "sgm_pi1" in str(exc.value) and "blur_sigma" in str(exc.value)
    hp = Hyperparameters()
    assert (hp.cbca_eta, hp.cbca_tau, hp.sgm_pi2, hp.blur_sigma, hp.blur_tau) == (4, 0.0442, 32, 5.656, 5)


def test_default_weights(ctx):
    if os.path.exists(default_weights_path()):
        m = StereoMatcher(device=ctx, max_disparity=16)
        assert m.weights.patch_size == 9
    else:  # until the trained model ships, a clear WeightsError pointing at the census cost
        with pytest.raises(WeightsError, match="census"):
            StereoMatcher(device=ctx)


@pytest.mark.slow
def test_cnn_cost_with_random_weights(ctx, shared_data, tmp_path, capsys):
    w = Weights.random(conv_layers=[[8, 5], [12, 5], [12, 1]], fc_layers=[16, 16, 2], seed=1)
    w.save(tmp_path / "w.npz")
    left, right, _, _, _ = load_pair(shared_data, "Tsukuba")
    left, right = left[100:140, 100:180], right[100:140, 100:180]
    for weights, progress in ((w, False), (tmp_path / "w.npz", True)):
        m = StereoMatcher(weights=weights, max_disparity=12, device=ctx, cost="cnn", progress=progress)
        res = m.compute(left, right, return_intermediates=True)
        assert res.intermediates["C_CNN"].shape == (12, 32, 72)
        assert res.disparity.shape == (40, 80) and np.isfinite(res.disparity).all()
    err = capsys.readouterr().err
    assert "cost volume (cnn)" in err and "12/12" in err  # the tqdm bar of the second run
    assert mccnn_cl.StereoMatcher is StereoMatcher


def cones(gray=False):
    """The eighth-size Cones pair (tests/cones_eighth, 225 x 188), BGR or gray uint8."""
    d = os.path.join(os.path.dirname(__file__), "cones_eighth")
    flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
    return [cv2.imread(os.path.join(d, n), flag) for n in ("im0.png", "im1.png")]


def test_params_changed_after_construction(ctx):
    """``matcher.params`` changed after construction: median_size is used (the
    filter was built once, at construction) and every field is checked at the
    call as the constructor checks it (median_size=4, sgm_pi2=-5 ran)."""
    import dataclasses

    left, right = cones()
    m = StereoMatcher(cost="census", max_disparity=32, device=ctx)
    m.params = dataclasses.replace(m.params, median_size=11)
    got = m.compute(left, right)
    want = StereoMatcher(cost="census", max_disparity=32, device=ctx, median_size=11).compute(left, right)
    np.testing.assert_array_equal(got, want)
    assert not np.array_equal(got, StereoMatcher(cost="census", max_disparity=32, device=ctx).compute(left, right))
    for name, value, words in (("median_size", 4, "median_size must be a positive odd"),
                               ("sgm_pi2", -5.0, "sgm_pi2 must be >= 0"),
                               ("interpolation", "nearest", "interpolation must be")):
        m.params = dataclasses.replace(Hyperparameters(), median_size=11)
        setattr(m.params, name, value)
        with pytest.raises(InputError, match=words):
            m.compute(left, right)
    m.params = {"median_size": 5}
    with pytest.raises(InputError, match="Hyperparameters"):
        m.compute(left, right)


def _held(m, base):
    import gc

    gc.collect()
    return m.ctx.memory.live - base


@pytest.mark.parametrize("cost", ["census", "cnn"])
def test_release_buffers_frees_every_kept_buffer(ctx, cost):
    """release_buffers() leaves only what the constructor made (it left CBCA's
    scratch and SGM's path state), and a call of another size holds what a
    fresh matcher's call of that size holds (the network's maps and features
    pools only grew: 305 MiB after a 718 x 496 call vs 68 MiB fresh)."""
    from mccnn_cl.opencl.context import ClContext

    big_l, big_r = cones()
    small_l, small_r = big_l[40:140, 30:190], big_r[40:140, 30:190]
    m = StereoMatcher(cost=cost, max_disparity=48, device=ClContext(ctx.device))
    base = m.ctx.memory.live
    m.compute(big_l, big_r)
    assert _held(m, base) > 0  # volumes and scratch kept for the next call
    m.release_buffers()
    assert _held(m, base) == 0
    m.compute(big_l, big_r)
    m.compute(small_l, small_r)
    fresh = StereoMatcher(cost=cost, max_disparity=48, device=ClContext(ctx.device))
    fresh_base = fresh.ctx.memory.live
    fresh.compute(small_l, small_r)
    assert _held(m, base) == _held(fresh, fresh_base) > 0


def _device_buffers(obj):
    """The device buffers an object holds in its attributes (directly, or in a
    dict, list or tuple attribute)."""
    import pyopencl as cl

    found = []
    for value in vars(obj).values():
        items = value.values() if isinstance(value, dict) else value if isinstance(value, (list, tuple)) else [value]
        found += [v for v in items if isinstance(v, cl.MemoryObjectHolder)]
    return found


def test_release_buffers_frees_the_bilateral_stage(ctx, monkeypatch):
    """The matcher's release_buffers frees the bilateral filter's tap tables through
    the stage's own release_buffers (before: the matcher cleared the stage's private
    dict), leaving the stage no device buffer; the next call makes them again and
    gives the same map."""
    from mccnn_cl.opencl.context import ClContext
    from mccnn_cl.stages.refine import BilateralFilter

    left, right = (a[:96, :128] for a in cones())
    m = StereoMatcher(cost="census", max_disparity=24, device=ClContext(ctx.device))
    calls, real = [], BilateralFilter.release_buffers
    monkeypatch.setattr(BilateralFilter, "release_buffers", lambda self: (calls.append(self), real(self))[1])
    want = m.compute(left, right)
    assert _device_buffers(m.bilateral)  # the tap table, kept for the next call
    m.release_buffers()
    assert calls == [m.bilateral] and _device_buffers(m.bilateral) == []
    np.testing.assert_array_equal(m.compute(left, right), want)
    assert _device_buffers(m.bilateral)


def test_colour_network_refused_at_construction(ctx):
    """StereoMatcher converts every pair to gray: a 3-channel network is a
    WeightsError when the matcher is made, not an InputError at the first call."""
    w = Weights.random(architecture="mccnn-fst", input_channels=3)
    with pytest.raises(WeightsError, match="3-channel.*gray"):
        StereoMatcher(weights=w, max_disparity=16, device=ctx)


def test_range_with_a_negative_minimum_may_span_the_width(ctx):
    """With M < 0 the method works on a W - M wide frame: D >= W is allowed
    (only disprange.check_range applies) and matches as a narrower range that
    covers the pair's disparities; D >= W from 0 is refused, naming what the
    caller gave."""
    left, right = cones()
    m = StereoMatcher(cost="census", max_disparity=32, device=ctx)
    W = left.shape[1]
    ref = m.compute(left, right, disparity_range=(-150, 73))
    wide = m.compute(left, right, disparity_range=(-150, 99))  # 250 levels on a 225-px image
    assert np.isfinite(wide).all()
    assert float(np.mean(np.abs(wide - ref) > 1)) < 0.01
    with pytest.raises(InputError, match=rf"disparity_range=\(0, {W}\)\) is not smaller than the image width {W}"):
        m.compute(left, right, disparity_range=(0, W))
    with pytest.raises(InputError, match=rf"max_disparity={W}\) is not smaller"):
        StereoMatcher(cost="census", max_disparity=W, device=ctx).compute(left, right)
    with pytest.raises(InputError, match="leave no pixel a match"):
        m.compute(left, right, disparity_range=(-400, -300))


def test_shipped_model_named_as_its_file(ctx):
    """weights="general-fst.npz", the name the demo prints, is the shipped model
    when no such file exists; a missing file's error lists the shipped names."""
    from mccnn_cl.weights import shipped_models

    names = list(shipped_models())
    assert "general-fst" in names
    m = StereoMatcher(weights="general-fst.npz", max_disparity=16, device=ctx)
    assert m.weights.architecture == "mccnn-fst"
    with pytest.raises(WeightsError) as info:
        StereoMatcher(weights="no-such-net.npz", max_disparity=16, device=ctx)
    assert "not found" in str(info.value) and all(n in str(info.value) for n in names)


def test_low_bits_warning_points_at_the_callers_line(ctx, recwarn):
    """The uint16 low-bits InputWarning names the caller's line (it named a line
    inside mccnn_cl/pipeline.py), through StereoMatcher.compute and to_gray."""
    import inspect
    import warnings

    from mccnn_cl.errors import InputWarning

    left, right = (a.astype(np.uint16) * 16 for a in cones(gray=True))
    m = StereoMatcher(cost="census", max_disparity=16, device=ctx)
    warnings.simplefilter("always")
    line = inspect.currentframe().f_lineno + 1
    m.compute(left, right)  # one warning per image, both on this line
    to_gray(left)  # the helper itself (mccnn_cl.pipeline.to_gray is imageops.to_gray)
    got = [(w.filename, w.lineno) for w in recwarn.list if issubclass(w.category, InputWarning)]
    assert got == [(__file__, line), (__file__, line), (__file__, line + 1)], got
