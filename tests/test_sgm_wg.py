"""SGMWorkGroup (kernels/sgm_wg.cl, one work-group per path line) against
mccnn_cl.reference.aggregation.sgm and against SGM's one-direction kernels.

Tolerance as tests/test_sgm.py: 2e-5 of (cost range + Pi2) against the
float64 reference (float32 path values re-based every step; an off-by-one
in a minimum, a wrong penalty or an invalid cell in a minimum moves values
by >= P1 / 40 = 0.025 at the defaults); NaN positions exactly.  Against
SGM(paired=False) bit for bit: both accumulate the directions in the same
order with the same float operations per cell (add, subtract, fmin: exactly
rounded), so any difference is a defect of one of them.  Half storage: the
per-cell bound of the roundings to half of tests/test_half.py (half_sgm_bound).

Work-group sizes 1, 4, 16, 64 and the kernel's maximum on this device, with
D below, at and above the group size, odd D, odd H and W; every output is
poisoned first, so a cell left unwritten fails.  On CPU implementations
(PoCL, Intel, Oclgrind in tests/test_oclgrind.py) these prove the barrier
and local-memory logic that a GPU runs.
"""

import numpy as np
import pytest

from conftest import POISON
from helpers import ad_volume, blocky_image, invalid_mask, kitti_crop, random_volume
from mccnn_cl.errors import InputError
from mccnn_cl.reference.aggregation import SGM_DIRECTIONS, sgm, sgm_direction
from mccnn_cl.stages.sgm import SGM
from mccnn_cl.stages.sgm_wg import SGMWorkGroup

F16_POISON = np.float16(-65504.0)
GROUP_SIZES = (1, 4, 16, 64, "max")


def group_sizes(ctx, sizes):
    """``sizes`` with "max" as the kernel's maximum on this device, those above
    it left out (Rusticl's llvmpipe allows 32): the maximum always runs."""
    kmax = ctx.work_group_size(SGMWorkGroup(ctx).kernel())
    return sorted({kmax if L == "max" else L for L in sizes if L == "max" or L <= kmax})


def run(ctx, stage, cost, img_l, img_r, dtype=np.float32, **kw):
    D, H, W = cost.shape
    nbytes = cost.size * np.dtype(dtype).itemsize
    d_out = ctx.empty(nbytes)
    ctx.fill(d_out, POISON if dtype == np.float32 else F16_POISON, nbytes, dtype=dtype)
    d_cost = ctx.to_device(cost)
    stage(d_cost, ctx.to_device(img_l), ctx.to_device(img_r), D, H, W, out=d_out, **kw)
    np.testing.assert_array_equal(ctx.from_device(d_cost, cost.shape, dtype).view(np.uint8),
                                  cost.view(np.uint8))  # input untouched
    return ctx.from_device(d_out, cost.shape, dtype)


def check_reference(got, cost, want, pi2=32.0):
    np.testing.assert_array_equal(np.isnan(got), invalid_mask(*cost.shape))
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    scale = np.nanmax(cost) - np.nanmin(cost) + pi2
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5 * scale)


def check_all(ctx, cost, img_l, img_r, sizes=GROUP_SIZES, **kw):
    """Each work-group size of ``sizes`` (and the kernel's maximum) against the
    reference and, bit for bit, SGM's one-direction kernels; returns the last
    result."""
    want = sgm(cost, img_l, img_r, **kw)
    cpu_path = run(ctx, SGM(ctx, paired=False), cost, img_l, img_r, **kw)
    for L in group_sizes(ctx, (*sizes, "max")):
        st = SGMWorkGroup(ctx, local_size=L)
        got = run(ctx, st, cost, img_l, img_r, **kw)
        assert st.work_group_size(cost.shape[0]) == L
        check_reference(got, cost, want, kw.get("pi2", 32.0))
        np.testing.assert_array_equal(got.view(np.uint32), cpu_path.view(np.uint32), err_msg=f"work-group {L}")
    return got


