"""The networks' GPU-shaped kernels against the CPU-shaped ones and the
numpy reference (mccnn_cl.reference.network):

* the conv stack and the L4 split as a local-memory tiled GEMM
  (kernels/network_conv_wg.cl, ``local_tiles=``) against network_conv.cl;
* fst's cosine volume with a work-group per (column tile, disparity chunk,
  row) (kernels/fst_wg.cl, ``FstCost(workgroup=)``) against
  fst_volume_pairs;
* the paper/acrt head layer by layer (kernels/network_head_wg.cl, each
  hidden layer the conv GEMM as a 1 x 1 convolution; ``head_gemm=True``)
  against the fused head (network_head.cl).

Against the CPU kernels bit for bit: both form each output from the same
float operations in the same order (conv and hidden units: bias, one fma
per term in k order, ReLU; fst: 0, one fma per map in k order, negated;
the last layer: one shared function, network_out.h); only where the
operands come from differs (local-memory tiles, activations in global
memory), so any difference is a defect.  (The head's last layer sums RN
lanes: the comparisons use the same RN on both sides.)  Against the float64 reference: the tolerances of test_fst.py
(2e-5 on cosines in [-1, 1]) and test_network.py / test_acrt.py (1e-4 on
probabilities).  NaN exactly where x - d < 0; every output poisoned
first, so a cell left unwritten fails.

Tiles: the profile's (shrunk to fit), forced ones with partial tiles in
every dimension, sizes that are not powers of two, work-groups of one, and
one as large as the kernel allows on this device (4096 work-items on
PoCL), on odd image sizes, D below and above the width, a real KITTI crop
with the shipped kitti-fst network.  On CPU implementations (and under
Oclgrind's race and bounds checks, tests/test_oclgrind.py cases
``network_wg`` and ``fst_wg``) these prove the local-memory and barrier
logic that a GPU runs.
"""


import numpy as np
import pytest

import helpers

from conftest import POISON
from helpers import kitti_crop, random_pair, run_poisoned
from mccnn_cl.opencl.device import RULES, DeviceProfile
from mccnn_cl.errors import InputError
from mccnn_cl.reference import network as ref
from mccnn_cl.costs.features import ConvStack, normalise
from mccnn_cl.costs.fst import FstCost
from mccnn_cl.costs import network as network_stage
from mccnn_cl.costs.network import AcrtCost, PaperCost
from mccnn_cl.weights import Weights, resolve

FST_TOL = 2e-5   # tests/test_fst.py
NET_TOL = 1e-4   # tests/test_network.py, tests/test_acrt.py

#: Forced conv GEMM tiles: partial tiles in M, N and K, no powers of two, groups of one.
CONV_TILES = (dict(TM=8, TN=8, TK=4, RM=2, RN=2), dict(TM=5, TN=3, TK=3, RM=1, RN=1),
              dict(TM=12, TN=16, TK=7, RM=3, RN=4), dict(TM=1, TN=1, TK=1, RM=1, RN=1), "max")
#: Forced fst volume tiles, the same kinds.
VOL_TILES = (dict(TX=4, TD=4, TK=3, RX=1, RD=1), dict(TX=6, TD=5, TK=2, RX=2, RD=1),
             dict(TX=16, TD=8, TK=8, RX=4, RD=2), dict(TX=1, TD=1, TK=1, RX=1, RD=1), "max")


def bits(a):
    return np.ascontiguousarray(a).view(np.uint8)


def largest(ctx, kind):
    """A forced tile whose work-group is the kernel's largest on this device
    (probed with the default tile's kernel; 1 x 1 register blocks)."""
    w = Weights.random([[8, 3]], architecture="mccnn-fst", seed=1)
    if kind == "conv":
        kern = ConvStack(ctx, w, 4, 1, local_tiles=True).layers[0][0].kern
    else:
        kern = FstCost(ctx, w, local_tiles=False, workgroup=True)._vol
    n = min(ctx.work_group_size(kern), int(ctx.device.max_work_item_sizes[1]) * 16)
    wa = min(16, n)
    wb = n // wa
    if kind == "conv":
        return dict(TM=wb, TN=wa, TK=8, RM=1, RN=1)
    return dict(TX=wa, TD=wb, TK=4, RX=1, RD=1)


