"""CBCA's GPU-shaped path ("workgroup", kernels/cbca_wg.cl: a work-group per
(row, d) and per (column tile, d)) against mccnn_cl.reference.aggregation.cbca
and against the short two-pass kernels of cbca.cl.

Against the short passes bit for bit: the same float additions in the same
order per cell, the same integer counts and the same division (see
kernels/cbca_wg.cl), in float32 and in half storage, so any difference is a
defect of one of them.  Against the float64 reference: tests/test_cbca.py's
1e-5 of the cost range (float32) and tests/test_half.py's 2 x iterations x
2^-11 relative (half).  NaN positions exactly; every output poisoned first,
so a cell left unwritten fails.

Work-group sizes 1, 4, 16, a columns shape that is no power of two, and the
kernels' maxima on this device (4096 on PoCL), on odd W, H, D with groups
that do not divide them: on CPU implementations (and Oclgrind's race and
barrier checks in tests/test_oclgrind.py) these prove the local-memory and
barrier logic that a GPU runs.
"""


import numpy as np
import pytest

import helpers

from conftest import POISON
from helpers import ad_volume, blocky_image, invalid_mask, kitti_crop, random_volume
from mccnn_cl.opencl.device import RULES, DeviceProfile
from mccnn_cl.errors import InputError
from mccnn_cl.reference.aggregation import cbca, cross_arms
from mccnn_cl.stages.cbca import CBCA, SHORT_MAX, path_scratch_bytes
from mccnn_cl.stages.cross import arms_to_device, max_arm

F16_POISON = np.float16(-65504.0)
#: Forced local sizes: int L (rows groups of L, columns groups columns_shape(L)) or (L, (TX, TY)).
SIZES = (1, 4, 16, (7, (3, 5)), "max")


def kernel_max(ctx, A=3):
    """The rows and the columns kernel's largest work-groups on this device."""
    st = CBCA(ctx, workgroup=True, max_arm=A)
    (k_rows, _), (k_cols, _) = st._get(A)[0]
    return ctx.work_group_size(k_rows), ctx.work_group_size(k_cols)


def local_sizes(ctx, sizes=SIZES, A=3):
    """``sizes`` with "max" as (rows kernel maximum, columns shape of the columns kernel maximum)."""
    mr, mc = kernel_max(ctx, A)
    st = CBCA(ctx, workgroup=True, max_arm=A)
    return [(mr, st.columns_shape(mc, A)) if s == "max" else s for s in sizes]


def run(ctx, cost, arms_l, arms_r, iterations, A, dtype=np.float32, in_place=False, **kw):
    """One CBCA call into a poisoned buffer (or in place); returns (result, stage)."""
    D, H, W = cost.shape
    nbytes = cost.nbytes
    stage = CBCA(ctx, half=dtype == np.float16, **kw)
    d_cost = ctx.to_device(cost)
    if in_place:
        out = d_cost
    else:
        out = ctx.empty(nbytes)
        ctx.fill(out, POISON if dtype == np.float32 else F16_POISON, nbytes, dtype=dtype)
    assert stage(d_cost, arms_to_device(ctx, arms_l), arms_to_device(ctx, arms_r), D, H, W,
                 iterations=iterations, max_arm=A, out=out) is out
    got = ctx.from_device(out, cost.shape, dtype)
    if not in_place:
        np.testing.assert_array_equal(ctx.from_device(d_cost, cost.shape, dtype).view(np.uint8),
                                      cost.view(np.uint8))  # input untouched
    return got, stage


def short_path(ctx, cost, arms_l, arms_r, iterations, A, dtype=np.float32):
    got, st = run(ctx, cost, arms_l, arms_r, iterations, A, dtype, short=True, fused=False, multi=False,
                  workgroup=False)
    assert st.path(A) == "short"
    return got


def compare(got, want, cost):
    """tests/test_cbca.py's tolerance: 1e-5 of the cost range; NaN exactly where invalid."""
    np.testing.assert_array_equal(np.isnan(got), invalid_mask(*cost.shape))
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    rng_ = np.nanmax(cost) - np.nanmin(cost)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * max(rng_, 1e-30))