@pytest.mark.parametrize("D", [16, 20, 70])
@pytest.mark.slow
def test_random_odd_size_every_group_size(ctx, D):
    """37 x 53, D = 16, 20 (levels below and above 16 and 4; not a multiple of
    16 or 64) and 70 (more levels than 64 work-items: several per work-item,
    unevenly); the smoothing really changed the costs."""
    rng = np.random.default_rng(D)
    H, W = 37, 53
    cost = random_volume(rng, D, H, W, scale=2.0)
    img_l, img_r = blocky_image(rng, H, W, 4, 0.05), blocky_image(rng, H, W, 4, 0.05)
    got = check_all(ctx, cost, img_l, img_r)
    valid = ~np.isnan(got)
    assert np.abs(got[valid] - cost[valid]).max() > 0.5


@pytest.mark.gpu_check
def test_default_group_size(ctx):
    """The default size: within the kernel's limit, covering D when it can."""
    rng = np.random.default_rng(3)
    D, H, W = 37, 9, 45
    cost = random_volume(rng, D, H, W, scale=3.0)
    img_l, img_r = blocky_image(rng, H, W), blocky_image(rng, H, W)
    st = SGMWorkGroup(ctx)
    L = st.work_group_size(D)
    kmax = ctx.work_group_size(st.kernel())
    assert 1 <= L <= kmax and (L >= D or L == kmax)
    got = run(ctx, st, cost, img_l, img_r)
    check_reference(got, cost, sgm(cost, img_l, img_r))


@pytest.mark.gpu_check
def test_variants_and_parameters(ctx):
    """Both penalty variants, P2 = Pi1 Pi2, the outside-the-image choice, other
    q1, q2, v and tau_so, at group sizes 4 and 16."""
    rng = np.random.default_rng(12)
    D, H, W = 11, 17, 23
    cost = random_volume(rng, D, H, W, scale=5.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.1), blocky_image(rng, H, W, 3, 0.1)
    a = check_all(ctx, cost, img_l, img_r, sizes=(4, 16), variant="code", pi1=2.0, pi2=7.0, p2_times_pi1=True)
    b = check_all(ctx, cost, img_l, img_r, sizes=(4, 16), outside_large=False, pi1=2.0, pi2=14.0, q1=3.0,
                  q2=5.0, v=4.0, tau_so=0.1)
    assert np.nanmax(np.abs(a - b)) > 0.01


@pytest.mark.parametrize("D,H,W", [(20, 7, 12), (5, 1, 40), (4, 30, 1), (1, 1, 1), (3, 2, 2), (40, 3, 5),
                                   (17, 4, 33), (65, 3, 70)])
def test_degenerate_and_d_at_least_w(ctx, D, H, W):
    """One row, one column, one pixel, D > W, D = 65 just over 64 work-items."""
    rng = np.random.default_rng(D * 100 + H * 10 + W)
    cost = random_volume(rng, D, H, W)
    check_all(ctx, cost, blocky_image(rng, H, W), blocky_image(rng, H, W), sizes=(1, 4, 64))


@pytest.mark.slow
def test_largest_group_size_on_many_levels(ctx):
    """The kernel's maximum work-group size (4096 on PoCL) with D = 130: most
    work-items own no level, the reduction runs through every tree level."""
    rng = np.random.default_rng(5)
    D, H, W = 130, 5, 141
    cost = random_volume(rng, D, H, W, scale=2.0)
    check_all(ctx, cost, blocky_image(rng, H, W), blocky_image(rng, H, W), sizes=(128, 7))


