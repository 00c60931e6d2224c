"""SGM: kernels/sgm.cl against mccnn_cl.reference.aggregation.sgm.

Tolerance: the reference works in float64 (gradient decisions in float32,
exactly as the kernel); the kernel's float32 path values are re-based at
every step (C - min + ...), so rounding errors stay a few ulp of the value
range, |C| + P2, and do not compound along the path.  We allow 2e-5 of
(cost range + Pi2): an off-by-one in a minimum, a wrong penalty or an invalid
cell entering a minimum moves values by at least P1 / 40 = 0.025 (at the
defaults), far beyond it.  NaN positions must match exactly.
"""

import cv2
import numpy as np
import pytest

from conftest import POISON, POISON_F16
from mccnn_cl.errors import InputError
from mccnn_cl.reference.aggregation import SGM_DIRECTIONS, sgm, sgm_direction
from mccnn_cl.reference.disparity import right_cost_volume
from mccnn_cl.stages.sgm import SGM, state_bytes
from helpers import ad_volume, blocky_image, invalid_mask, kitti_crop, random_volume


def run_sgm(ctx, cost, img_l, img_r, prefetch=None, band=None, cols=None, fused_rows=None, specialize=None,
            whole_tiles=None, paired=None, width=None, mirror_reads=None, **kw):
    D, H, W = cost.shape
    d_out = ctx.empty(cost.nbytes)
    ctx.fill(d_out, POISON, cost.nbytes)
    d_cost = ctx.to_device(cost)
    SGM(ctx, prefetch=prefetch, band=band, cols=cols, fused_rows=fused_rows, specialize=specialize,
        whole_tiles=whole_tiles, paired=paired, width=width, mirror_reads=mirror_reads)(
        d_cost, ctx.to_device(img_l), ctx.to_device(img_r), D, H, W, out=d_out, **kw)
    np.testing.assert_array_equal(ctx.from_device(d_cost, cost.shape), cost)  # input untouched
    return ctx.from_device(d_out, cost.shape)


def check(ctx, cost, img_l, img_r, prefetch=None, band=None, cols=None, fused_rows=None, specialize=None,
          whole_tiles=None, paired=None, width=None, **kw):
    got = run_sgm(ctx, cost, img_l, img_r, prefetch=prefetch, band=band, cols=cols, fused_rows=fused_rows,
                  specialize=specialize, whole_tiles=whole_tiles, paired=paired, width=width, **kw)
    want = sgm(cost, img_l, img_r, **kw)
    np.testing.assert_array_equal(np.isnan(got), invalid_mask(*cost.shape))
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    scale = np.nanmax(cost) - np.nanmin(cost) + kw.get("pi2", 32.0)
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5 * scale)
    return got, want


@pytest.mark.gpu_check
def test_random_odd_size(ctx):
    rng = np.random.default_rng(11)
    D, H, W = 16, 37, 53
    cost = random_volume(rng, D, H, W, scale=2.0)
    img_l, img_r = blocky_image(rng, H, W, 4, 0.05), blocky_image(rng, H, W, 4, 0.05)
    got, _ = check(ctx, cost, img_l, img_r)
    valid = ~np.isnan(got)
    assert np.abs(got[valid] - cost[valid]).max() > 0.5  # smoothing did something


@pytest.mark.gpu_check
def test_variants_and_parameters(ctx):
    rng = np.random.default_rng(12)
    D, H, W = 11, 17, 23
    cost = random_volume(rng, D, H, W, scale=5.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.1), blocky_image(rng, H, W, 3, 0.1)
    a, _ = check(ctx, cost, img_l, img_r, variant="code", pi1=2.0, pi2=7.0, p2_times_pi1=True)
    b, _ = check(ctx, cost, img_l, img_r, outside_large=False, pi1=2.0, pi2=14.0, q1=3.0, q2=5.0,
                 v=4.0, tau_so=0.1)
    assert np.nanmax(np.abs(a - b)) > 0.01


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
    check(ctx, ad_volume(imgs[0], imgs[1], D), imgs[0], imgs[1])


