"""Volume reuse (mccnn_cl.opencl.context.BufferPool, StereoMatcher's kept volumes).

A matcher keeps its cost volumes between calls, so a reused buffer still
holds the previous pair's values: every stage must write every cell it
later reads.  Checked by running pair B after pair A (and after a larger
pair) on one matcher and comparing bit for bit with a fresh matcher's run
on B alone, intermediates included.
"""

import cv2
import numpy as np
import pytest

from mccnn_cl.opencl.context import BufferPool
from mccnn_cl.pipeline import StereoMatcher

D = 24


def crop(shared_data, name, y0, x0, h, w):
    d = shared_data / "middlebury" / name
    left = cv2.imread(str(d / "im0.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(d / "im1.png"), cv2.IMREAD_GRAYSCALE)
    assert left is not None and right is not None, f"cannot read {name} from {d}"
    return left[y0:y0 + h, x0:x0 + w], right[y0:y0 + h, x0:x0 + w]


def same(a, b, what):
    assert a.shape == b.shape, what
    assert a.tobytes() == b.tobytes(), f"{what}: {int(np.sum(a.view(np.uint8) != b.view(np.uint8)))} bytes differ"


def test_pool_take_give_trim(ctx):
    pool = BufferPool(ctx)
    live0 = ctx.memory.live
    a = pool.take(4096, "a")
    b = pool.take(8192, "b")
    assert ctx.memory.live == live0 + 4096 + 8192
    pool.give(a, b, a)  # twice: kept once
    assert pool.free_bytes == 4096 + 8192
    assert pool.take(4000) is a  # smallest that fits
    assert pool.take(100) is b
    assert pool.free_bytes == 0
    pool.give(a, b)
    c = pool.take(16384, "c")  # nothing fits: the small free ones are freed first
    assert pool.free_bytes == 0 and ctx.memory.live == live0 + 16384
    pool.give(c)
    pool.trim(keep=16384)
    assert pool.free_bytes == 16384
    pool.trim(keep=4096)
    assert pool.free_bytes == 0 and ctx.memory.live == live0
    del a, b, c


@pytest.mark.full_data
def test_reused_volumes_give_the_same_result(ctx, shared_data):
    A = crop(shared_data, "Cones", 40, 60, 60, 90)
    B = crop(shared_data, "Reindeer", 100, 120, 60, 90)
    big = crop(shared_data, "Cones", 0, 0, 80, 120)
    fresh = StereoMatcher(cost="census", max_disparity=D, device=ctx)
    want = fresh.compute(*B, return_intermediates=True)
    fresh.release_buffers()

    m = StereoMatcher(cost="census", max_disparity=D, device=ctx)
    m.compute(*A)
    kept = m._pool.free_bytes
    vol = m.memory_plan(A[0].shape).volume_bytes
    assert kept == 2 * vol  # the cost volume (mirrored in place for the right reference) and SGM's
    got = m.compute(*B, return_intermediates=True)  # same size: the kept volumes are reused
    for name, arr in want.intermediates.items():
        same(got.intermediates[name], arr, name)
    same(got.disparity, want.disparity, "D_BF")
    # the kept volumes count in the peak (a first call also makes the CBCA rings)
    assert 2 * vol <= got.peak_device_bytes <= want.peak_device_bytes <= got.plan.peak_bytes
    assert m._pool.free_bytes == kept  # nothing new kept

    m.compute(*big)  # larger: the small kept volumes are freed, not held beside the new ones
    assert m._pool.free_bytes == 2 * m.memory_plan(big[0].shape).volume_bytes
    got = m.compute(*B)  # smaller again: the large ones are freed by the call
    same(got, want.disparity, "D_BF after a larger pair")
    assert m._pool.free_bytes == kept
    live = ctx.memory.live
    m.release_buffers()
    assert ctx.memory.live == live - kept and m._pool.free_bytes == 0


@pytest.mark.parametrize("right_reference", ["derived"])
@pytest.mark.full_data
def test_reuse_with_derived_right_reference(ctx, shared_data, right_reference):
    A = crop(shared_data, "Cones", 40, 60, 50, 80)
    B = crop(shared_data, "Reindeer", 100, 120, 50, 80)
    want = StereoMatcher(cost="census", max_disparity=D, device=ctx, right_reference=right_reference).compute(*B)
    m = StereoMatcher(cost="census", max_disparity=D, device=ctx, right_reference=right_reference)
    m.compute(*A)
    assert m._pool.free_bytes == 2 * m.memory_plan(A[0].shape).volume_bytes
    same(m.compute(*B), want, "D_BF")
    m.release_buffers()
