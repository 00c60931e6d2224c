"""Enlarge, median and bilateral kernels against their numpy twins.

Enlarge and median move values without arithmetic: compared exactly.  The
bilateral filter is a weighted mean of at most (2r+1)^2 = 1225 disparities
accumulated in float32 (kernel: separable Gaussian taps in float32; reference:
the 2-D Gaussian in float64), so it is compared with rtol 1e-5 + atol 1e-4 px,
far below the 1/4 px resolution that matters for disparities; its indicator
function is evaluated identically (float32 |G(p) - G(q)| < tau) in both.
"""

import cv2
import numpy as np
import pytest

from mccnn_cl.reference import disparity as ref
from mccnn_cl.stages.refine import BilateralFilter, Enlarge, MedianFilter, bilateral_radius, median_network

from conftest import POISON

TAU_BF = np.float32(5 / 255)  # the paper's tau_BF = 5 on the 0..255 scale, for [0, 1] images
SIGMA = 5.656


def poisoned(ctx, nbytes):
    buf = ctx.empty(nbytes, "poisoned output")
    ctx.fill(buf, POISON, nbytes)
    return buf


def run_enlarge(ctx, D, margin, shape):
    H, W = D.shape
    Ho, Wo = shape
    out = Enlarge(ctx)(ctx.to_device(D), H, W, Ho, Wo, margin, out=poisoned(ctx, Ho * Wo * 4))
    return ctx.from_device(out, shape)


def run_median(ctx, D, size=5, vector=None):
    H, W = D.shape
    out = MedianFilter(ctx, size, vector)(ctx.to_device(D), H, W, out=poisoned(ctx, H * W * 4))
    return ctx.from_device(out, (H, W))