@pytest.mark.gpu_check
def test_kitti_crop_against_reference_and_sgm(ctx, shared_data):
    """A real KITTI crop (AD costs, D = 30 over 70 columns), both penalty
    variants and the outside-the-image choice."""
    H, W, D = 20, 70, 30
    imgs = kitti_crop(shared_data, 180, 400, H, W)
    assert imgs[0].std() > 0.02
    cost = ad_volume(imgs[0], imgs[1], D)
    a = check_all(ctx, cost, imgs[0], imgs[1], sizes=(16, 64))
    b = check_all(ctx, cost, imgs[0], imgs[1], sizes=(4, 32), variant="code", outside_large=False, pi1=2.0,
                  pi2=14.0)
    assert np.nanmax(np.abs(a - b)) > 0.01


def half_sgm_bound(C32, img_l, img_r):
    """The reference C_SGM of the half input (float64) and the per-cell bound of
    |half SGM - reference| of tests/test_half.py (half_sgm_bound) for the order
    in which SGMWorkGroup and SGM(paired=False) store into the half output:
    C_lr, C_lr + C_rl, C_lr + C_rl + C_tb, then (.. + C_bt) / 4, each rounded to
    nearest (<= 2^-11 of the value stored, costs >= 0), plus 2^-20 of C_SGM for
    float32 against float64 and 2^-23 for stores below half's normal range."""
    lr, rl, tb, bt = (sgm_direction(C32, img_l, img_r, r).astype(np.float64) for r in SGM_DIRECTIONS)
    want = (lr + rl + tb + bt) / 4
    u = 2.0 ** -11
    return want, u * ((lr + (lr + rl) + (lr + rl + tb)) / 4 + want) + 2.0 ** -20 * want + 2.0 ** -23


@pytest.mark.parametrize("L", [1, 16, 32])
def test_half_storage(ctx, shared_data, L):
    """Half volumes (VOL_HALF=1): equal to SGM(half=True, paired=False) (the
    same in-place accumulation in half) and within the per-cell bound of the
    roundings to half (half_sgm_bound) of the reference on the half input."""
    L_img, R_img = kitti_crop(shared_data, 150, 60, 20, 45)
    D, H, W = 24, 20, 45
    C = ad_volume(L_img, R_img, D).astype(np.float16)
    C32 = C.astype(np.float32)
    got = run(ctx, SGMWorkGroup(ctx, half=True, local_size=L), C, L_img, R_img, dtype=np.float16)
    cpu_path = run(ctx, SGM(ctx, half=True, paired=False), C, L_img, R_img, dtype=np.float16)
    # equal values, NaN in the same cells (the NaN's bits may differ: Rusticl
    # stores NAN as 0x7fff in one kernel and 0x7e00 in the other)
    np.testing.assert_array_equal(got, cpu_path)
    got = got.astype(np.float64)
    want, bound = half_sgm_bound(C32, L_img, R_img)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    v = ~np.isnan(want)
    ratio = np.abs(got[v] - want[v]) / bound[v]
    assert ratio.max() <= 1.0, f"{np.sum(ratio > 1)} cells beyond the rounding bound, worst {ratio.max():.3f} x"
    assert np.abs(got[v] - want[v]).max() > 0  # rounding happened: the half path ran