@pytest.mark.gpu_check
def test_d_at_least_w_single_row_single_column(ctx):
    rng = np.random.default_rng(13)
    for D, H, W in [(20, 7, 12), (5, 1, 40), (4, 30, 1), (1, 1, 1), (3, 2, 2), (40, 3, 5), (5, 3, 32), (17, 4, 33), (37, 9, 45)]:
        cost = random_volume(rng, D, H, W)
        check(ctx, cost, blocky_image(rng, H, W), blocky_image(rng, H, W))


@pytest.mark.slow
def test_several_tiles_and_interior_chunks_with_and_without_prefetch(ctx):
    """D = 40: three 16-level tiles in sgm_rows, the last one partial; W = 100:
    interior chunks (right-image gradients read as whole vectors), edge chunks
    (read element by element) and a partial last chunk.  Both builds, with and
    without CPU prefetch instructions, match the reference, and each other bit
    for bit (prefetches are hints)."""
    rng = np.random.default_rng(17)
    D, H, W = 40, 3, 100
    cost = random_volume(rng, D, H, W, scale=3.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
    for paired in (False, True):
        with_pf, _ = check(ctx, cost, img_l, img_r, prefetch=True, outside_large=False, paired=paired)
        without_pf, _ = check(ctx, cost, img_l, img_r, prefetch=False, outside_large=False, paired=paired)
        np.testing.assert_array_equal(with_pf, without_pf)


@pytest.mark.slow
def test_whole_tile_path_and_general_path(ctx):
    """sgm_rows moves whole 16 x 16 tiles by plain loads and stores
    (whole_tiles, default except on Rusticl) and the rest element-wise; with
    whole_tiles=False every tile takes the general path.  D = 40, W = 100:
    whole tiles, partial last tiles (levels) and a partial last chunk
    (columns), both row directions in one launch and in two.  Both builds
    match the reference, and each other bit for bit."""
    rng = np.random.default_rng(19)
    D, H, W = 40, 4, 100
    cost = random_volume(rng, D, H, W, scale=3.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
    for fused, paired in ((True, False), (False, False), (None, True)):
        whole, _ = check(ctx, cost, img_l, img_r, whole_tiles=True, fused_rows=fused, paired=paired)
        general, _ = check(ctx, cost, img_l, img_r, whole_tiles=False, fused_rows=fused, paired=paired)
        np.testing.assert_array_equal(whole.view(np.uint32), general.view(np.uint32))


#: (band, cols, fused_rows, specialize) configurations: whole image / bands
#: of 1 and 3 rows (the vertical path's state carried between launches), 16
#: to 128 columns per sgm_columns work-item (one to eight groups of 16,
#: partial strips), the two row directions in one launch or two, the column
#: kernel's row loop specialised per case or not (the other tests run each
#: device's default, on CPUs 128 columns specialised; here the wide strips
#: are unspecialised because Rusticl's llvmpipe takes minutes to compile a
#: specialised 128-column kernel).
CONFIGS = [(0, 16, False, True), (1, 32, True, False), (3, 128, False, False), (0, 64, True, False),
           (5, 48, True, True)]


@pytest.mark.parametrize("D,H,W", [(21, 9, 150), (40, 6, 23), (17, 13, 130)])
@pytest.mark.slow
def test_configurations_match_reference_and_each_other(ctx, D, H, W):
    """Every band / columns / fused-rows configuration against the reference,
    and bit for bit against the others (they reorder work, never arithmetic).  W not a
    multiple of 16, 32 or 128; D not a multiple of 16; D > W."""
    rng = np.random.default_rng(D * 1000 + W)
    cost = random_volume(rng, D, H, W, scale=3.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
    first = None
    for band, cols, fused, spec in CONFIGS:
        got, _ = check(ctx, cost, img_l, img_r, band=band, cols=cols, fused_rows=fused, specialize=spec,
                       paired=False)
        if first is None:
            first = got
        np.testing.assert_array_equal(got.view(np.uint32), first.view(np.uint32),
                                      err_msg=f"band={band} cols={cols} fused={fused} specialize={spec}")


def test_configurations_on_kitti_crop(ctx, shared_data):
    """A real KITTI crop (AD costs, D = 30 over 70 columns): every configuration
    matches the reference and the others bit for bit."""
    H, W, D = 20, 70, 30
    imgs = kitti_crop(shared_data, 180, 400, H, W)
    cost = ad_volume(imgs[0], imgs[1], D)
    first = None
    for band, cols, fused, spec in CONFIGS:
        got, _ = check(ctx, cost, imgs[0], imgs[1], band=band, cols=cols, fused_rows=fused, specialize=spec,
                       paired=False)
        if first is None:
            first = got
        np.testing.assert_array_equal(got.view(np.uint32), first.view(np.uint32),
                                      err_msg=f"band={band} cols={cols} fused={fused} specialize={spec}")


@pytest.mark.parametrize("D,H,W", [(16, 37, 53), (40, 9, 70), (21, 10, 150), (37, 5, 45), (20, 7, 12),
                                   (5, 1, 40), (6, 2, 33), (4, 30, 1), (1, 1, 1), (3, 3, 16), (64, 4, 100)])
def test_paired_sweeps_match_reference_and_one_direction_kernels(ctx, D, H, W):
    """The paired sweeps (sgm_paired: two work-items, each adding one
    horizontal and one vertical path, two launches; the default on CPUs with
    <= 2 compute units) against the reference and against the one-direction
    kernels.  They sum the directions in another order, ((C_lr + C_tb) +
    (C_rl + C_bt)) / 4 instead of (((C_lr + C_rl) + C_tb) + C_bt) / 4, so the
    two agree to rounding, not bit for bit.  Odd and even H (the split row
    h = H // 2; H = 1: one work-item walks nothing in the first launch), W
    below, at and above 16 and not a multiple of it, D > W, partial tiles."""
    rng = np.random.default_rng(D * 7919 + H * 31 + W)
    cost = random_volume(rng, D, H, W, scale=3.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
    paired, want = check(ctx, cost, img_l, img_r, paired=True)
    one_dir, _ = check(ctx, cost, img_l, img_r, paired=False)
    scale = np.nanmax(cost) - np.nanmin(cost) + 32.0
    np.testing.assert_allclose(paired, one_dir, rtol=0, atol=2e-5 * scale)


@pytest.mark.gpu_check
def test_paired_sweeps_on_real_images_both_variants(ctx, shared_data):
    """Paired sweeps on a real KITTI crop (AD costs), both penalty variants and
    the outside-the-image choice, against the reference."""
    H, W, D = 23, 90, 40
    imgs = kitti_crop(shared_data, 150, 600, H, W)
    cost = ad_volume(imgs[0], imgs[1], D)
    a, _ = check(ctx, cost, imgs[0], imgs[1], paired=True)
    b, _ = check(ctx, cost, imgs[0], imgs[1], paired=True, variant="code", outside_large=False, pi1=2.0, pi2=14.0)
    assert np.nanmax(np.abs(a - b)) > 0.01


def mirrored(cost):
    """The right-reference volume C_R'(d, y, x) = C(d, y, W - 1 + d - x), NaN
    where x < d (what RightReference.volume makes in place)."""
    return np.ascontiguousarray(right_cost_volume(cost)[:, :, ::-1])


@pytest.mark.parametrize("D,H,W", [(16, 37, 53), (40, 9, 70), (21, 10, 150), (37, 5, 45), (20, 7, 12),
                                   (5, 1, 40), (6, 2, 33), (4, 30, 1), (1, 1, 1), (3, 3, 16), (64, 4, 100),
                                   (24, 3, 48), (9, 2, 8)])
def test_paired_sweeps_read_the_volume_mirrored(ctx, D, H, W):
    """SGM(mirror=True) on C (the paired sweeps read C as the right-reference
    volume C_R', which the pipeline then never makes) gives the bits of SGM on
    C_R' made explicitly, which matches the reference: both vector widths,
    whole tiles or not, half storage.  C's cells x < d are no cells of C_R'
    and hold +1000 here, so reading one shows.  W not a multiple of 8 or 16
    (the partial last chunk), D > W, the diagonal tiles (x0 < d), one row, one
    column."""
    rng = np.random.default_rng(D * 613 + H * 17 + W)
    cost = random_volume(rng, D, H, W, scale=3.0)
    dirty = with_invalid(cost, 1000.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
    for cfg in (dict(width=8), dict(width=16), dict(width=8, whole_tiles=False)):
        want, _ = check(ctx, mirrored(cost), img_l, img_r, paired=True, **cfg)
        got = run_sgm(ctx, dirty, img_l, img_r, paired=True, mirror=True, **cfg)
        np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32), err_msg=str(cfg))
    halves = []
    for c, mirror in ((mirrored(cost), False), (dirty, True)):
        c16 = c.astype(np.float16)
        d_out = ctx.empty(c16.nbytes)
        ctx.fill(d_out, POISON_F16, c16.nbytes, np.float16)
        SGM(ctx, half=True, paired=True, width=8)(ctx.to_device(c16), ctx.to_device(img_l), ctx.to_device(img_r),
                                                  D, H, W, out=d_out, mirror=mirror)
        halves.append(ctx.from_device(d_out, cost.shape, np.float16))
    np.testing.assert_array_equal(halves[1].view(np.uint16), halves[0].view(np.uint16))
    np.testing.assert_array_equal(np.isnan(halves[1]), invalid_mask(D, H, W))


@pytest.mark.gpu_check
def test_mirrored_reads_on_real_images(ctx, shared_data):
    """The mirrored reads on a real KITTI crop (AD costs): the pipeline's right
    reference, whose images are the mirrored right and left ones, against the
    reference on the explicitly mirrored volume."""
    H, W, D = 23, 90, 40
    left, right = kitti_crop(shared_data, 150, 600, H, W)
    cost = ad_volume(left, right, D)
    k_l, k_r = np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1])
    want, _ = check(ctx, mirrored(cost), k_l, k_r, paired=True)
    got = run_sgm(ctx, cost, k_l, k_r, paired=True, mirror=True)
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))