def check_all(ctx, cost, arms_l, arms_r, iterations, sizes=SIZES, in_place=False):
    """Each forced local size against the reference and, bit for bit, the short passes."""
    A = int(max(arms_l.max(), arms_r.max()))
    want = cbca(cost, arms_l, arms_r, iterations)
    ref = short_path(ctx, cost, arms_l, arms_r, iterations, A)
    for ls in local_sizes(ctx, sizes, A):
        got, st = run(ctx, cost, arms_l, arms_r, iterations, A, in_place=in_place, workgroup=True, local_size=ls)
        assert st.path(A) == "workgroup"
        L, shape = (ls, None) if isinstance(ls, int) else ls
        assert st.work_group_sizes(cost.shape[2], A) == (L, shape or st.columns_shape(L, A))
        compare(got, want, cost)
        np.testing.assert_array_equal(got.view(np.uint32), ref.view(np.uint32), err_msg=f"local size {ls}")
    return got


@pytest.mark.parametrize("D,H,W,eta,nb,its", [(16, 37, 53, 4, False, (1, 4)), (9, 23, 31, 9, True, (2, 5)),
                                             (11, 19, 45, 6, False, (3,))])
@pytest.mark.slow
def test_random_odd_sizes_every_group_size(ctx, D, H, W, eta, nb, its):
    """Odd sizes, arms up to 3, 8 (SHORT_MAX, the longest the path serves) and 5,
    1 to 5 iterations; the aggregation really changed the costs."""
    rng = np.random.default_rng(D * 1000 + W)
    cost = random_volume(rng, D, H, W, scale=3.0) - 1.0  # negative costs too
    img_l, img_r = blocky_image(rng, H, W, 4, 0.01), blocky_image(rng, H, W, 3, 0.01)
    arms_l = cross_arms(img_l, eta=eta, include_neighbor=nb)
    arms_r = cross_arms(img_r, eta=eta, include_neighbor=nb)
    assert max(arms_l.max(), arms_r.max()) == max_arm(eta, nb)
    for it in its:
        got = check_all(ctx, cost, arms_l, arms_r, it)
        valid = ~np.isnan(got)
        assert np.abs(got[valid] - cost[valid]).max() > 0.05


@pytest.mark.parametrize("D,H,W", [(20, 7, 12), (5, 1, 40), (4, 30, 1), (1, 1, 1), (3, 2, 2), (40, 3, 70),
                                   (6, 5, 300)])
@pytest.mark.slow
def test_degenerate_and_d_at_least_w(ctx, D, H, W):
    """One row, one column, one pixel, D > W (whole tiles and rows invalid), a
    row of 300 columns (several chunks of the rows ring at every size)."""
    rng = np.random.default_rng(D * 100 + H * 10 + W)
    cost = random_volume(rng, D, H, W)
    arms_l, arms_r = cross_arms(blocky_image(rng, H, W)), cross_arms(blocky_image(rng, H, W))
    check_all(ctx, cost, arms_l, arms_r, 2, sizes=(1, 4, (5, (2, 3)), "max"))


@pytest.mark.slow
def test_kitti_crop_in_place(ctx, shared_data):
    """A real KITTI crop (AD costs, arms from the images), in place as the
    pipeline runs it, 4 iterations."""
    H, W, D = 40, 75, 20
    img_l, img_r = kitti_crop(shared_data, 180, 600, H, W)
    assert img_l.std() > 0.02
    cost = ad_volume(img_l, img_r, D)
    arms_l, arms_r = cross_arms(img_l), cross_arms(img_r)
    check_all(ctx, cost, arms_l, arms_r, 4, sizes=(1, 16, (9, (4, 3)), "max"), in_place=True)
    # and equal to this device's default path (fused or multi on CPUs: bit-identical in float32)
    got, _ = run(ctx, cost, arms_l, arms_r, 4, 3, workgroup=True, local_size=32)
    default, _ = run(ctx, cost, arms_l, arms_r, 4, 3)
    np.testing.assert_array_equal(got.view(np.uint32), default.view(np.uint32))