@pytest.mark.gpu_check
@pytest.mark.parametrize("cols", [8, 16, 32])
def test_columns_per_work_group_give_the_same_bits(ctx, shared_data, cols):
    """cols (kernel sgm_wg_cols, the vertical paths with adjacent columns per work-group):
    the same bits as a work-group per column, on random volumes with NaN costs (D above
    and below the level slices, W not a multiple of the columns, one row, one column),
    on a real KITTI crop with both penalty variants, and with half volumes; and within
    the reference's tolerance."""
    rng = np.random.default_rng(cols)
    cases = [((20, 7, 12), {}), ((70, 9, 37), {"variant": "code", "outside_large": False}), ((5, 1, 40), {}),
             ((4, 30, 1), {}), ((33, 12, 17), {"pi1": 2.0, "pi2": 7.0, "p2_times_pi1": True})]
    for (D, H, W), kw in cases:
        cost = random_volume(rng, D, H, W, scale=3.0)
        img_l, img_r = blocky_image(rng, H, W), blocky_image(rng, H, W)
        st = SGMWorkGroup(ctx, cols=cols)
        assert st.cols_shape(D) is not None
        got = run(ctx, st, cost, img_l, img_r, **kw)
        want = run(ctx, SGMWorkGroup(ctx), cost, img_l, img_r, **kw)
        np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32), err_msg=f"{D}x{H}x{W} {kw}")
        check_reference(got, cost, sgm(cost, img_l, img_r, **kw), kw.get("pi2", 32.0))
    imgs = kitti_crop(shared_data, 180, 400, 20, 70)
    cost = ad_volume(imgs[0], imgs[1], 30)
    for kw in ({}, {"variant": "code", "outside_large": False, "pi1": 2.0, "pi2": 14.0}):
        got = run(ctx, SGMWorkGroup(ctx, cols=cols), cost, imgs[0], imgs[1], **kw)
        np.testing.assert_array_equal(got.view(np.uint32), run(ctx, SGMWorkGroup(ctx), cost, *imgs, **kw)
                                      .view(np.uint32))
        check_reference(got, cost, sgm(cost, imgs[0], imgs[1], **kw), kw.get("pi2", 32.0))
    C = cost.astype(np.float16)
    got = run(ctx, SGMWorkGroup(ctx, half=True, cols=cols), C, *imgs, dtype=np.float16)
    np.testing.assert_array_equal(got, run(ctx, SGMWorkGroup(ctx, half=True), C, *imgs, dtype=np.float16))


@pytest.mark.parametrize("half", [False, True], ids=["float", "half"])
def test_invalid_cells_holding_finite_values_change_nothing(ctx, half):
    """Validity by index, never by value: invalid cells (x < d) holding -1000, 0
    or +1000 instead of NaN give the same bits as NaN there (NaN in the invalid
    output cells included), for a work-group per path line (sizes 1, 16 and the
    maximum) and per 8, 16 and 32 columns, float and half volumes.  fmin drops
    NaN, so a kernel that lets an invalid cell into a minimum passes on
    NaN-filled volumes alone."""
    rng = np.random.default_rng(29)
    dtype = np.float16 if half else np.float32
    bits = np.uint16 if half else np.uint32
    for D, H, W in ((21, 5, 45), (30, 4, 23)):
        cost = random_volume(rng, D, H, W, scale=3.0).astype(dtype)
        img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
        stages = [SGMWorkGroup(ctx, half=half, local_size=L) for L in group_sizes(ctx, (1, 16, "max"))]
        stages += [SGMWorkGroup(ctx, half=half, cols=c) for c in (8, 16, 32)]
        for st in stages:
            base = run(ctx, st, cost, img_l, img_r, dtype=dtype)
            np.testing.assert_array_equal(np.isnan(base), invalid_mask(D, H, W))
            for value in (-1000.0, 0.0, 1000.0):
                dirty = cost.copy()
                dirty[invalid_mask(D, H, W)] = value
                got = run(ctx, st, dirty, img_l, img_r, dtype=dtype)
                np.testing.assert_array_equal(got.view(bits), base.view(bits), err_msg=(
                    f"{D}x{H}x{W} local size {st.local_size} cols {st.wg_cols}: invalid cells = {value}"))
        if not half:
            check_reference(base, cost, sgm(cost, img_l, img_r))


def test_columns_choice_is_checked(ctx):
    with pytest.raises(InputError, match="columns must be one of"):
        SGMWorkGroup(ctx, cols=12)
    assert SGMWorkGroup(ctx).cols_shape(64) is None  # 0: a work-group per column