def test_mirror_needs_the_paired_sweeps(ctx):
    """Only the paired sweeps read a volume mirrored; the one-direction kernels refuse."""
    rng = np.random.default_rng(5)
    cost = random_volume(rng, 4, 3, 10)
    img = blocky_image(rng, 3, 10, 2, 0.1)
    assert SGM(ctx, paired=True, mirror_reads=True).reads_mirrored
    assert not SGM(ctx, paired=False, mirror_reads=True).reads_mirrored
    # the paired sweeps still read mirrored when asked, whatever the right reference prefers (sgm_mirror_reads)
    assert not SGM(ctx, paired=True, mirror_reads=False).reads_mirrored
    want = run_sgm(ctx, cost, img, img, paired=True, mirror=True)
    got = run_sgm(ctx, cost, img, img, paired=True, mirror=True, mirror_reads=False)
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
    with pytest.raises(ValueError, match="paired"):
        run_sgm(ctx, cost, img, img, paired=False, mirror=True)
    from mccnn_cl.stages.sgm_wg import SGMWorkGroup
    assert not SGMWorkGroup(ctx).reads_mirrored
    with pytest.raises(ValueError, match="paired"):
        SGMWorkGroup(ctx)(ctx.to_device(cost), ctx.to_device(img), ctx.to_device(img), *cost.shape, mirror=True)