def tiles(ctx, choices, kind):
    return [largest(ctx, kind) if t == "max" else t for t in choices]


# -- the conv stack -----------------------------------------------------------------
def layer_outputs(ctx, stack, img):
    """Each layer's map, launched into a poisoned buffer, from the previous one
    of the same stack; returns the host maps and checks none is left poisoned."""
    H, W = img.shape[:2]
    d_in, h, w = ctx.to_device(np.ascontiguousarray(img, np.float32)), H, W
    outs = []
    for conv, d_w, d_b, ks, npad in stack.layers:
        ho, wo = h - ks + 1, w - ks + 1
        d_out = ctx.empty(ho * wo * npad * 4, "test map")
        ctx.fill(d_out, POISON, ho * wo * npad * 4)
        stack.launch(conv, d_in, w, d_w, d_b, d_out, wo, ho * wo, npad)
        got = ctx.from_device(d_out, (ho, wo, npad))
        assert not np.any(got == POISON), "outputs left unwritten"
        outs.append(got)
        d_in, h, w = d_out, ho, wo
    return outs


@pytest.mark.parametrize("conv,H,W,relu_last", [
    ([[16, 3], [13, 5], [7, 3]], 23, 37, False),   # odd maps (padded channels), kernel 5, fst-like
    ([[6, 5], [10, 5], [10, 1]], 21, 30, True),    # the paper's shapes, small: a 1x1 layer
    ([[64, 3]] * 4, 14, 45, False),                # KITTI fst's layers: K = 576, several slices
], ids=["odd-maps", "paper-like", "kitti-fst-layers"])
@pytest.mark.slow
@pytest.mark.gpu_check
def test_conv_stack_bit_identical(ctx, conv, H, W, relu_last):
    """Every layer of the local-memory GEMM equals network_conv bit for bit
    (default and forced tiles), and the stack's features the reference."""
    arch = "mccnn-fst" if not relu_last else "mccnn-paper"
    w = Weights.random(conv, [8, 2] if relu_last else None, architecture=arch, seed=H * W)
    raw = np.random.default_rng(H).random((H, W)).astype(np.float32)
    img = normalise(raw)[:, :, None]
    base = ConvStack(ctx, w, 4, 3, local_tiles=False, winograd=False)
    assert base.path == "register"
    want = layer_outputs(ctx, base, img)
    assert np.ptp(want[-1]) > 0.1
    feat = ref.image_features(w, raw)  # the float64 tower (standardises the image itself)
    for t in [True] + tiles(ctx, CONV_TILES, "conv"):
        st = ConvStack(ctx, w, 4, 3, local_tiles=t)
        assert st.path == "local"
        got = layer_outputs(ctx, st, img)
        for i, (a, b) in enumerate(zip(got, want)):
            np.testing.assert_array_equal(bits(a), bits(b), err_msg=f"layer {i}, tile {st.layers[i][0].tile}")
        np.testing.assert_allclose(got[-1][:, :, :w.feature_maps], feat, rtol=1e-4, atol=1e-4)
        if isinstance(t, dict):
            assert all(l[0].tile == t for l in st.layers)


