"""The conv stack's Winograd F(2x2, 3x3) layers (kernels/network_conv_wino.cl,
mccnn_cl.costs.features): the kernel against a float64 convolution, its row
anchor, the stack's choice of layers, and the path against the direct GEMM.

Tolerance: every output within 1e-5 of the largest output.  A float32 output
sums 9 x CIN terms (the transforms add 3 more roundings per term); the
measured error is ~5e-7 of the largest output (the direct kernel's ~1.3e-6),
so 1e-5 leaves a margin of ~10 and still fails any wrong tap, channel or
transform entry (each moves outputs by ~1e-2 of the largest)."""

from __future__ import annotations

import numpy as np
import pytest

from mccnn_cl.reference.network import conv_layer as reference
from mccnn_cl.costs.features import (CONV_WINO_CL, ConvStack, launch_winograd, normalise, winograd_local_bytes,
                                     winograd_weights)

TOL = 1e-5


def fitting_block(ctx, cin, npad, rn, rt=4, xa=4):
    """(RT, XA) with RT reduced until a work-group's local memory fits the device (~32 KiB at
    64 maps and RT 4: CPU runtimes have 256 KiB to 1 MiB, Oclgrind 32 KiB, GPUs 48-64 KiB)."""
    while rt > 1 and winograd_local_bytes(cin, npad, rn, rt) > ctx.local_mem:
        rt -= 1
    assert winograd_local_bytes(cin, npad, rn, rt) <= ctx.local_mem, "the test's maps need less local memory"
    return rt, xa


def run_layer(ctx, x, W, b, relu, rt, xa, rn, row0=0):
    """network_conv_wino on a host map; the output buffer poisoned with NaN before the launch."""
    h, w, cin = x.shape
    cout = W.shape[0]
    kern = ctx.kernel(CONV_WINO_CL, "network_conv_wino", CIN=cin, CS=cin, NP=cout, RELU=int(relu), RN=rn, RT=rt,
                      XA=xa)
    n = (h - 2) * (w - 2) * cout
    d_out = ctx.empty(4 * n)
    ctx.fill(d_out, np.float32(np.nan), 4 * n)
    launch_winograd(ctx, kern, rt, rn, ctx.to_device(np.ascontiguousarray(x, np.float32)), w,
                    ctx.to_device(winograd_weights(W, cout)), ctx.to_device(np.asarray(b, np.float32)), d_out,
                    w - 2, h - 2, cout, row0)
    return ctx.from_device(d_out, ((h - 2) * (w - 2), cout))


@pytest.mark.parametrize("cin,cout", [(16, 16), (16, 48), (48, 16)])
@pytest.mark.parametrize("rt,xa,rn,relu", [(4, 4, 16, True), (4, 1, 16, False), (6, 1, 16, True), (2, 8, 8, True),
                                         (3, 2, 8, False)])
def test_winograd_layer_matches_a_float64_convolution(ctx, rt, xa, rn, relu, cin, cout):
    """Fresh random maps of odd and even sizes (partial last tiles in both directions; RT not
    dividing a tile row), either row anchor: every output written and within TOL.  The channel
    counts give a work-group (cout / RN members, which share the input transform RN channels
    each in turn) more members than channel groups to transform, fewer, and as many."""
    rng = np.random.default_rng(rt * 100 + xa * 10 + rn + cin + 7 * cout)
    for h, w in ((13, 21), (12, 20), (3, 3), (4, 37)):
        x = rng.standard_normal((h, w, cin)).astype(np.float32)
        W = (rng.standard_normal((cout, cin, 3, 3)) / 12).astype(np.float32)
        b = rng.standard_normal(cout).astype(np.float32)
        ref = reference(x, W, b, relu)
        for p in (0, 1):
            got = run_layer(ctx, x, W, b, relu, rt, xa, rn, p)
            assert not np.isnan(got).any(), (h, w, p)
            assert np.abs(got - ref).max() <= TOL * np.abs(ref).max(), (h, w, p)


