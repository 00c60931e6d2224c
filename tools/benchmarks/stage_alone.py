"""One stage's kernels alone on a KITTI-sized input (random data, 228 x 367 x 1234
volume; fst maps of one 367 x 1234 image), timed after a warm-up, each run
printed (BENCHMARKS.md, "Machine C again").

    .venv/bin/python tools/benchmarks/stage_alone.py cbca [--iterations 4] [--select-add 0|1]
    .venv/bin/python tools/benchmarks/stage_alone.py sgm [--widths 16 8 [--rounds 4]]
    .venv/bin/python tools/benchmarks/stage_alone.py wta [--chunks 1|4|8|16]
    .venv/bin/python tools/benchmarks/stage_alone.py normalise     # fst_normalise16 and fst_normalise

Compare variants by running them in turn in one session (speed drifts between
minutes); the device is the default one (PYOPENCL_CTX or GPU > CPU).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mccnn_cl.opencl.context import ClContext, launch_sizes

H, W, D = 367, 1234, 228


def timed(ctx, fn, runs):
    fn()
    ctx.finish()
    out = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ctx.finish()
        out.append(time.perf_counter() - t)
    return out


def volume_inputs(ctx, rows=None):
    """The tuner's random inputs (:func:`mccnn_cl.opencl.tune._inputs`) at this size (``rows`` rows
    instead of H where given), on the device."""
    from mccnn_cl.opencl.tune import _inputs

    img_l, img_r, vol = _inputs(ctx, (H if rows is None else int(rows), W, D))
    return ctx.to_device(img_l), ctx.to_device(img_r), ctx.to_device(vol), ctx.empty(vol.nbytes, "out")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("stage", choices=("cbca", "sgm", "normalise", "wta"))
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--iterations", type=int, default=4, help="CBCA iterations (general-fst: 4)")
    ap.add_argument("--max-arm", type=int, default=4, help="CBCA arm bound (general-fst's eta 5: 4)")
    ap.add_argument("--select-add", type=int, choices=(0, 1), default=None,
                    help="CBCA multi path's masked-term form (default: by the device)")
    ap.add_argument("--chunks", type=int, default=None, help="left WTA chunks per work-item (default: the rule)")
    ap.add_argument("--widths", type=int, nargs="+", choices=(16, 8), default=None,
                    help="SGM: these vector widths in turn (default: the device's one)")
    ap.add_argument("--rounds", type=int, default=4, help="SGM --widths: rounds of the widths in turn")
    args = ap.parse_args()
    ctx = ClContext()
    print(f"device: {ctx.describe()}")
    if args.stage == "normalise":
        from mccnn_cl.costs.fst import PADL, FstCost
        from mccnn_cl.models import resolve

        cost = FstCost(ctx, resolve("general-fst"))
        cs, nk, wp = cost.stack.stride, cost.nk, cost._wp(W)
        d_feat = ctx.to_device(np.random.default_rng(0).standard_normal((H * W, cs), dtype=np.float32))
        d_out = ctx.empty(H * nk * wp * 4, "planes")
        for name, px in (("fst_normalise16", 16), ("fst_normalise", 1)):
            kern = ctx.kernel("fst.cl", name, NK=nk, CS=cs, PADL=PADL)
            ts = timed(ctx, lambda: kern(ctx.queue, *launch_sizes(ctx, (wp // px, H), guarded=(1, 0)), d_feat,
                                         d_out, np.int32(W), np.int32(wp)), args.runs)
            print(f"{name} ({nk} maps, {H} x {W}): " + " ".join(f"{t * 1000:.1f}" for t in ts) + " ms")
        return
    d_l, d_r, d_vol, d_out = volume_inputs(ctx)
    if args.stage == "cbca":
        from mccnn_cl.stages.cbca import CBCA
        from mccnn_cl.stages.cross import CrossArms

        cross = CrossArms(ctx)
        al, ar = cross(d_l, H, W), cross(d_r, H, W)
        cb = CBCA(ctx, select_add=None if args.select_add is None else bool(args.select_add))
        ts = timed(ctx, lambda: cb(d_vol, al, ar, D, H, W, args.iterations, args.max_arm, out=d_out), args.runs)
        print(f"CBCA ({cb.path(args.max_arm)} path, {args.iterations} iterations, max arm {args.max_arm}): "
              + " ".join(f"{t * 1000:.0f}" for t in ts) + " ms")
    elif args.stage == "wta":
        from mccnn_cl.stages.disparity import WinnerTakeAll

        wta = WinnerTakeAll(ctx, chunks=args.chunks)
        disp = ctx.empty(H * W * 4, "map")
        ts = timed(ctx, lambda: wta.left(d_vol, D, H, W, out=disp), args.runs)
        print(f"WTA left ({wta.chunks} chunks of 16 pixels per work-item): "
              + " ".join(f"{t * 1000:.1f}" for t in ts) + " ms")
    elif args.widths:  # SGM on 16- and 8-wide vectors, in turn, the outputs compared bit for bit
        from mccnn_cl.stages.sgm import SGM

        sgms = {w: SGM(ctx, width=w) for w in args.widths}
        outs = {}
        for w, sgm in sgms.items():
            sgm(d_vol, d_l, d_r, D, H, W, out=d_out)
            outs[w] = ctx.from_device(d_out, (D, H, W)).view(np.uint32)
        first = outs[args.widths[0]]
        print("the same bits at every width: " + str(all(np.array_equal(o, first) for o in outs.values())))
        for r in range(args.rounds):
            for w in (args.widths if r % 2 == 0 else args.widths[::-1]):
                ts = timed(ctx, lambda: sgms[w](d_vol, d_l, d_r, D, H, W, out=d_out), args.runs)
                print(f"round {r}: SGM width {w} (paired sweeps: {sgms[w].paired}): "
                      + " ".join(f"{t * 1000:.0f}" for t in ts) + " ms", flush=True)
    else:
        from mccnn_cl.stages.sgm_select import make_sgm

        sgm = make_sgm(ctx)
        ts = timed(ctx, lambda: sgm(d_vol, d_l, d_r, D, H, W, out=d_out), args.runs)
        print(f"SGM (paired sweeps: {getattr(sgm, 'paired', None)}): " + " ".join(f"{t * 1000:.0f}" for t in ts)
              + " ms")


if __name__ == "__main__":
    main()