def _wire(w: int, n: int) -> np.ndarray:
    """Bit w of every n-bit input 0 .. 2^n - 1, packed: bit k of the result is (k >> w) & 1."""
    if w >= 6:  # runs of whole 64-bit words
        run = 1 << (w - 6)
        return np.tile(np.repeat(np.array([0, ~np.uint64(0)], np.uint64), run), (1 << n) // (128 * run))
    word = np.uint64(sum(1 << k for k in range(64) if (k >> w) & 1))
    return np.full((1 << n) // 64, word, np.uint64)


@pytest.mark.parametrize("count", [9, 25])
def test_median_network_selects_the_middle_of_every_01_input(count):
    """0-1 principle: a comparator network puts the k-th smallest value at
    output k for every input iff it does so for every input of 0s and 1s.
    All 2^count 0/1 inputs at once, one bit per input: output count // 2 must
    be 1 exactly when the input has more than count // 2 ones."""
    v = [_wire(w, count) for w in range(count)]
    for i, j in median_network(count):
        v[i], v[j] = v[i] & v[j], v[i] | v[j]
    idx = np.arange(1 << count, dtype=np.uint32)
    ones = np.zeros(idx.size, np.uint8)
    table = np.array([bin(b).count("1") for b in range(256)], np.uint8)
    for b in idx.view(np.uint8).reshape(-1, 4).T:
        ones += table[b]
    want = np.packbits(ones > count // 2, bitorder="little").view(np.uint64)
    np.testing.assert_array_equal(v[count // 2], want)
    # and it is not a trivially short network
    assert len(median_network(count)) > count


def run_bilateral(ctx, D, guide, sigma, tau, radius=None):
    H, W = D.shape
    d_disp = ctx.to_device(D)
    d_guide = d_disp if guide is D else ctx.to_device(guide)
    out = BilateralFilter(ctx)(d_disp, d_guide, H, W, sigma, tau, radius, out=poisoned(ctx, H * W * 4))
    return ctx.from_device(out, (H, W))


def test_bilateral_release_buffers_frees_the_tap_tables(ctx):
    """BilateralFilter.release_buffers frees the Gaussian tap tables it keeps between
    calls (one per sigma and radius: the device bytes go at once, not when the
    garbage collector finds them), and the next call makes them again with the
    same bits."""
    import gc

    rng = np.random.default_rng(5)
    H, W = 23, 31
    D = rng.uniform(0, 20, (H, W)).astype(np.float32)
    guide = rng.random((H, W), dtype=np.float32)
    d_disp, d_guide = ctx.to_device(D), ctx.to_device(guide)
    stage = BilateralFilter(ctx)
    outs = []
    for _ in range(2):
        for sigma, radius in ((SIGMA, None), (2.0, 3)):
            out = stage(d_disp, d_guide, H, W, sigma, TAU_BF, radius, out=poisoned(ctx, H * W * 4))
            outs.append(ctx.from_device(out, (H, W)))
        assert len(stage._taps) == 2
        taps = sum(int(b.size) for b in stage._taps.values())
        gc.collect()
        held = ctx.memory.live
        stage.release_buffers()
        assert stage._taps == {} and ctx.memory.live == held - taps
    np.testing.assert_array_equal(outs[0], outs[2])
    np.testing.assert_array_equal(outs[1], outs[3])


@pytest.fixture(scope="module")
def kitti(shared_data):
    """A 45 x 71 crop of KITTI 2015 000000 (left, [0, 1]) and its ground truth
    disparities (holes filled with the median) as a realistic disparity map."""
    d = shared_data / "kitti2015" / "training"
    img = cv2.imread(str(d / "image_2" / "000000_10.png"), cv2.IMREAD_GRAYSCALE)[200:245, 500:571]
    gt = cv2.imread(str(d / "disp_occ_0" / "000000_10.png"), cv2.IMREAD_UNCHANGED)[200:245, 500:571]
    gt = gt.astype(np.float32) / 256
    gt[gt == 0] = np.median(gt[gt > 0])
    img = img.astype(np.float32) / 255
    assert img.std() > 0.03 and gt.std() > 0.5
    return img, gt


@pytest.mark.parametrize("H,W,margin,shape", [(29, 45, 4, (37, 53)), (1, 5, 4, (9, 13)), (3, 1, 2, (7, 5))])
def test_enlarge(ctx, H, W, margin, shape):
    D = np.random.default_rng(H).random((H, W), dtype=np.float32) * 30
    out = run_enlarge(ctx, D, margin, shape)
    np.testing.assert_array_equal(out, ref.enlarge(D, margin, shape))
    np.testing.assert_array_equal(out[margin:margin + H, margin:margin + W], D)


@pytest.mark.parametrize("vector", [True, False])
@pytest.mark.parametrize("H,W,size", [(37, 53, 5), (1, 17, 5), (4, 3, 5), (21, 19, 3), (9, 9, 1), (6, 70, 5)])
@pytest.mark.slow
def test_median_random(ctx, H, W, size, vector):
    """Both kernels; 53 and 70 columns give the vector kernel interior 16-px
    chunks beside its clamped border ones.  Values rounded to 0.1, so ties occur."""
    D = (np.random.default_rng(W).random((H, W), dtype=np.float32) * 50).round(1)
    out = run_median(ctx, D, size, vector)
    np.testing.assert_array_equal(out, ref.median_filter(D, size))
    if size == 5 and H >= 5 and W >= 5:  # same as OpenCV's replicate-border median
        np.testing.assert_array_equal(out, cv2.medianBlur(D, 5))


def test_median_large_window_uses_sorting_kernel(ctx):
    D = np.random.default_rng(7).random((12, 40), dtype=np.float32)
    m = MedianFilter(ctx, 7)
    assert not m.vector
    np.testing.assert_array_equal(run_median(ctx, D, 7), ref.median_filter(D, 7))
    with pytest.raises(ValueError):
        MedianFilter(ctx, 7, vector=True)


@pytest.mark.parametrize("vector", [True, False])
def test_median_real_and_constant(ctx, kitti, vector):
    _, gt = kitti
    np.testing.assert_array_equal(run_median(ctx, gt, 5, vector), ref.median_filter(gt))
    c = np.full((6, 11), 7.25, np.float32)
    np.testing.assert_array_equal(run_median(ctx, c, 5, vector), c)


def test_median_even_size_rejected(ctx):
    with pytest.raises(ValueError):
        MedianFilter(ctx, 4)


@pytest.mark.parametrize("H,W", [(37, 53), (11, 150)])
def test_bilateral_random(ctx, H, W):
    """Narrow maps take the kernel's border path for every 16-px chunk at
    radius 17; 150 columns also have interior chunks (plain vector loads)."""
    rng = np.random.default_rng(W)
    D = rng.random((H, W), dtype=np.float32) * 40
    guide = (rng.integers(0, 256, (H, W)) / 255).astype(np.float32)
    for sigma, tau, radius in ((SIGMA, TAU_BF, None), (2.0, np.float32(0.3), 3)):
        r = bilateral_radius(sigma) if radius is None else radius
        out = run_bilateral(ctx, D, guide, sigma, tau, radius)
        np.testing.assert_allclose(out, ref.bilateral(D, guide, sigma, r, tau), rtol=1e-5, atol=1e-4)


def test_bilateral_real_paper_and_code_variant(ctx, kitti):
    img, gt = kitti
    r = bilateral_radius(SIGMA)
    assert r == 17
    out = run_bilateral(ctx, gt, img, SIGMA, TAU_BF)
    np.testing.assert_allclose(out, ref.bilateral(gt, img, SIGMA, r, TAU_BF), rtol=1e-5, atol=1e-4)
    assert np.abs(out - gt).max() > 0.1  # it does smooth
    # released code's variant: guided by the disparities themselves, tau in pixels
    out2 = run_bilateral(ctx, gt, gt, SIGMA, np.float32(2.0))
    np.testing.assert_allclose(out2, ref.bilateral(gt, gt, SIGMA, r, 2.0), rtol=1e-5, atol=1e-4)


def test_bilateral_edge_cases(ctx):
    # constant guide: plain Gaussian blur; constant map stays constant
    c = np.full((1, 23), 3.5, np.float32)
    np.testing.assert_allclose(run_bilateral(ctx, c, np.zeros_like(c), SIGMA, TAU_BF), c, atol=1e-5)
    # tau = 0: no neighbour passes (strict <), W(p) = 0 -> D(p) kept
    D = np.random.default_rng(3).random((5, 7), dtype=np.float32)
    np.testing.assert_array_equal(run_bilateral(ctx, D, D, SIGMA, np.float32(0.0)), D)
    # a guide edge stops the averaging: two flat halves stay apart
    D2 = np.zeros((8, 20), np.float32)
    D2[:, 10:] = 30
    g = (D2 / 255).astype(np.float32)
    out = run_bilateral(ctx, D2, g, SIGMA, TAU_BF)
    np.testing.assert_allclose(out, D2, atol=1e-5)