@pytest.mark.parametrize("D,H,W", [(40, 9, 170), (64, 12, 300)])
def test_paths_walked_in_several_launches_are_bit_identical(ctx, D, H, W):
    """Under a loop limit (llvmpipe's, on Rusticl: 65535 iterations per
    work-item) the one-direction kernels walk the vertical paths in bands of
    rows and the rows in ranges of chunks, their path state kept between
    launches.  Forced here with small limits (3000: ranges of 6 chunks at
    D = 64; 700: one chunk or row per launch) on any device: bit-identical to
    one launch per path, and to the reference."""
    rng = np.random.default_rng(D + W)
    cost = random_volume(rng, D, H, W, scale=2.0)
    img_l, img_r = blocky_image(rng, H, W, 4, 0.05), blocky_image(rng, H, W, 4, 0.05)
    whole, _ = check(ctx, cost, img_l, img_r, paired=False)
    for limit in (3000, 700):
        d_out = ctx.empty(cost.nbytes)
        ctx.fill(d_out, POISON, cost.nbytes)
        SGM(ctx, paired=False, loop_limit=limit)(ctx.to_device(cost), ctx.to_device(img_l), ctx.to_device(img_r),
                                                 D, H, W, out=d_out)
        got = ctx.from_device(d_out, cost.shape)
        np.testing.assert_array_equal(got.view(np.uint32), whole.view(np.uint32), err_msg=f"loop_limit={limit}")
    with pytest.raises(InputError):  # the paired sweeps walk half the image per work-item
        SGM(ctx, paired=True, loop_limit=700)(ctx.to_device(cost), ctx.to_device(img_l), ctx.to_device(img_r),
                                              D, H, W)