@pytest.mark.parametrize("rt,xa,rn", [(4, 4, 16), (3, 2, 8)])
def test_rows_cut_at_an_odd_row_are_bit_identical(ctx, rt, xa, rn):
    """A map cut from a larger one at row r (a band, a row tile), run with row0 = r, gives the
    larger map's rows bit for bit: its tiles are the larger map's.  Anchored at row 0 instead,
    an odd cut differs (the check that the property is not vacuous)."""
    rng = np.random.default_rng(7)
    x = rng.standard_normal((23, 19, 16)).astype(np.float32)
    W = (rng.standard_normal((16, 16, 3, 3)) / 12).astype(np.float32)
    b = rng.standard_normal(16).astype(np.float32)
    whole = run_layer(ctx, x, W, b, True, rt, xa, rn).reshape(21, 17, 16)
    for r0, r1 in ((1, 23), (3, 12), (2, 9), (5, 8)):
        got = run_layer(ctx, x[r0:r1], W, b, True, rt, xa, rn, r0).reshape(r1 - r0 - 2, 17, 16)
        np.testing.assert_array_equal(got.view(np.uint32), whole[r0:r1 - 2].view(np.uint32), err_msg=f"rows {r0}:{r1}")
    odd = run_layer(ctx, x[1:23], W, b, True, rt, xa, rn, 0).reshape(20, 17, 16)
    assert not np.array_equal(odd.view(np.uint32), whole[1:].view(np.uint32))


def _kitti_crop(shared_data, rows=slice(100, 141), cols=slice(300, 383)):
    from mccnn_cl.imageops import to_gray
    from mccnn_cl.io import read_image

    img = to_gray(read_image(shared_data / "kitti2015" / "training" / "image_2" / "000000_10.png"))
    return np.ascontiguousarray(img[rows, cols], np.float32)


def test_winograd_layer_on_real_features(ctx, shared_data):
    """A real map: general-fst's first layer (float64) over a KITTI 2015 crop, then its second
    layer by the kernel against float64."""
    from mccnn_cl.models import resolve

    crop = normalise(_kitti_crop(shared_data))
    w = resolve("general-fst")
    (W0, b0), (W1, b1) = w.conv[0], w.conv[1]
    x = reference(crop[:, :, None], np.asarray(W0), np.asarray(b0)).reshape(39, 81, -1).astype(np.float32)
    rt, xa = fitting_block(ctx, x.shape[2], W1.shape[0], 16)
    got = run_layer(ctx, x, np.asarray(W1, np.float32), np.asarray(b1, np.float32), True, rt, xa, 16)
    ref = reference(x, np.asarray(W1), np.asarray(b1))
    assert not np.isnan(got).any()
    assert np.abs(got - ref).max() <= TOL * np.abs(ref).max()


def _stack_features(ctx, stack, img, row0=0):
    H, W = img.shape
    d = stack(ctx.to_device(np.ascontiguousarray(img[:, :, None])), H, W, row0)
    h, w = H - stack.patch + 1, W - stack.patch + 1
    out = ctx.from_device(d, (h, w, stack.stride))
    stack.give(d)
    return out


def test_the_stack_runs_3x3_layers_by_winograd_and_matches_the_direct_path(ctx, shared_data):
    """general-fst's stack: the first layer (one input channel) direct, the 64 -> 64 layers by
    Winograd on the block asked for; both paths within TOL of a float64 stack on a real crop,
    and a band starting at an odd row equals the whole crop's rows bit for bit."""
    from mccnn_cl.models import resolve
    from mccnn_cl.reference.network import image_features

    w = resolve("general-fst")
    raw = _kitti_crop(shared_data, slice(60, 131), slice(200, 331))
    crop = normalise(raw)
    block = fitting_block(ctx, 64, 64, 16)
    wino = ConvStack(ctx, w, 16, 4, local_tiles=False, winograd=block)
    direct = ConvStack(ctx, w, 16, 4, local_tiles=False, winograd=False)
    assert [l[0].wino for l in wino.layers] == [None] + [block] * (len(w.conv) - 1)
    assert all(l[0].wino is None for l in direct.layers)
    ref = image_features(w, raw)  # the float64 tower, on the same standardised crop
    scale = np.abs(ref).max()
    a, b = _stack_features(ctx, wino, crop), _stack_features(ctx, direct, crop)
    for got in (a, b):
        assert np.abs(got[:, :, :ref.shape[2]] - ref).max() <= TOL * scale
    assert not np.array_equal(a, b)  # the paths are different code (sums ordered differently)
    r0 = 13
    band = _stack_features(ctx, wino, crop[r0:r0 + 30], row0=r0)
    np.testing.assert_array_equal(band.view(np.uint32), a[r0:r0 + 30 - wino.patch + 1].view(np.uint32))