@pytest.mark.parametrize("ls", [1, 16, (6, (5, 3)), None])
@pytest.mark.slow
def test_half_storage(ctx, shared_data, ls):
    """Half volumes: equal to the short passes in half (the row sums stored as
    half between the passes in both) and within tests/test_half.py's bound of
    the reference on the half input; in place gives the same bits."""
    H, W, D = 30, 47, 12
    img_l, img_r = kitti_crop(shared_data, 120, 300, H, W)
    C = ad_volume(img_l, img_r, D).astype(np.float16)
    arms_l, arms_r = cross_arms(img_l), cross_arms(img_r)
    A, it = 3, 4
    got, st = run(ctx, C, arms_l, arms_r, it, A, np.float16, workgroup=True, local_size=ls)
    assert st.path(A) == "workgroup" and st.half
    np.testing.assert_array_equal(got, short_path(ctx, C, arms_l, arms_r, it, A, np.float16))
    got32 = got.astype(np.float32)
    want = cbca(C.astype(np.float32), arms_l, arms_r, it)
    np.testing.assert_array_equal(np.isnan(got32), np.isnan(want))
    np.testing.assert_allclose(got32, want, rtol=2 * it * 2 ** -11, atol=1e-7)
    assert np.nanmax(np.abs(got32 - want)) > 0  # rounded: the half kernels ran
    inp, _ = run(ctx, C, arms_l, arms_r, it, A, np.float16, in_place=True, workgroup=True, local_size=ls)
    np.testing.assert_array_equal(inp.view(np.uint16), got.view(np.uint16))


def test_default_sizes_within_the_kernel_limits(ctx):
    """The default work-group sizes: within each kernel's maximum, the rows
    groups a multiple of the preferred size unless the row is shorter."""
    st = CBCA(ctx, workgroup=True)
    mr, mc = kernel_max(ctx)
    for W in (1, 13, 53, 1232):
        L, (TX, TY) = st.work_group_sizes(W, 3)
        assert 1 <= L <= min(mr, 256) and 1 <= TX * TY <= min(mc, 256)
        pref = st._limits(st._get(3)[0][0][0], 0)[0]
        assert L % pref == 0 or L == mr
    rng = np.random.default_rng(4)
    D, H, W = 7, 13, 29
    cost = random_volume(rng, D, H, W)
    arms_l, arms_r = cross_arms(blocky_image(rng, H, W)), cross_arms(blocky_image(rng, H, W))
    got, _ = run(ctx, cost, arms_l, arms_r, 2, 3, workgroup=True)
    compare(got, cbca(cost, arms_l, arms_r, 2), cost)


def test_small_local_memory_shrinks_the_groups(ctx, monkeypatch):
    """A device with little local memory (simulated: 600 bytes): the default
    groups shrink to fit, the results stay exact; a forced size that does not
    fit is an InputError naming the local memory."""
    monkeypatch.setattr(type(ctx), "local_mem", property(lambda self: 600))
    st = CBCA(ctx, workgroup=True)
    L, (TX, TY) = st.work_group_sizes(500, 8)
    assert 4 * (L + 16) <= 600 and 5 * (TY + 16) * TX <= 600
    rng = np.random.default_rng(6)
    D, H, W = 5, 21, 40
    cost = random_volume(rng, D, H, W)
    img_l, img_r = blocky_image(rng, H, W, 6, 0.01), blocky_image(rng, H, W, 6, 0.01)
    arms_l, arms_r = cross_arms(img_l, eta=9, include_neighbor=True), cross_arms(img_r, eta=9, include_neighbor=True)
    got, _ = run(ctx, cost, arms_l, arms_r, 2, 8, workgroup=True)
    compare(got, cbca(cost, arms_l, arms_r, 2), cost)
    with pytest.raises(InputError, match="local memory"):
        CBCA(ctx, workgroup=True, local_size=(8, (8, 2))).work_group_sizes(W, 8)  # 720 bytes