@pytest.mark.gpu_check
def test_default_conv_tile_fits_and_is_capped(ctx):
    """The profile's tile: TN capped by the layer's channels and TK by its
    terms, within the kernel's work-group limit and the local memory."""
    w = Weights.random([[5, 3], [64, 3]], architecture="mccnn-fst", seed=3)
    st = ConvStack(ctx, w, 4, 1, local_tiles=True)
    t0, t1 = (l[0].tile for l in st.layers)
    assert (t0["TN"], t0["TK"]) == (8, 9) and (t1["TN"], t1["TK"]) == (64, 16)
    for conv, *_ in st.layers:
        t = conv.tile
        assert (t["TM"] // t["RM"]) * (t["TN"] // t["RN"]) <= ctx.work_group_size(conv.kern)
        assert 4 * t["TK"] * (t["TM"] + t["TN"]) + 8 * t["TM"] <= ctx.local_mem


# -- the fst cosine volume ----------------------------------------------------------
@pytest.mark.parametrize("conv,H,W,D", [
    ([[16, 3]] * 4, 37 + 8, 53 + 8, 16),   # the odd size: 37 x 53 volume, D = 16
    ([[64, 3]] * 4, 12, 80, 70),           # KITTI's layers, D close to W, several disparity chunks
    ([[7, 3], [5, 5]], 9, 23, 20),         # odd maps (NK 5 < TK), D > W (cropped W = 17)
    ([[12, 3]], 5, 8, 1),                  # one layer, D = 1, w < 16
], ids=["37x53-D16", "kitti-layers-D70", "odd-maps-D>W", "one-layer-D1"])
@pytest.mark.slow
@pytest.mark.gpu_check
def test_fst_volume_bit_identical(ctx, conv, H, W, D):
    """fst_volume_wg (with the GEMM conv stack) equals the CPU kernels bit for
    bit for every tile, and the reference within test_fst's tolerance."""
    w = Weights.random(conv, architecture="mccnn-fst", seed=H * W)
    left, right = random_pair(np.random.default_rng(H + W), H, W)
    base_cost = FstCost(ctx, w, local_tiles=False, workgroup=False, winograd=False)
    assert base_cost.volume_path == "pairs" and base_cost.stack.path == "register"
    base = run_poisoned(ctx, base_cost, left, right, D)
    want = ref.fst_cost_volume(w, left, right, D)
    np.testing.assert_array_equal(np.isnan(base), np.isnan(want))
    assert np.nanstd(want) > 0.05
    for t in [True] + tiles(ctx, VOL_TILES, "fst"):
        cost = FstCost(ctx, w, local_tiles=True, workgroup=t)
        assert cost.volume_path == "workgroup" and cost.stack.path == "local"
        got = run_poisoned(ctx, cost, left, right, D)
        np.testing.assert_array_equal(bits(got), bits(base), err_msg=f"tile {cost.volume_tile}")
        v = ~np.isnan(want)
        assert np.abs(got[v] - want[v]).max() <= FST_TOL
    # each GPU-shaped kernel alone, the other CPU-shaped
    for lt, wg in ((True, False), (False, dict(TX=8, TD=3, TK=4, RX=2, RD=1))):
        got = run_poisoned(ctx, FstCost(ctx, w, local_tiles=lt, workgroup=wg, winograd=False), left, right, D)
        np.testing.assert_array_equal(bits(got), bits(base))


@pytest.mark.slow
@pytest.mark.gpu_check
def test_fst_real_crop_shipped_network(ctx, shared_data):
    """The shipped kitti-fst on a held-out KITTI crop: the GPU-shaped path
    equals the CPU path bit for bit and the reference within 2e-5."""
    w = resolve("kitti-fst")
    left, right = kitti_crop(shared_data, 180, 500, 39, 75)
    assert left.std() > 0.02
    D = 28
    base = run_poisoned(ctx, FstCost(ctx, w, local_tiles=False, workgroup=False, winograd=False), left, right, D)
    want = ref.fst_cost_volume(w, left, right, D)
    assert np.nanmin(want) < -0.9 and np.nanmax(want) > 0.0
    for wg in (True, dict(TX=16, TD=7, TK=16, RX=4, RD=7)):
        got = run_poisoned(ctx, FstCost(ctx, w, local_tiles=True, workgroup=wg), left, right, D)
        np.testing.assert_array_equal(bits(got), bits(base))
        v = ~np.isnan(want)
        np.testing.assert_allclose(got[v], want[v], rtol=0, atol=FST_TOL)


@pytest.mark.parametrize("rows", [1, 3])
@pytest.mark.slow
@pytest.mark.gpu_check
def test_fst_bands_half_and_to_host(ctx, monkeypatch, rows):
    """Bands of 1 and 3 rows (the volume's row offset y0), to_host, half
    storage: the GPU-shaped path gives the CPU path's bits in each."""
    from mccnn_cl.costs import fst as fst_stage

    w = Weights.random([[10, 3]] * 3, architecture="mccnn-fst", seed=4)
    left, right = random_pair(np.random.default_rng(9), 20, 45)
    D = 11
    cpu = FstCost(ctx, w, local_tiles=False, workgroup=False, winograd=False)
    gpu = FstCost(ctx, w, local_tiles=dict(TM=16, TN=8, TK=8, RM=2, RN=2),
                  workgroup=dict(TX=8, TD=4, TK=4, RX=2, RD=2))
    whole = run_poisoned(ctx, cpu, left, right, D)
    monkeypatch.setattr(fst_stage, "BAND_BYTES", rows * gpu._row_bytes(39))
    assert gpu.band_rows(14, 39) == rows
    np.testing.assert_array_equal(bits(run_poisoned(ctx, gpu, left, right, D)), bits(whole))
    np.testing.assert_array_equal(bits(gpu.to_host(left, right, D, max_bytes=D * 39 * 4 * 2)), bits(whole))
    half_cpu = run_poisoned(ctx, FstCost(ctx, w, half=True, local_tiles=False, workgroup=False, winograd=False),
                            left, right, D, half=True)
    half_gpu = run_poisoned(ctx, FstCost(ctx, w, half=True, local_tiles=True, workgroup=True), left, right, D,
                            half=True)
    np.testing.assert_array_equal(bits(half_gpu), bits(half_cpu))


# -- the fc networks' conv stack and L4 split ---------------------------------------
@pytest.mark.parametrize("cls,conv,fc,arch", [
    (PaperCost, [[8, 3], [12, 3], [12, 1]], [16, 16, 2], "mccnn-paper"),
    (AcrtCost, [[6, 3], [9, 3]], [10, 10, 1], "mccnn-acrt"),
])
@pytest.mark.slow
@pytest.mark.gpu_check
def test_fc_networks_local_tiles(ctx, cls, conv, fc, arch):
    """The paper and acrt networks with the GEMM conv stack and L4 split:
    bit for bit the CPU-shaped volumes, the reference within 1e-4."""
    w = Weights.random(conv, fc, architecture=arch, seed=11)
    left, right = random_pair(np.random.default_rng(5), 17, 29)
    D = 9
    base = run_poisoned(ctx, cls(ctx, w, local_tiles=False, winograd=False), left, right, D)
    want = ref.cost_volume(w, left, right, D)
    v = ~np.isnan(want)
    assert np.abs(base[v] - want[v]).max() <= NET_TOL and np.nanstd(want) > 1e-3
    for t in (True, dict(TM=6, TN=4, TK=5, RM=2, RN=1)):
        net = cls(ctx, w, local_tiles=t)
        assert net.stack.path == "local"
        np.testing.assert_array_equal(bits(run_poisoned(ctx, net, left, right, D)), bits(base))


# -- the fc networks' head layer by layer -------------------------------------------
HEAD_TILES = (None, dict(TM=4, RM=2, RN=4, CONV_RM=3), dict(TM=3, RM=1, RN=1, CONV_RM=1),
              dict(TM=8, RM=2, RN=8, ROWS_FASTEST=0))


@pytest.mark.parametrize("cls,conv,fc,arch", [
    pytest.param(PaperCost, [[8, 3], [12, 3], [12, 1]], [16, 16, 16, 2], "mccnn-paper",
                 marks=(pytest.mark.slow, pytest.mark.gpu_check)),  # 2 hidden layers
    pytest.param(AcrtCost, [[6, 3], [9, 3]], [10, 10, 1], "mccnn-acrt", marks=pytest.mark.slow),  # 1 hidden layer
    pytest.param(AcrtCost, [[5, 3]], [7, 1], "mccnn-acrt", marks=pytest.mark.slow),  # no hidden layer
], ids=["paper-2-hidden", "acrt-1-hidden", "acrt-0-hidden"])
def test_gemm_head_bit_identical(ctx, monkeypatch, cls, conv, fc, arch):
    """The head layer by layer equals the fused head bit for bit (same
    register tiles, so the same RN), with either conv kernel, in runs of 7
    cells (runs across rows and disparities), in float32 and half; and the
    reference within 1e-4.  Every register tile with two hidden layers; the
    default and one other with fewer (each tile is a program per layer shape,
    ~4 s of builds on a cold PoCL cache)."""
    w = Weights.random(conv, fc, architecture=arch, seed=len(fc) * 7)
    left, right = random_pair(np.random.default_rng(len(conv)), 16, 27)
    D = 10
    want = ref.cost_volume(w, left, right, D)
    assert np.nanstd(want) > 1e-3
    for tiles in HEAD_TILES if len(fc) == 4 else HEAD_TILES[:2]:
        fused = cls(ctx, w, tiles=tiles, local_tiles=False, head_gemm=False, winograd=False)
        assert fused.head_path == "fused"
        base = run_poisoned(ctx, fused, left, right, D)
        v = ~np.isnan(want)
        assert np.abs(base[v] - want[v]).max() <= NET_TOL
        for lt, cells in ((False, 1 << 16), (True, 7), (dict(TM=6, TN=5, TK=4, RM=2, RN=1), 40)):
            monkeypatch.setattr(network_stage, "GEMM_CELLS", cells)
            net = cls(ctx, w, tiles=tiles, local_tiles=lt, head_gemm=True, winograd=False)
            assert net.head_path == "gemm"
            np.testing.assert_array_equal(bits(run_poisoned(ctx, net, left, right, D)), bits(base),
                                          err_msg=f"tiles {tiles}, conv tile {lt}, runs of {cells}")
    half = run_poisoned(ctx, cls(ctx, w, half=True, head_gemm=True, local_tiles=True), left, right, D, half=True)
    np.testing.assert_array_equal(bits(half), bits(run_poisoned(ctx, cls(ctx, w, half=True, head_gemm=False,
                                                                         winograd=False),
                                                                left, right, D, half=True)))


@pytest.mark.slow
@pytest.mark.gpu_check
def test_gemm_head_real_crop_bands_to_host(ctx, shared_data, monkeypatch):
    """The shipped kitti-paper network on a KITTI crop: the head layer by
    layer (with the GEMM conv stack) equals the fused head bit for bit, in
    one band and in bands of 2 rows through to_host; the reference within 1e-4."""
    w = resolve("kitti-paper")
    left, right = kitti_crop(shared_data, 180, 500, 14, 40)
    left, right = left * 255, right * 255
    D = 12
    t = dict(RN=4)  # one RN on both sides
    base = run_poisoned(ctx, PaperCost(ctx, w, tiles=t, local_tiles=False, head_gemm=False, winograd=False),
                        left, right, D)
    want = ref.cost_volume(w, left, right, D)
    v = ~np.isnan(want)
    assert np.abs(base[v] - want[v]).max() <= NET_TOL and np.nanstd(want) > 0.05
    monkeypatch.setattr(network_stage, "GEMM_CELLS", 50)
    gpu = PaperCost(ctx, w, tiles=t, local_tiles=True, head_gemm=True)
    np.testing.assert_array_equal(bits(run_poisoned(ctx, gpu, left, right, D)), bits(base))
    monkeypatch.setattr(network_stage, "BAND_BYTES", 2 * 32 * gpu.hp * 4)
    assert gpu.band_rows(6, 32) == 2
    np.testing.assert_array_equal(bits(gpu.to_host(left, right, D)), bits(base))
    assert gpu.scratch_bytes(6, 32) > PaperCost(ctx, w, tiles=t, head_gemm=False).scratch_bytes(6, 32)


# -- sizes, limits and bad input ----------------------------------------------------
@pytest.mark.slow
@pytest.mark.gpu_check
def test_small_local_memory_shrinks_the_tiles(ctx, monkeypatch):
    """A device with little local memory (simulated: 1200 bytes): the default
    tiles shrink to fit and the results stay exact; a forced tile that does
    not fit is an InputError naming the local memory."""
    w = Weights.random([[12, 3]] * 2, architecture="mccnn-fst", seed=8)
    left, right = random_pair(np.random.default_rng(2), 15, 40)
    base = run_poisoned(ctx, FstCost(ctx, w, local_tiles=False, workgroup=False, winograd=False), left, right, 13)
    monkeypatch.setattr(type(ctx), "local_mem", property(lambda self: 1200))
    cost = FstCost(ctx, w, local_tiles=True, workgroup=True)
    t = cost.volume_tile
    assert 4 * t["TK"] * (2 * t["TX"] + t["TD"] - 1) <= 1200
    for conv, *_ in cost.stack.layers:
        c = conv.tile
        assert 4 * c["TK"] * (c["TM"] + c["TN"]) + 8 * c["TM"] <= 1200
    np.testing.assert_array_equal(bits(run_poisoned(ctx, cost, left, right, 13)), bits(base))
    with pytest.raises(InputError, match="local memory"):
        FstCost(ctx, w, local_tiles=False, workgroup=dict(TX=64, TD=64, TK=16, RX=4, RD=4))
    with pytest.raises(InputError, match="local memory"):
        FstCost(ctx, w, local_tiles=dict(TM=64, TN=16, TK=16, RM=4, RN=4), workgroup=False)


@pytest.mark.gpu_check
def test_bad_tiles(ctx):
    w = Weights.random([[8, 3]], architecture="mccnn-fst", seed=1)
    with pytest.raises(InputError, match="multiple"):
        FstCost(ctx, w, local_tiles=False, workgroup=dict(TX=6, RX=4))
    with pytest.raises(InputError, match="multiple"):
        ConvStack(ctx, w, 4, 1, local_tiles=dict(TN=6, RN=4))
    with pytest.raises(InputError, match=">= 1"):
        ConvStack(ctx, w, 4, 1, local_tiles=dict(TK=0))
    with pytest.raises(InputError, match="unknown"):
        FstCost(ctx, w, local_tiles=False, workgroup=dict(TM=8))
    big = ctx.work_group_size(FstCost(ctx, w, local_tiles=False, workgroup=True)._vol) + 1
    with pytest.raises(InputError, match="work-items"):
        FstCost(ctx, w, local_tiles=False, workgroup=dict(TX=big, TD=1, TK=1, RX=1, RD=1))


# -- the paths a device gets (the profile's rules) ----------------------------------
def fake_device(name, type_, units=8, width=1):
    return helpers.fake_device(name, type_, units, width, global_mem=1 << 34, max_alloc=1 << 32, max_work_group=1024)


@pytest.mark.parametrize("kind,name,type_,gpu_shaped", [
    ("gpu", "NVIDIA H200", "GPU", True), ("gpu", "Oclgrind Simulator", "ALL", True),
    ("cpu", "pthread-skylake-avx512", "CPU", False), ("llvmpipe", "llvmpipe (LLVM 15.0.6)", "CPU", False)])
@pytest.mark.gpu_check
def test_profile_selects_the_paths(ctx, monkeypatch, kind, name, type_, gpu_shaped):
    """The gpu column takes both GPU-shaped kernels, CPU and llvmpipe keep
    theirs; explicit choices beat the rules either way."""
    import pyopencl as cl

    prof = DeviceProfile.of(fake_device(name, getattr(cl.device_type, type_)), cl)
    assert prof.kind == kind
    for path, tile in (("network_local_tiles", "network_gemm_tile"), ("fst_workgroup", "fst_volume_tile")):
        got = prof.local_tile(path, tile)
        assert (got is not None) == gpu_shaped
        if got is not None:
            assert got == (RULES[tile][kind], False)
        assert prof.local_tile(path, tile, False) is None
        assert prof.local_tile(path, tile, True) == (RULES[tile][kind], False)
    monkeypatch.setattr(ctx, "profile", prof)
    w = Weights.random([[8, 3]] * 2, architecture="mccnn-fst", seed=2)
    cost = FstCost(ctx, w)
    assert (cost.volume_path == "workgroup") == gpu_shaped and (cost.stack.path == "local") == gpu_shaped
    assert FstCost(ctx, w, local_tiles=not gpu_shaped, workgroup=not gpu_shaped).volume_path == \
        ("pairs" if gpu_shaped else "workgroup")
    net = PaperCost(ctx, Weights.random([[4, 3]], [8, 2], seed=3))
    assert (net.stack.path == "local") == gpu_shaped and (net.head_path == "gemm") == gpu_shaped
    assert PaperCost(ctx, Weights.random([[4, 3]], [8, 2], seed=3), head_gemm=not gpu_shaped).head_path == \
        ("fused" if gpu_shaped else "gemm")
    assert prof.rule("network_head_gemm") == gpu_shaped


@pytest.mark.slow
@pytest.mark.gpu_check
def test_stereo_matcher_with_the_gpu_profile(ctx, shared_data, monkeypatch):
    """StereoMatcher with the shipped default fst network on this device with the gpu
    column of the rules (a profile built for a GPU): the network takes the
    GEMM conv stack and the work-group volume (and CBCA / SGM their
    work-group paths).  C_CNN equals the CPU path's bit for bit, and so do
    the later volumes and the disparity map when the CPU run uses the CPU
    paths that sum in the same order as the work-group ones (SGM's
    one-direction kernels, tests/test_cbca_gpu.py; the direct conv GEMM,
    not the CPU column's Winograd layers)."""
    from dataclasses import replace

    import pyopencl as cl

    from mccnn_cl.pipeline import StereoMatcher
    from mccnn_cl.stages.sgm import SGM

    left, right = kitti_crop(shared_data, 150, 300, 41, 97)
    D = 24
    # the CPU column for the baseline, also on a GPU (whose own profile is the gpu column)
    cpu_profile = DeviceProfile.of(fake_device("Some CPU", cl.device_type.CPU, 2, 16), cl)
    monkeypatch.setattr(ctx, "profile", replace(cpu_profile, tuned={"network_winograd": None}))
    cpu = StereoMatcher(max_disparity=D, device=ctx)
    assert cpu.cost.volume_path == "pairs" and cpu.cost.stack.path == "register" and cpu.cost.stack.winograd is None
    cpu.sgm = SGM(ctx, paired=False)
    want = cpu.compute(left, right, return_intermediates=True)
    monkeypatch.setattr(ctx, "profile", DeviceProfile.of(fake_device("Some GPU", cl.device_type.GPU, 64), cl))
    m = StereoMatcher(max_disparity=D, device=ctx)
    assert m.cost.volume_path == "workgroup" and m.cost.stack.path == "local" and m.cbca.path(3) == "workgroup"
    got = m.compute(left, right, return_intermediates=True)
    assert set(got.intermediates) == set(want.intermediates)
    c_cnn = got.intermediates["C_CNN"]
    assert np.nanmin(c_cnn) < -0.9
    for name, a in got.intermediates.items():
        b = want.intermediates[name]
        assert a.shape == b.shape and a.dtype == b.dtype, name
        np.testing.assert_array_equal(bits(a), bits(b), err_msg=name)
    np.testing.assert_array_equal(bits(got.disparity), bits(want.disparity))


@pytest.mark.slow
@pytest.mark.gpu_check
def test_paper_network_with_the_gpu_profile(ctx, shared_data, monkeypatch):
    """The shipped kitti-paper network with a GPU profile takes the GEMM conv
    stack and the head layer by layer; its C_CNN equals, bit for bit, the
    CPU-shaped kernels' with the same register tiles (the gpu column's)."""
    import pyopencl as cl

    from mccnn_cl.costs.registry import make_cost

    w = resolve("kitti-paper")
    left, right = kitti_crop(shared_data, 150, 300, 15, 37)
    D = 9
    monkeypatch.setattr(ctx, "profile", DeviceProfile.of(fake_device("Some GPU", cl.device_type.GPU, 64), cl))
    gpu = make_cost(ctx, w)
    assert gpu.head_path == "gemm" and gpu.stack.path == "local"
    cpu = PaperCost(ctx, w, local_tiles=False, head_gemm=False, winograd=False)  # the gpu column's register tiles
    assert cpu.rn == gpu.rn
    np.testing.assert_array_equal(bits(run_poisoned(ctx, gpu, left, right, D)),
                                  bits(run_poisoned(ctx, cpu, left, right, D)))
