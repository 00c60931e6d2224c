"""Volume reuse (mccnn_cl.opencl.context.BufferPool, StereoMatcher's kept volumes).

A matcher keeps its cost volumes between calls, so a reused buffer still
holds the previous pair's values: every stage must write every cell it
later reads.  Checked by running pair B after pair A (and after a larger
pair) on one matcher and comparing bit for bit with a fresh matcher's run
on B alone, intermediates included.
"""

import gc

import cv2
import numpy as np
import pytest

from mccnn_cl.errors import InputError
from mccnn_cl.opencl.context import Arena, BufferPool
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
    gc.collect()  # an earlier test's matcher, collected later, would free its buffers inside this count
    base = ctx.memory.live  # the constructor's own small tables
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
    m.release_buffers()  # the kept volumes and every stage's scratch
    assert ctx.memory.live <= live - kept and m._pool.free_bytes == 0
    assert ctx.memory.live == base


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


# -- a lent buffer (Arena): the network's scratch inside SGM's output volume -----------

def test_arena_carves_sub_buffers_of_the_lent_buffer(ctx):
    align = ctx.sub_buffer_align
    assert align >= 4096 and align & (align - 1) == 0
    parent = ctx.empty(16 * align, "lent")
    ctx.fill(parent, -7.0, 16 * align)
    live0 = ctx.memory.live
    arena = Arena(ctx, parent)
    maps, planes = BufferPool(ctx), BufferPool(ctx)  # two pools share one arena, as the fst cost's do
    maps.lend(arena)
    planes.lend(arena)
    x = maps.take(1000, "x")                  # at 0
    y = planes.take(2 * align, "y")           # at the next aligned offset: align
    assert ctx.memory.live == live0           # no new device memory
    ctx.fill(x, 1.0, 1000)
    ctx.fill(y, 2.0, 2 * align)
    host = ctx.from_device(parent, (16 * align // 4,))
    q = align // 4
    assert (host[:250] == 1.0).all() and (host[250:q] == -7.0).all()  # x, then the gap to the aligned offset
    assert (host[q:3 * q] == 2.0).all() and (host[3 * q:] == -7.0).all()
    z = maps.take(14 * align, "z")            # does not fit behind them (3 of 16 pages used): a new buffer
    assert ctx.memory.live == live0 + 14 * align
    w = maps.take(13 * align, "w")            # fits: carved
    assert ctx.memory.live == live0 + 14 * align
    maps.give(x, z, w)
    planes.give(y)
    assert maps.free_bytes == 14 * align and planes.free_bytes == 0  # carved buffers are the arena's
    assert maps.take(900) is x                # a carved buffer is reused while the loan lasts
    maps.give(x)
    maps.end_loan()
    planes.end_loan()
    assert maps.take(4, "after") is z and maps.free_bytes == 0  # only the pool's own buffer is kept
    maps.give(z)
    maps.lend(Arena(ctx, parent))             # a new loan, the pool's state reset
    v = maps.take(14 * align + 1)             # the kept z is too small: carved
    with pytest.raises(RuntimeError, match="not given back"):
        maps.end_loan()
    assert maps.take(8) is z                  # the loan ended all the same
    with pytest.raises(RuntimeError, match="already"):
        maps.lend(arena)
        maps.lend(arena)
    maps._arena = None
    del v
    maps.give(z)
    maps.clear()
    assert ctx.memory.live == live0


@pytest.mark.parametrize("weights", ["general-fst", "kitti-paper"])
def test_lent_scratch_gives_the_same_volume(ctx, shared_data, weights):
    """A network's volume with its maps carved from a lent (poisoned) buffer is
    the volume without the loan, bit for bit, whether the loan holds every map
    or only some; after the call the lent buffer is the caller's: overwriting
    it changes nothing in the next call, and the cost keeps no part of it."""
    from mccnn_cl.costs.registry import make_cost
    from mccnn_cl.models import resolve

    from conftest import POISON
    from helpers import kitti_crop, run_poisoned

    left, right = kitti_crop(shared_data, 120, 300, 40, 90)
    D = 20
    cost = make_cost(ctx, resolve(weights))
    want = run_poisoned(ctx, cost, left, right, D)
    cost.release_buffers()
    h, w = left.shape[0] - 2 * cost.margin, left.shape[1] - 2 * cost.margin
    items = cost._pooled_scratch(h, w)
    for lent_bytes in (sum(items) + len(items) * ctx.sub_buffer_align, max(items) + 100):
        lent = ctx.empty(lent_bytes, "lent")
        for call in range(2):
            ctx.fill(lent, POISON, lent_bytes)
            d_out = ctx.empty(D * h * w * 4, "volume")
            ctx.fill(d_out, POISON, D * h * w * 4)
            live = ctx.memory.live
            assert cost(left, right, D, out=d_out, scratch=lent) is d_out
            got = ctx.from_device(d_out, (D, h, w))
            assert got.tobytes() == want.tobytes(), f"{weights}, {lent_bytes} bytes lent"
            held = [b for p in cost._pools() for b in p._free]
            if lent_bytes > sum(items):  # every map carved: nothing new made, nothing of the loan kept
                assert ctx.memory.live == live and not held
            else:  # the maps that did not fit are the cost's own, made in the first call and kept
                assert held and ctx.memory.live == live + (0 if call else sum(int(b.size) for b in held))
            assert not any(p._carved or p._arena for p in cost._pools())
            assert (ctx.from_device(lent, (lent_bytes // 4,)) != POISON).any()  # the loan was used
        cost.release_buffers()
        assert cost.lent_scratch_bytes(h, w, lent_bytes) <= sum(items)
    with pytest.raises(InputError, match="lent"):
        cost(left, right, D, out=d_out, scratch=d_out)


def test_matcher_lends_sgm_volume_to_the_network(ctx, shared_data, monkeypatch):
    """StereoMatcher lends SGM's output volume to the network for its maps: the
    same map as without the loan, bit for bit, a first call's device peak
    lower by at least what the plan counts as lent, and within the plan."""
    from helpers import kitti_crop

    left, right = kitti_crop(shared_data, 100, 300, 100, 360)
    D = 160
    lent = StereoMatcher("general-fst", max_disparity=D, device=ctx)
    got = lent.compute(left, right, timings=True)
    own = StereoMatcher("general-fst", max_disparity=D, device=ctx)
    orig = own._matching_cost
    monkeypatch.setattr(own, "_matching_cost", lambda *a, scratch=None, **k: orig(*a, **k))
    want = own.compute(left, right, timings=True)
    same(got.disparity, want.disparity, "D_BF")
    H, W = left.shape[0] - 2 * lent.margin, left.shape[1] - 2 * lent.margin
    saved = lent.cost.lent_scratch_bytes(H, W, got.plan.volume_bytes)
    assert saved > 0.5 * got.plan.volume_bytes  # D 160 against 4 buffers of 64 maps
    assert want.peak_device_bytes - got.peak_device_bytes >= saved
    assert got.peak_device_bytes <= got.plan.peak_bytes < want.peak_device_bytes
    live = ctx.memory.live
    again = lent.compute(left, right)  # a second call makes nothing new
    same(again, got.disparity, "D_BF, second call")
    assert ctx.memory.live == live


def test_an_error_inside_a_loan_is_the_error_raised(ctx, shared_data, monkeypatch):
    """An exception (here a simulated Ctrl-C) while the network's maps are
    carved from a lent buffer propagates as itself; the loan ends, and the
    next call is as usual."""
    from mccnn_cl.costs.registry import make_cost
    from mccnn_cl.models import resolve

    from helpers import kitti_crop, run_poisoned

    left, right = kitti_crop(shared_data, 120, 300, 30, 70)
    cost = make_cost(ctx, resolve("general-fst"))
    want = run_poisoned(ctx, cost, left, right, 16)
    cost.release_buffers()
    lent = ctx.empty(64 << 20, "lent")

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    with monkeypatch.context() as mp:
        mp.setattr(cost, "_features", lambda *a, **k: (cost.stack._pool.take(4096), interrupted())[1])
        with pytest.raises(KeyboardInterrupt):
            cost(left, right, 16, scratch=lent)
    assert not any(p._carved or p._arena for p in cost._pools())
    h, w = left.shape[0] - 2 * cost.margin, left.shape[1] - 2 * cost.margin
    out = ctx.empty(16 * h * w * 4, "volume")
    cost(left, right, 16, out=out, scratch=lent)
    same(ctx.from_device(out, (16, h, w)), want, "volume after an interrupted call")


def test_a_refused_sub_buffer_falls_back_to_a_buffer_of_its_own(ctx, caplog):
    """A runtime that refuses a sub-buffer costs the loan, not the call: one
    warning, and the pool makes its own buffers from then on.  The refusal is
    real: an arena that believes its buffer larger than it is asks for a
    sub-buffer past the end (CL_INVALID_VALUE on every runtime)."""
    align = ctx.sub_buffer_align

    class Overstated:
        def __init__(self, buf):
            self.buf, self.size = buf, 64 * align

        def get_sub_region(self, origin, size):
            return self.buf.get_sub_region(origin, size)

    arena = Arena(ctx, Overstated(ctx.empty(align, "lent")))
    pool = BufferPool(ctx)
    pool.lend(arena)
    live = ctx.memory.live
    first = pool.take(100, "first")  # offset 0: inside the buffer, carved
    assert ctx.memory.live == live
    with caplog.at_level("WARNING", logger="mccnn_cl.opencl.context"):
        second = pool.take(100, "second")  # offset align: past the buffer's end, refused
        third = pool.take(100, "third")
    assert arena.refused and ctx.memory.live == live + 2 * 100
    assert sum("refused a sub-buffer" in r.getMessage() for r in caplog.records) == 1
    pool.give(first, second, third)
    pool.end_loan()
    assert pool.free_bytes == 200
    pool.clear()
    assert ctx.memory.live == live


def test_no_loan_where_the_runtime_makes_no_sub_buffers(ctx, shared_data, monkeypatch):
    """Where the context's probe found no sub-buffers, the cost ignores a lent
    buffer (it stays as it was) and the memory plan counts no lent bytes, so a
    run there stays within its plan as before the loan existed."""
    from conftest import POISON
    from helpers import kitti_crop

    assert ctx.sub_buffers  # PoCL, Oclgrind, Intel's runtime and Rusticl make them
    left, right = kitti_crop(shared_data, 100, 300, 100, 360)
    m = StereoMatcher("general-fst", max_disparity=160, device=ctx)
    H, W = left.shape[0] - 2 * m.margin, left.shape[1] - 2 * m.margin
    vol = m.memory_plan(left.shape).volume_bytes
    lent_plan = m.memory_plan(left.shape).peak_bytes
    held = m.cost.lent_scratch_bytes(H, W, vol)
    assert held > 0
    monkeypatch.setattr(ctx, "_sub_buffers", False)
    assert m.cost.lent_scratch_bytes(H, W, vol) == 0
    plan = m.memory_plan(left.shape)
    assert plan.peak_bytes == lent_plan + held  # the maps counted beside the volumes again
    lent = ctx.empty(vol, "lent")
    ctx.fill(lent, POISON, vol)
    m.cost(left, right, 160, out=ctx.empty(vol, "volume"), scratch=lent)
    assert (ctx.from_device(lent, (vol // 4,)) == POISON).all()  # untouched
    got = m.compute(left, right, timings=True)
    assert got.peak_device_bytes <= got.plan.peak_bytes == plan.peak_bytes