def test_layers_that_cannot_run_by_winograd_stay_direct(ctx, monkeypatch):
    """A layer stays on the direct GEMM where its work-group's local memory does not fit the
    device, and every layer where the stack is built with winograd=False or on the local-tiles
    path; the profile's rule gives the default block."""
    from mccnn_cl.models import resolve

    w = resolve("general-fst")
    cin, npad = w.conv[1][0].shape[1], 64
    need = winograd_local_bytes(cin, npad, 16, 4)
    # ~32 KiB: V's tiles padded by 16 floats, shared by the group, and each work-item's products
    assert need == 4 * (16 * 64 + 16 + 4 * 16 * 16) * 4
    monkeypatch.setattr(type(ctx), "local_mem", property(lambda self: need - 4))
    assert all(l[0].wino is None for l in ConvStack(ctx, w, 16, 4, local_tiles=False, winograd=(4, 4)).layers)
    monkeypatch.undo()
    assert ConvStack(ctx, w, 16, 4, winograd=(4, 4), local_tiles=True).winograd is None
    rule = ConvStack(ctx, w, 16, 4)
    assert rule.winograd == (ctx.profile.winograd() if rule.path == "register" else None)


def test_the_rule_and_its_block_per_vector_width(ctx, monkeypatch):
    """CPU devices: (4, 4) with 16-float vectors, (4, 1) with 8 (BENCHMARKS.md); a tuned value
    stands; None (GPUs) is the direct GEMM."""
    from dataclasses import replace

    prof = replace(ctx.profile, tuned={})
    if prof.kind != "cpu":
        pytest.skip(f"the rule's XA by vector width is for the cpu column; this device is {prof.kind}")
    monkeypatch.setattr(type(prof), "wide_vectors", property(lambda self: True))
    assert prof.winograd() == (4, 4)
    monkeypatch.setattr(type(prof), "wide_vectors", property(lambda self: False))
    assert prof.winograd() == (4, 1)
    assert replace(prof, tuned={"network_winograd": [4, 2]}).winograd() == (4, 2)
    assert replace(prof, tuned={"network_winograd": None}).winograd() is None


def test_winograd_channels_per_work_item_give_the_same_bits(ctx):
    """RN 16, 8 and 4 channels per work-item: each output sums its terms in one order whatever
    RN, so the fst volume is the same bit for bit (and the register block's XA too)."""
    from helpers import random_pair, run_poisoned

    from mccnn_cl.costs.fst import FstCost
    from mccnn_cl.weights import Weights

    w = Weights.random([[32, 3]] * 3, architecture="mccnn-fst", seed=5)
    left, right = random_pair(np.random.default_rng(5), 14, 45)
    vols = []
    for rn, block in ((16, (4, 4)), (8, (4, 1)), (4, (2, 2))):
        block = fitting_block(ctx, 32, 32, rn, *block)
        cost = FstCost(ctx, w, tiles={"CONV_RN": rn}, local_tiles=False, winograd=block)
        assert [l[0].wino for l in cost.stack.layers] == [None, block, block]
        vols.append(run_poisoned(ctx, cost, left, right, 9))
    for v in vols[1:]:
        np.testing.assert_array_equal(v.view(np.uint32), vols[0].view(np.uint32))


def test_a_row_tile_at_an_odd_row_gives_the_whole_volume_rows(ctx, shared_data):
    """The fst cost of a row tile cut at an odd row (as mccnn_cl.distributed's split tiles and the
    row tiles are), standardised with the whole images' statistics and given its row0, equals the
    whole volume's rows bit for bit, in one band and in bands of 3 rows; without row0 its
    Winograd tiles are shifted by a row and the values differ (the check is not vacuous)."""
    from mccnn_cl.costs.fst import FstCost
    from mccnn_cl.imageops import image_stats
    from mccnn_cl.weights import Weights

    w = Weights.random([[16, 3]] * 3, architecture="mccnn-fst", seed=11)  # patch 7
    L = _kitti_crop(shared_data, slice(120, 160), slice(400, 470))
    R = _kitti_crop(shared_data, slice(120, 160), slice(403, 473))
    stats = (image_stats(L), image_stats(R))
    cost = FstCost(ctx, w, tiles={"CONV_RN": 16}, local_tiles=False, winograd=fitting_block(ctx, 16, 16, 16))
    assert all(l[0].wino is not None for l in cost.stack.layers[1:])
    D, P = 8, cost.patch
    whole = cost.to_host(L, R, D, stats=stats)
    r0, r1 = 7, 22
    cut = (L[r0:r1 + P - 1], R[r0:r1 + P - 1])
    for rows in (None, 3):
        tile = cost.to_host(*cut, D, stats=stats, rows=rows, row0=r0)
        np.testing.assert_array_equal(tile.view(np.uint32), whole[:, r0:r1].view(np.uint32), err_msg=f"rows {rows}")
    shifted = cost.to_host(*cut, D, stats=stats)
    assert not np.array_equal(shifted.view(np.uint32), whole[:, r0:r1].view(np.uint32))