def test_long_arms_fall_back_to_running_sums(ctx):
    """max_arm > SHORT_MAX: the work-group path is not taken (running sums)."""
    st = CBCA(ctx, workgroup=True)
    assert st.path(SHORT_MAX) == "workgroup" and st.path(SHORT_MAX + 1) == "running"
    assert CBCA(ctx, workgroup=True, short=False).path(3) == "running"
    assert path_scratch_bytes(228, 1232, 3, "workgroup") == 0
    rng = np.random.default_rng(9)
    D, H, W = 5, 9, 31
    cost = random_volume(rng, D, H, W)
    img = np.full((H, W), 0.5, np.float32)
    arms = cross_arms(img, eta=15)
    got, _ = run(ctx, cost, arms, arms, 1, 14, workgroup=True)
    compare(got, cbca(cost, arms, arms, 1), cost)


def test_bad_input(ctx):
    d_cost = ctx.to_device(np.zeros((2, 3, 4), np.float32))
    d_arms = ctx.to_device(np.zeros((4, 3, 4), np.uint8))
    with pytest.raises(InputError):
        CBCA(ctx, workgroup=True, fused=True)
    with pytest.raises(InputError):
        CBCA(ctx, workgroup=True, local_size=0)
    with pytest.raises(InputError):
        CBCA(ctx, workgroup=True, local_size=(4, (0, 2)))
    mr, mc = kernel_max(ctx)
    with pytest.raises(InputError, match="rows work-group"):
        CBCA(ctx, workgroup=True, local_size=mr + 1)(d_cost, d_arms, d_arms, 2, 3, 4, max_arm=3)
    with pytest.raises(InputError, match="columns work-group"):
        CBCA(ctx, workgroup=True, local_size=(4, (mc, 2)))(d_cost, d_arms, d_arms, 2, 3, 4, max_arm=3)


# -- the path a device gets (the profile's "cbca_workgroup" rule) --------------------
def fake_device(name, type_, units, width):
    return helpers.fake_device(name, type_, units, width, global_mem=1 << 34, max_alloc=1 << 32, max_work_group=1024)


@pytest.mark.parametrize("kind,name,type_,path", [
    ("gpu", "NVIDIA H200", "GPU", "workgroup"), ("gpu", "Oclgrind Simulator", "ALL", "workgroup"),
    ("cpu", "pthread-skylake-avx512", "CPU", "multi"), ("llvmpipe", "llvmpipe (LLVM 15.0.6)", "CPU", "short")])
def test_profile_selects_the_path(ctx, monkeypatch, kind, name, type_, path):
    """A profile built for each device class: the gpu column takes the
    work-group path by default (and on PoCL the stage then runs it, with the
    default sizes, exactly); CPU and llvmpipe keep their paths; explicit
    fused/multi choices still reach the other kernels."""
    import pyopencl as cl

    prof = DeviceProfile.of(fake_device(name, getattr(cl.device_type, type_), 8, 1), cl)
    assert prof.kind == kind
    assert prof.cbca_path(3, SHORT_MAX) == path
    assert prof.cbca_path(SHORT_MAX + 1, SHORT_MAX) == "running"
    assert prof.cbca_path(3, SHORT_MAX, fused=False, multi=False) == "short"
    assert prof.cbca_path(3, SHORT_MAX, fused=True, multi=False) == "fused"
    assert prof.cbca_path(3, SHORT_MAX, workgroup=True) == "workgroup"
    monkeypatch.setattr(ctx, "profile", prof)
    st = CBCA(ctx)
    assert st.path(3) == path and st.workgroup == (path == "workgroup")
    assert CBCA(ctx, fused=False).path(3) == "short"  # an explicit choice beats the rule
    rng = np.random.default_rng(2)
    D, H, W = 6, 11, 27
    cost = random_volume(rng, D, H, W)
    arms_l, arms_r = cross_arms(blocky_image(rng, H, W)), cross_arms(blocky_image(rng, H, W))
    got, _ = run(ctx, cost, arms_l, arms_r, 3, 3)
    np.testing.assert_array_equal(got.view(np.uint32), short_path(ctx, cost, arms_l, arms_r, 3, 3).view(np.uint32))