@pytest.mark.parametrize("D,H,W", [(40, 9, 70), (21, 10, 150), (50, 5, 45), (3, 3, 16), (64, 4, 100)])
def test_vector_widths_are_bit_identical(ctx, D, H, W):
    """sgm.cl on 8-wide vectors (SGM_VW 8, the rule on CPUs) and on 16-wide ones: the paired sweeps, the one-direction kernels (whole
    image, bands with 48 columns per work-item, specialised or not) and the paired
    sweeps on half-precision volumes give the same bits, and match the reference.  W
    not a multiple of 8 or 16, partial tiles, D > W."""
    rng = np.random.default_rng(D * 131 + H * 7 + W)
    cost = random_volume(rng, D, H, W, scale=3.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
    for cfg in (dict(paired=True), dict(paired=False), dict(paired=False, band=3, cols=48, specialize=False)):
        wide, _ = check(ctx, cost, img_l, img_r, width=16, **cfg)
        narrow, _ = check(ctx, cost, img_l, img_r, width=8, **cfg)
        np.testing.assert_array_equal(narrow.view(np.uint32), wide.view(np.uint32), err_msg=str(cfg))
    d_cost = ctx.to_device(cost.astype(np.float16))
    halves = []
    for width in (16, 8):
        d_out = ctx.empty(cost.size * 2)
        ctx.fill(d_out, POISON_F16, cost.size * 2, np.float16)
        SGM(ctx, half=True, paired=True, width=width)(d_cost, ctx.to_device(img_l), ctx.to_device(img_r), D, H, W,
                                                      out=d_out)
        halves.append(ctx.from_device(d_out, cost.shape, np.float16))
    np.testing.assert_array_equal(halves[1].view(np.uint16), halves[0].view(np.uint16))
    np.testing.assert_array_equal(np.isnan(halves[0]), invalid_mask(D, H, W))


#: Values held by invalid cells (x < d) instead of NaN: below, inside and far
#: above every cost.  fmin drops NaN, so a kernel that lets an invalid cell
#: into a minimum (or into the path state) passes on NaN-filled volumes alone.
FINITE_FILLS = (-1000.0, 0.0, 1000.0)

#: The stage forms the other tests parametrise: the paired sweeps and the
#: one-direction kernels (sgm_rows, sgm_columns), both vector widths, bands and
#: column strips, specialised or not, fused row directions or not, the whole
#: tile path or the general one, prefetches, paths walked in several launches
#: (loop_limit), half storage; each a build the other tests make on CPUs too.
FILL_FORMS = [
    dict(paired=True, width=16), dict(paired=True, width=8),
    dict(paired=False, width=16), dict(paired=False, width=8),
    dict(paired=False, width=8, band=3, cols=48, specialize=False),
    dict(paired=False, band=1, cols=128, fused_rows=True, whole_tiles=False),
    dict(paired=False, cols=16, fused_rows=False, whole_tiles=True, specialize=True, prefetch=True),
    dict(paired=False, loop_limit=700),
    dict(paired=True, half=True), dict(paired=False, half=True),
]


def with_invalid(cost, value):
    """``cost`` with ``value`` in its invalid cells (x < d) instead of NaN."""
    dirty = cost.copy()
    dirty[invalid_mask(*cost.shape)] = value
    return dirty


def run_form(ctx, form, cost, img_l, img_r):
    """SGM(ctx, **form) on ``cost`` (stored as half with half=True) into a poisoned output."""
    D, H, W = cost.shape
    dtype = np.float16 if form.get("half") else np.float32
    c = cost.astype(dtype)
    d_out = ctx.empty(c.nbytes)
    ctx.fill(d_out, POISON_F16 if dtype == np.float16 else POISON, c.nbytes, dtype)
    SGM(ctx, **form)(ctx.to_device(c), ctx.to_device(img_l), ctx.to_device(img_r), D, H, W, out=d_out)
    return ctx.from_device(d_out, cost.shape, dtype)


@pytest.mark.parametrize("form", FILL_FORMS, ids=lambda f: "-".join(f"{k}={v}" for k, v in f.items()))
def test_invalid_cells_holding_finite_values_change_nothing(ctx, form):
    """Validity by index, never by value (sgm.cl's header): a volume whose
    invalid cells hold -1000, 0 or +1000 instead of NaN gives the same bits as
    the NaN-filled one (NaN in the invalid output cells included), which matches
    the reference.  D = 21 over W = 45 (whole and partial tiles and chunks) and
    D = 30 > W = 23 (planes with no valid cell)."""
    rng = np.random.default_rng(23)
    for D, H, W in ((21, 5, 45), (30, 4, 23)):
        cost = random_volume(rng, D, H, W, scale=3.0)
        img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
        base = run_form(ctx, form, cost, img_l, img_r)
        np.testing.assert_array_equal(np.isnan(base), invalid_mask(D, H, W))
        if not form.get("half"):  # half storage: test_half.py's bound; here the bits below
            np.testing.assert_allclose(base, sgm(cost, img_l, img_r), rtol=0, atol=2e-5 * (3.0 + 32.0))
        bits = np.uint16 if form.get("half") else np.uint32
        for value in FINITE_FILLS:
            got = run_form(ctx, form, with_invalid(cost, value), img_l, img_r)
            np.testing.assert_array_equal(got.view(bits), base.view(bits),
                                          err_msg=f"{D}x{H}x{W}, invalid cells = {value}")


def test_vector_width_rule(ctx):
    """The width follows the rule (8 on CPUs whatever their vector width, 16 on GPUs), a
    tuned width wins, a bad one is refused."""
    from dataclasses import replace
    from mccnn_cl.opencl.device import RULES

    assert RULES["sgm_width"]["cpu"] == 8 and RULES["sgm_width"]["gpu"] == 16
    prof = ctx.profile
    for kind, width, expected in (("cpu", 16, 8), ("cpu", 8, 8), ("gpu", 8, 16), ("gpu", 16, 16)):
        assert replace(prof, kind=kind, vector_width=width, tuned={}).sgm_width() == expected
    assert replace(prof, kind="cpu", vector_width=16, tuned={"sgm_width": 16}).sgm_width() == 16
    assert SGM(ctx).width == prof.sgm_width()
    with pytest.raises(InputError, match="width"):
        SGM(ctx, width=4)


def test_bad_configuration(ctx):
    with pytest.raises(InputError):
        SGM(ctx, cols=24)
    with pytest.raises(InputError):
        SGM(ctx, band=-1)
    with pytest.raises(InputError):
        SGM(ctx, loop_limit=-1)


def test_scratch_bytes_bounds_the_state_buffer(ctx):
    """The path state the stage allocates fits SGM.scratch_bytes (the memory
    planner's figure), for the default and the widest configuration."""
    D, H, W = 7, 3, 130
    cost = np.zeros((D, H, W), np.float32)
    d_img = ctx.to_device(np.zeros((H, W), np.float32))
    for cols in (None, 128):
        st = SGM(ctx, cols=cols, paired=False)
        st(ctx.to_device(cost), d_img, d_img, D, H, W)
        assert st._state.size <= state_bytes(D, W, 128)
        assert st._state.size == state_bytes(D, W, st.cols) == st.scratch_bytes(D, W)
    st = SGM(ctx, paired=True)
    st(ctx.to_device(cost), d_img, d_img, D, H, W)
    assert st._state.size == state_bytes(D, W, paired=True) == st.scratch_bytes(D, W)


def test_constant_images(ctx):
    rng = np.random.default_rng(14)
    D, H, W = 9, 12, 19
    img = np.full((H, W), 0.4, np.float32)
    check(ctx, random_volume(rng, D, H, W), img, img)


def test_single_direction_matches_path_reference(ctx):
    """A single row: the vertical paths have length 1 (C_r = C), so C_SGM =
    (C_lr + C_rl + 2 C) / 4 - checks the horizontal recurrences in isolation."""
    rng = np.random.default_rng(15)
    D, H, W = 6, 1, 30
    cost = random_volume(rng, D, H, W)
    img_l, img_r = blocky_image(rng, H, W), blocky_image(rng, H, W)
    got = run_sgm(ctx, cost, img_l, img_r)
    lr = sgm_direction(cost, img_l, img_r, SGM_DIRECTIONS[0])
    rl = sgm_direction(cost, img_l, img_r, SGM_DIRECTIONS[1])
    np.testing.assert_allclose(got, (lr + rl + 2 * cost) / 4, rtol=0, atol=1e-5 * 33)


@pytest.mark.gpu_check
def test_clear_minimum_is_kept(ctx):
    """A volume with one clear minimum per pixel on a smooth disparity map:
    the winner-take-all disparity after SGM is that minimum."""
    rng = np.random.default_rng(16)
    D, H, W = 12, 19, 29
    true_d = np.clip((np.arange(W)[None, :] // 7 + np.arange(H)[:, None] // 6), 0, D - 1)
    true_d = np.minimum(true_d, np.arange(W)[None, :])  # must be a valid disparity
    cost = (0.5 + 0.5 * rng.random((D, H, W))).astype(np.float32)
    np.put_along_axis(cost, true_d[None], 0.0, axis=0)
    cost[invalid_mask(D, H, W)] = np.nan
    img = blocky_image(rng, H, W)
    got = run_sgm(ctx, cost, img, img)
    wta = np.nanargmin(got, axis=0)
    np.testing.assert_array_equal(wta, true_d)


def test_bad_input(ctx):
    cost = np.zeros((2, 3, 4), np.float32)
    d_cost = ctx.to_device(cost)
    d_img = ctx.to_device(np.zeros((3, 4), np.float32))
    with pytest.raises(InputError):
        SGM(ctx)(d_cost, d_img, d_img, 2, 3, 4, out=d_cost)
    with pytest.raises(InputError):
        SGM(ctx)(d_cost, d_img, d_img, 2, 3, 4, variant="other")
    with pytest.raises(InputError):
        SGM(ctx)(d_cost, d_img, d_img, 0, 3, 4)


@pytest.mark.full_data
def test_chain_arms_cbca_sgm_cbca_on_real_images(ctx, shared_data):
    """The paper's order, all on the device: arms, C_CBCA^4, C_SGM, CBCA again
    (now on costs of the SGM's larger range), against the references."""
    from mccnn_cl.reference.aggregation import cbca, cross_arms
    from mccnn_cl.stages.cbca import CBCA
    from mccnn_cl.stages.cross import CrossArms, arms_from_device, max_arm

    H, W, D = 21, 43, 12
    imgs = []
    for rel in ("middlebury/Cones/im0.png", "middlebury/Cones/im1.png"):
        img = cv2.imread(str(shared_data / rel), cv2.IMREAD_GRAYSCALE)
        imgs.append(img[300:300 + H, 250:250 + W].astype(np.float32) / 255.0)
    cost = ad_volume(imgs[0], imgs[1], D)
    arms_l, arms_r = cross_arms(imgs[0]), cross_arms(imgs[1])
    want = cbca(sgm(cbca(cost, arms_l, arms_r), imgs[0], imgs[1]), arms_l, arms_r)

    def poisoned(nbytes, value=POISON, dtype=np.float32):  # every stage writes into a poisoned buffer
        buf = ctx.empty(nbytes)
        ctx.fill(buf, value, nbytes, dtype)
        return buf

    d_l, d_r = ctx.to_device(imgs[0]), ctx.to_device(imgs[1])
    # arms are bytes 0 .. 255; 0xAB = 171 exceeds any arm of a 43-column image
    d_al, d_ar = (CrossArms(ctx)(d, H, W, out=poisoned(4 * H * W, 0xAB, np.uint8)) for d in (d_l, d_r))
    np.testing.assert_array_equal(arms_from_device(ctx, d_al, H, W), arms_l)
    np.testing.assert_array_equal(arms_from_device(ctx, d_ar, H, W), arms_r)
    aggregate, smooth = CBCA(ctx), SGM(ctx)
    d_c = aggregate(ctx.to_device(cost), d_al, d_ar, D, H, W, max_arm=max_arm(4), out=poisoned(cost.nbytes))
    d_s = smooth(d_c, d_l, d_r, D, H, W, out=poisoned(cost.nbytes))
    for name, buf in (("C_CBCA", d_c), ("C_SGM", d_s)):  # every cell written: NaN exactly where invalid
        np.testing.assert_array_equal(np.isnan(ctx.from_device(buf, cost.shape)), invalid_mask(D, H, W), err_msg=name)
    d_out = aggregate(d_s, d_al, d_ar, D, H, W, max_arm=max_arm(4), out=poisoned(cost.nbytes))
    got = ctx.from_device(d_out, cost.shape)
    np.testing.assert_array_equal(np.isnan(got), invalid_mask(D, H, W))
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5 * (1.0 + 32.0))
    assert np.nanstd(got) > 0.1


def test_release_buffers_frees_the_path_state(ctx):
    """SGM.release_buffers drops the path-state scratch it keeps between calls
    (the matcher's release_buffers calls it); the next call makes it again and
    gives the same bits."""
    rng = np.random.default_rng(11)
    D, H, W = 12, 9, 40
    cost = random_volume(rng, D, H, W, scale=3.0)
    img_l, img_r = blocky_image(rng, H, W, 3, 0.08), blocky_image(rng, H, W, 3, 0.08)
    for paired in (True, False):
        stage = SGM(ctx, paired=paired)
        d_cost, d_l, d_r = ctx.to_device(cost), ctx.to_device(img_l), ctx.to_device(img_r)
        outs = []
        for _ in range(2):
            d_out = ctx.empty(cost.nbytes)
            ctx.fill(d_out, POISON, cost.nbytes)
            stage(d_cost, d_l, d_r, D, H, W, out=d_out)
            outs.append(ctx.from_device(d_out, cost.shape))
            assert stage._state is not None
            held = ctx.memory.live
            stage.release_buffers()
            assert stage._state is None and stage._rstate is None
            assert ctx.memory.live < held
        np.testing.assert_array_equal(outs[0], outs[1])
