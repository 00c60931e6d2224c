"""Memory on GPUs (issue 16, item 4): the memory planner's row tiles with the
GPU-shaped stages, on a simulated small device.

PoCL is given the profile of a GPU (the ``gpu`` column of mccnn_cl.opencl.device.RULES:
work-group CBCA, SGMWorkGroup, the networks' local-memory tiles and fst's
work-group volume) and a memory limit that cannot hold the whole image's
volumes.  The plan counts the GPU-shaped stages' own scratch
(``scratch_bytes``; it differs from the CPU paths', so the two plans cut
different tiles), the run stays within the plan and the limit (the context's
allocation counter), and, since every GPU-shaped stage sums in the CPU paths'
order (tests/test_cbca_gpu.py, tests/test_network_gpu.py), the tiled
disparity map equals the CPU paths' run on the same tiles bit for bit.
"""

from dataclasses import replace

import numpy as np
import pytest

from helpers import fake_device, kitti_crop
from mccnn_cl.opencl.device import DeviceProfile
from mccnn_cl.errors import InputError
from mccnn_cl.pipeline import MAP_BUFFERS, StereoMatcher
from mccnn_cl.stages.sgm import SGM
from mccnn_cl.stages.sgm_wg import SGMWorkGroup


def _maps_bytes(m, shape):
    """The plan's per-image buffers (pipeline.memory_plan's ``maps``)."""
    Hi, Wi = shape
    W = Wi - 2 * m.margin
    return (MAP_BUFFERS * Hi * Wi * 4 + m.cbca.scratch_bytes(m.max_disparity, W, m.params)
            + m.sgm.scratch_bytes(m.max_disparity, W, m.params))


def _gpu(ctx, monkeypatch):
    import pyopencl as cl

    monkeypatch.setattr(ctx, "profile", DeviceProfile.of(fake_device(
        "Some GPU", cl.device_type.GPU, 64, 1, global_mem=1 << 34, max_alloc=1 << 32, max_work_group=1024), cl))


@pytest.mark.parametrize("cost,weights,D,W", [("census", None, 24, 241), ("cnn", "kitti-fst", 256, 400)])
@pytest.mark.slow
def test_tiled_run_on_a_small_gpu(ctx, shared_data, monkeypatch, cost, weights, D, W):
    left, right = kitti_crop(shared_data, 100, 300, 190, W)
    # the direct conv GEMM (the GPU-shaped GEMM's summation order), not the cpu column's Winograd layers
    monkeypatch.setattr(ctx, "profile", replace(ctx.profile, tuned={**ctx.profile.tuned, "network_winograd": None}))
    cpu = StereoMatcher(weights, cost=cost, max_disparity=D, device=ctx, tile_overlap=16)
    assert cpu.cost.local or cpu.cost.stack.winograd is None
    cpu.sgm = SGM(ctx, paired=False)  # SGMWorkGroup's summation order
    whole = cpu.memory_plan(left.shape)
    assert not whole.tiled

    _gpu(ctx, monkeypatch)
    m = StereoMatcher(weights, cost=cost, max_disparity=D, device=ctx, tile_overlap=16)
    assert isinstance(m.sgm, SGMWorkGroup) and m.cbca.path(2) == "workgroup"
    H, Wc = left.shape[0] - 2 * m.margin, left.shape[1] - 2 * m.margin
    vols = 2 * D * Wc * 4 * H  # the two volumes alive at once
    if cost == "cnn":  # the network's phase (its feature maps) must fit; the volumes must not (D 256: two
        # volumes outweigh the feature maps, so tiles can hold less than the whole image)
        assert m.cost.stack.path == "local" and m.cost.volume_path == "workgroup"
        m.memory_limit = _maps_bytes(m, left.shape) + m.cost.scratch_bytes(H, Wc) + vols // 20
    else:
        m.memory_limit = _maps_bytes(m, left.shape) + vols // 3
    limit = m.memory_limit
    plan = m.memory_plan(left.shape)
    assert plan.tiled and len(plan.tiles) >= 2 and plan.peak_bytes <= limit
    got = m.compute(left, right, timings=True)
    # the GPU-shaped stages' scratch is in the plan: the run's allocations stay within it
    assert got.plan.tiles == plan.tiles and got.peak_device_bytes <= got.plan.peak_bytes <= limit

    # the same tiles through the CPU paths (their scratch differs, so their own plan would
    # cut other tiles): equal bit for bit
    monkeypatch.undo()
    cpu.memory_plan = lambda shape: plan
    want = cpu.compute(left, right, timings=True)
    assert want.plan.tiles == plan.tiles
    np.testing.assert_array_equal(got.disparity.view(np.uint8), want.disparity.view(np.uint8))
    assert np.isfinite(got.disparity).mean() > 0.9 and np.nanstd(got.disparity) > 1.0


def test_network_phase_that_cannot_fit_is_an_error(ctx, shared_data, monkeypatch):
    """Row tiles would fit, but not the network's feature maps beside one band of
    its volume, even of one row: a clear InputError, never a plan above the
    limit.  Where thinner bands fit, the plan takes them (memory_limit sizes
    the bands) and stays within the limit."""
    left, right = kitti_crop(shared_data, 100, 300, 190, 241)
    _gpu(ctx, monkeypatch)
    m = StereoMatcher("kitti-fst", max_disparity=24, device=ctx, tile_overlap=16)
    H, W = left.shape[0] - 2 * m.margin, left.shape[1] - 2 * m.margin
    maps = _maps_bytes(m, left.shape) + m.fixed_bytes
    m.memory_limit = maps + m.cost.scratch_bytes(H, W) // 2  # the cost's own bands do not fit: thinner ones do
    plan = m.memory_plan(left.shape)
    assert plan.band_rows < m.cost.band_rows(H, W) and plan.peak_bytes + m.fixed_bytes <= m.memory_limit
    m.tile_overlap = 4  # tiles of 16 + 2 x 4 rows fit, a one-row band (1 byte short) does not
    m.memory_limit = maps + m.cost.scratch_bytes(H, W, rows=1) + 24 * W * 4 - 1
    assert 2 * 24 * W * 4 * (16 + 2 * 4) < m.memory_limit - maps
    with pytest.raises(InputError, match="feature maps"):
        m.memory_plan(left.shape)
    with pytest.raises(InputError, match="feature maps"):
        m.compute(left, right)