@pytest.mark.parametrize("dtype", ["float32", "float16"])
@pytest.mark.slow
def test_stereo_matcher_with_the_gpu_profile(ctx, shared_data, monkeypatch, dtype):
    """StereoMatcher on this device with the gpu column of the rules (a profile
    built for a GPU): both CBCA runs take the work-group path and SGM is
    SGMWorkGroup.  Its disparity map and every volume equal, bit for bit, the
    run with the CPU paths that compute the same sums in the same order: SGM's
    one-direction kernels (SGM(paired=False)) and, for CBCA, this device's
    default in float32 (fused or multi on CPUs, bit-identical to the short
    passes there) or the short passes in half (the fused kernels keep their row
    sums in float, the short and work-group passes store them as half)."""
    import pyopencl as cl

    from mccnn_cl.pipeline import StereoMatcher
    from mccnn_cl.stages.sgm import SGM
    from mccnn_cl.stages.sgm_wg import SGMWorkGroup

    left, right = kitti_crop(shared_data, 150, 300, 37, 83)
    D, half = 21, dtype == "float16"
    # the CPU column for the baseline, also on a GPU (whose own profile is the gpu column)
    monkeypatch.setattr(ctx, "profile", DeviceProfile.of(fake_device("Some CPU", cl.device_type.CPU, 2, 16), cl))
    cpu = StereoMatcher(cost="census", max_disparity=D, device=ctx, volume_dtype=dtype)
    cpu.sgm = SGM(ctx, half=half, paired=False)
    if half:
        cpu.cbca = CBCA(ctx, half=True, fused=False, multi=False, workgroup=False)
    assert cpu.cbca.path(3) != "workgroup"
    want = cpu.compute(left, right, return_intermediates=True)
    monkeypatch.setattr(ctx, "profile", DeviceProfile.of(fake_device("Some GPU", cl.device_type.GPU, 64, 1), cl))
    m = StereoMatcher(cost="census", max_disparity=D, device=ctx, volume_dtype=dtype)
    assert m.cbca.path(3) == "workgroup" and isinstance(m.sgm, SGMWorkGroup) and m.cbca.half == half
    got = m.compute(left, right, return_intermediates=True)
    assert "C_CBCA" in got.intermediates and set(got.intermediates) == set(want.intermediates)
    for name, a in got.intermediates.items():
        b = want.intermediates[name]
        assert a.shape == b.shape and a.dtype == b.dtype, name
        np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8), err_msg=name)
    np.testing.assert_array_equal(got.disparity.view(np.uint8), want.disparity.view(np.uint8))
    assert np.isfinite(got.disparity).mean() > 0.5 and np.nanstd(got.disparity) > 0.5


@pytest.fixture
def workgroup_cbca(ctx, monkeypatch):
    """This device's profile told to take the GPU-shaped CBCA (its "cbca_workgroup" rule)."""
    monkeypatch.setitem(RULES["cbca_workgroup"], ctx.profile.kind, True)


def test_stereo_matcher_with_the_workgroup_path(ctx, shared_data, workgroup_cbca):
    """StereoMatcher with the GPU path forced runs it for both CBCA runs; its
    disparity map and every volume equal, bit for bit, the run with the
    short two-pass kernels (and so the fused ones, in float32)."""
    from mccnn_cl.pipeline import StereoMatcher

    left, right = kitti_crop(shared_data, 150, 300, 37, 83)
    D = 21
    m = StereoMatcher(cost="census", max_disparity=D, device=ctx)
    assert m.cbca.path(3) == "workgroup"
    got = m.compute(left, right, return_intermediates=True)
    ref_m = StereoMatcher(cost="census", max_disparity=D, device=ctx)
    ref_m.cbca = CBCA(ctx, fused=False, multi=False, workgroup=False)
    assert ref_m.cbca.path(3) == "short"
    want = ref_m.compute(left, right, return_intermediates=True)
    assert "C_CBCA" in got.intermediates and set(got.intermediates) == set(want.intermediates)
    for name, a in got.intermediates.items():
        b = want.intermediates[name]
        assert a.shape == b.shape and a.dtype == b.dtype, name
        np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8), err_msg=name)
    np.testing.assert_array_equal(got.disparity.view(np.uint8), want.disparity.view(np.uint8))
    assert np.isfinite(got.disparity).mean() > 0.5 and np.nanstd(got.disparity) > 0.5