def test_allocates_output_and_reuses_stage(ctx):
    """out=None allocates; one stage object serves several D (a new local size each)."""
    rng = np.random.default_rng(8)
    st = SGMWorkGroup(ctx)
    for D, H, W in ((6, 5, 9), (33, 4, 40)):
        cost = random_volume(rng, D, H, W)
        img = blocky_image(rng, H, W)
        d_out = st(ctx.to_device(cost), ctx.to_device(img), ctx.to_device(img), D, H, W)
        check_reference(ctx.from_device(d_out, cost.shape), cost, sgm(cost, img, img))
    assert SGMWorkGroup.scratch_bytes(33, 40) == 0


@pytest.mark.gpu_check
def test_bad_input(ctx):
    cost = np.zeros((2, 3, 4), np.float32)
    d_cost = ctx.to_device(cost)
    d_img = ctx.to_device(np.zeros((3, 4), np.float32))
    with pytest.raises(InputError):
        SGMWorkGroup(ctx)(d_cost, d_img, d_img, 2, 3, 4, out=d_cost)
    with pytest.raises(InputError):
        SGMWorkGroup(ctx)(d_cost, d_img, d_img, 2, 3, 4, variant="other")
    with pytest.raises(InputError):
        SGMWorkGroup(ctx)(d_cost, d_img, d_img, 0, 3, 4)
    with pytest.raises(InputError):
        SGMWorkGroup(ctx, local_size=0)
    too_big = ctx.work_group_size(SGMWorkGroup(ctx).kernel()) + 1
    with pytest.raises(InputError):
        SGMWorkGroup(ctx, local_size=too_big)(d_cost, d_img, d_img, 2, 3, 4)


# -- the stage a device gets (the profile's "sgm_stage" rule) -------------------
@pytest.fixture
def workgroup_sgm(ctx, monkeypatch):
    """This device's profile told to take the GPU-shaped SGM (its "sgm_stage" rule)."""
    from mccnn_cl.opencl.device import RULES

    monkeypatch.setitem(RULES["sgm_stage"], ctx.profile.kind, "workgroup")


@pytest.mark.gpu_check
def test_stereo_matcher_with_the_workgroup_stage(ctx, shared_data, workgroup_sgm):
    """StereoMatcher with the GPU path forced runs SGMWorkGroup; its disparity
    map and every volume equal, bit for bit, the run with SGM's one-direction
    kernels (SGM(paired=False)); the CPU default on two compute units is the
    paired sweeps, equal to rounding only, so it is not the reference here."""
    from mccnn_cl.pipeline import StereoMatcher

    left, right = kitti_crop(shared_data, 150, 300, 37, 83)
    D = 21
    m = StereoMatcher(cost="census", max_disparity=D, device=ctx)
    assert isinstance(m.sgm, SGMWorkGroup)
    got = m.compute(left, right, return_intermediates=True)
    ref_m = StereoMatcher(cost="census", max_disparity=D, device=ctx)
    ref_m.sgm = SGM(ctx, paired=False)
    want = ref_m.compute(left, right, return_intermediates=True)
    assert "C_SGM" in got.intermediates and set(got.intermediates) == set(want.intermediates)
    for name, a in got.intermediates.items():
        b = want.intermediates[name]
        assert a.shape == b.shape and a.dtype == b.dtype, name
        np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8), err_msg=name)
    np.testing.assert_array_equal(got.disparity.view(np.uint8), want.disparity.view(np.uint8))
    assert np.isfinite(got.disparity).mean() > 0.5 and np.nanstd(got.disparity) > 0.5


def test_the_columns_rule_reaches_the_stage(ctx, workgroup_sgm, monkeypatch):
    """make_sgm hands the profile's sgm_wg_cols to the work-group stage (the tuner's choice)."""
    from mccnn_cl.opencl.device import RULES
    from mccnn_cl.stages.sgm_select import make_sgm

    assert make_sgm(ctx).wg_cols == 0
    monkeypatch.setitem(RULES["sgm_wg_cols"], ctx.profile.kind, 16)
    st = make_sgm(ctx)
    assert isinstance(st, SGMWorkGroup) and st.wg_cols == 16 and st.cols_shape(64)[0] == 16
