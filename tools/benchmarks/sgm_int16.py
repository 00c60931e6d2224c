"""How fast could SGM's paired sweeps be in 16-bit integer lanes?  A
measurement prototype (``sgm_int16.cl``, not used by the package): the paired
sweeps' structure in float16 lanes and in short16 lanes, timed in one process
beside the package's SGM (the device's rules) on stage_alone.py's KITTI-sized
random volume (BENCHMARKS.md, "SGM in 16-bit lanes").

    .venv/bin/python tools/benchmarks/sgm_int16.py --check      # short form == integer reference
    .venv/bin/python tools/benchmarks/sgm_int16.py [--rounds 5] [--rows 367] [--pitch 1232]

A prototype work-item walks its half of the rows with two of the four paths;
the package's paired sweeps walk every row with all four (two launches), so
each prototype form is timed as two calls.  Times are the best of 3 per round,
rounds in turn; speed drifts between minutes on these VMs, so only ratios
within one run mean much.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

BIG = 0x3000  # the short form's +infinity (sgm_int16.cl)
PEN_SHORT = (20, 10, 300, 150)  # P1 (flag clear, set), P2 (flag clear, set): integers
PEN_FLOAT = (0.02, 0.01, 0.3, 0.15)


def build(ctx, short, float_io=False, prefetch=False):
    # through the context's own program path: its build log (PoCL's notes on 16-float vectors
    # without AVX-512) and compiler output are handled as the package's programs' are
    src = (HERE / "sgm_int16.cl").read_text()
    return ctx._make_program("sgm_int16.cl", src, [
        "-I", ctx.kernel_dir, f"-DPROTO_SHORT={int(short)}", f"-DFLOAT_IO={int(float_io)}",
        f"-DPROTO_PREFETCH={int(prefetch)}", "-DMAXD=256"])


def flag_table(rng, W, dtype):
    """Penalty flags (-1 set, 0 clear) read at x + 256 - d (vertical) and 512 + x - d0 + j (horizontal)."""
    return ((rng.random(W + 544) < 0.3) * -1).astype(dtype)


def reference(c, bigs, rows_per, pen=PEN_SHORT):
    """The short form's result in exact integers: per work-item (rows_per rows each) the
    top->bottom path from its first row plus the left->right path of each row."""
    D, H, W = c.shape
    p1a, p1b, p2a, p2b = pen
    c = c.astype(np.int64)
    out = np.zeros_like(c)
    dd = np.arange(D)

    def step(cc, prev, big):
        m = prev.min()
        lo = np.concatenate([[BIG], prev[:-1]])
        hi = np.concatenate([prev[1:], [BIG]])
        best = np.minimum(np.minimum(prev, np.where(big, m + p2b, m + p2a)),
                          np.minimum(lo, hi) + np.where(big, p1b, p1a))
        return cc - m + best

    for y0 in range(0, H, rows_per):
        vprev = None
        for y in range(y0, min(H, y0 + rows_per)):
            v = np.empty((D, W), np.int64)
            h = np.empty((D, W), np.int64)
            for x in range(W):
                v[:, x] = c[:, y, x] if vprev is None else step(c[:, y, x], vprev[:, x], bigs[x + 256 - dd] != 0)
                h[:, x] = c[:, y, x] if x == 0 else step(c[:, y, x], h[:, x - 1],
                                                         bigs[512 + x - 2 * (dd // 16) * 16 + dd] != 0)
            out[:, y] = v + h
            vprev = v
    return out


class Proto:
    """One prototype form on its own buffers, arguments set."""

    def __init__(self, ctx, short, float_io, D, H, W, rng, prefetch=False, pitch=None):
        cl, mf = ctx.cl, ctx.cl.mem_flags
        self.ctx, self.prog = ctx, build(ctx, short, float_io, prefetch)
        t = np.int16 if short else np.float32
        io = np.float32 if (float_io or not short) else np.int16
        P = W if pitch is None else int(pitch)
        host = rng.random((D, H, P), dtype=np.float32)
        self.cost = (np.round(host * 1023) if io == np.int16 else host).astype(io)
        self.bigs = flag_table(rng, W, np.int16 if short else np.int32)
        self.bufs = [cl.Buffer(ctx.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=self.cost),
                     cl.Buffer(ctx.context, mf.READ_WRITE, size=self.cost.nbytes),
                     cl.Buffer(ctx.context, mf.READ_WRITE, size=2 * (W // 16) * (D + 2) * 16 * np.dtype(t).itemsize),
                     cl.Buffer(ctx.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=self.bigs)]
        self.rows_per, self.W = (H + 1) // 2, W
        pen = PEN_SHORT if short else PEN_FLOAT
        self.kernel = self.prog.proto
        self.kernel.set_args(*self.bufs, np.int32(D), np.int32(H), np.int32(W), *(t(p) for p in pen),
                             np.int32(self.rows_per), np.int32(P))

    def __call__(self):
        self.ctx.cl.enqueue_nd_range_kernel(self.ctx.queue, self.kernel, (2,), (1,))
        self.ctx.queue.finish()

    def output(self):
        out = np.empty_like(self.cost)
        self.ctx.cl.enqueue_copy(self.ctx.queue, out, self.bufs[1])
        return out[:, :, :self.W]


def check(ctx) -> int:
    rng = np.random.default_rng(1)
    ok = True
    for (D, H, W, P), fio in (((48, 10, 64, 64), False), ((32, 7, 48, 53), False), ((48, 9, 80, 85), True)):
        p = Proto(ctx, True, fio, D, H, W, rng, pitch=P)
        # the output poisoned first (a cell the kernel skips then differs from the reference)
        ctx.fill(p.bufs[1], 1e30 if fio else -12345, p.cost.nbytes, np.float32 if fio else np.int16)
        p()
        if fio:  # costs scaled by 512 and rounded (to even) on load; the sum scaled back on store
            ref = reference(np.round(p.cost[:, :, :W] * np.float32(512)), p.bigs, p.rows_per)
            got = p.output().astype(np.float64) * 512
        else:
            ref = reference(p.cost[:, :, :W], p.bigs, p.rows_per)
            got = p.output()
        same = np.array_equal(ref, got.astype(np.int64)) and np.array_equal(got, np.round(got))
        ok &= same
        form = "float volumes" if fio else "short volumes"
        print(f"short lanes, {form}, {D} x {H} x {W} (rows {P} apart): "
              f"{'the same integers as the reference' if same else 'DIFFERENT'}")
    return 0 if ok else 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="compare the short form with the integer reference")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--rows", type=int, default=None, help="volume rows (default: stage_alone.py's 367)")
    ap.add_argument("--pitch", type=int, default=None,
                    help="the prototypes' row pitch in floats (default: the package's W, 1234; 1232 aligns "
                         "every 16-float line to 64 bytes)")
    args = ap.parse_args()
    from mccnn_cl.opencl.context import ClContext

    ctx = ClContext()
    print(f"device: {ctx.describe()}")
    if args.check:
        return check(ctx)
    from mccnn_cl.stages.sgm import SGM
    from stage_alone import D, H, W, volume_inputs

    rows = H if args.rows is None else args.rows
    d_l, d_r, d_vol, d_out = volume_inputs(ctx, rows)
    sgm = SGM(ctx)

    def package():
        sgm(d_vol, d_l, d_r, D, rows, W, out=d_out)
        ctx.queue.finish()

    rng = np.random.default_rng(0)
    Wp, Dp = W // 16 * 16, D // 16 * 16
    pitch = W if args.pitch is None else args.pitch
    forms = {f"package SGM (paired {sgm.paired}, width {sgm.width}), {D} x {rows} x {W}": (package, 1)}
    for name, short, fio in (("float16 lanes", False, False), ("short16 lanes, short volumes", True, False),
                             ("short16 lanes, float volumes", True, True)):
        for pf in (False, True):
            label = (f"prototype, {name}{', prefetch' if pf else ''}, {Dp} x {rows} x {Wp} (rows {pitch} apart), "
                     "two calls")
            forms[label] = (Proto(ctx, short, fio, Dp, rows, Wp, rng, pf, pitch), 2)

    def timed(f, n):
        t = time.perf_counter()
        for _ in range(n):
            f()
        return time.perf_counter() - t

    for f, n in forms.values():
        timed(f, n)
    res = {k: [] for k in forms}
    for _ in range(args.rounds):
        for k, (f, n) in forms.items():
            res[k].append(min(timed(f, n) for _ in range(3)))
    base = np.median(res[next(iter(res))])
    for k, v in res.items():
        print(f"{k}: median {1e3 * np.median(v):.1f} ms ({np.median(v) / base:.2f}x)  "
              + " ".join(f"{1e3 * t:.0f}" for t in v))
    return 0


if __name__ == "__main__":
    sys.exit(main())
