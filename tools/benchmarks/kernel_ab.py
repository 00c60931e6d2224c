"""Kernel sources A/B for one stage alone (SGM or CBCA) on a KITTI-sized
random volume (stage_alone.py's inputs: 228 x 367 x 1234, or ``--rows`` rows), in turn in one
process: the working tree's kernels against those of a git revision
(``--rev``) and/or against the tree built with extra defines (``--define``),
each round timing every variant (best of 3 calls), the outputs compared bit
for bit with the first variant's (BENCHMARKS.md, "SGM's tile loops unrolled").

    .venv/bin/python tools/benchmarks/kernel_ab.py sgm --rev HEAD~1 [--width 8] [--rounds 7] [--rows 48]
    .venv/bin/python tools/benchmarks/kernel_ab.py sgm --define SGM_PAIR_CW=32 [--define ...]
    .venv/bin/python tools/benchmarks/kernel_ab.py sgm --paired 0 --rev HEAD  # the one-direction kernels
    .venv/bin/python tools/benchmarks/kernel_ab.py cbca --rev f36a0c6 [--iterations 4 --max-arm 4] [--images kitti]

A revision's kernels are checked out (``git show``) into a temporary folder
and built from there; its stage must take the tree's host-side buffers (the
same scratch layout).  ``--cpu-time`` times by the process's CPU time / 2
(steadier than wall time while other work shares the 2 cores).  Speed drifts
between minutes on these VMs: only ratios within a round mean much.  Kernel
binaries are not stored (MCCNN_BINARY_CACHE=off for this process).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ["MCCNN_BINARY_CACHE"] = "off"  # before the package reads it; keeps foreign builds out of the cache

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stage_alone import H, W, D, volume_inputs  # noqa: E402

from mccnn_cl.opencl.context import ClContext  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
KERNELS = "mccnn_cl/kernels"


def checkout_kernels(rev: str, into: Path) -> None:
    """The kernel folder (``.cl`` and ``.h``) of git revision ``rev`` into ``into``."""
    names = subprocess.run(["git", "ls-tree", "--name-only", f"{rev}:{KERNELS}"], cwd=REPO, check=True,
                           capture_output=True, text=True).stdout.split()
    for name in names:
        if name.endswith((".cl", ".h")):
            src = subprocess.run(["git", "show", f"{rev}:{KERNELS}/{name}"], cwd=REPO, check=True,
                                 capture_output=True).stdout
            (into / name).write_bytes(src)


class Variant:
    """One stage object whose kernels come from ``kernel_dir`` built with ``extra`` defines."""

    def __init__(self, ctx, stage, name, kernel_dir, extra, args):
        self.ctx, self.name, self.kernel_dir, self.extra = ctx, name, kernel_dir, dict(extra)
        if kernel_dir is not None:
            self.extra["MCCNN_AB_VARIANT"] = name.replace("~", "_").replace("^", "_").replace("-", "_")
        if stage == "sgm":
            from mccnn_cl.stages.sgm import SGM

            self.obj = SGM(ctx, width=args.width, paired=args.paired)
            self.call = lambda d_vol, d_l, d_r, al, ar, out: self.obj(d_vol, d_l, d_r, D, H, W, out=out)
        else:
            from mccnn_cl.stages.cbca import CBCA

            self.obj = CBCA(ctx)
            self.call = lambda d_vol, d_l, d_r, al, ar, out: self.obj(d_vol, al, ar, D, H, W, args.iterations,
                                                                      args.max_arm, out=out)

    def __call__(self, *a):
        """One call, its kernels built (on the first call) from this variant's folder and defines."""
        ctx, kernel, tree_dir = self.ctx, self.ctx.kernel, self.ctx.kernel_dir

        def patched(filename, name, **defines):
            return kernel(filename, name, **{**defines, **self.extra})  # the variant's defines win

        ctx.kernel = patched
        if self.kernel_dir is not None:
            ctx.kernel_dir = str(self.kernel_dir)
        try:
            return self.call(*a)
        finally:
            ctx.kernel = kernel
            ctx.kernel_dir = tree_dir


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("stage", choices=("sgm", "cbca"))
    ap.add_argument("--rev", action="append", default=[], help="a git revision whose kernels to compare (repeatable)")
    ap.add_argument("--define", action="append", default=[], metavar="NAME=VALUE",
                    help="a variant: the tree's kernels with this extra define (repeatable; 'A=1,B=2' for several)")
    ap.add_argument("--width", type=int, choices=(8, 16), default=None, help="SGM vector width (default: the rule)")
    ap.add_argument("--paired", type=int, choices=(0, 1), default=None,
                    help="SGM: 1 the paired sweeps, 0 the one-direction kernels (sgm_rows, sgm_columns; "
                         "the rule on CPUs with more than 2 compute units); default: the rule")
    ap.add_argument("--iterations", type=int, default=4, help="CBCA iterations (general-fst: 4)")
    ap.add_argument("--max-arm", type=int, default=4, help="CBCA arm bound (general-fst's eta 5: 4)")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--rows", type=int, default=None,
                    help="rows of the volume instead of 367 (e.g. 48: ~40 ms calls, so many rounds fit in a "
                         "minute and the host's drift between minutes weighs less; the kernels' time per cell "
                         "is the same at 4 and at 367 rows on the Zen 3)")
    ap.add_argument("--images", choices=("random", "kitti"), default="random",
                    help="CBCA: the arms of the tuner's random images (default) or of KITTI 2015 000000 "
                         "($MCCNN_DATA, else ../shared/data; its top-left corner at the volume's size, "
                         "standardised; general-fst's tau 0.03, eta 5)")
    ap.add_argument("--cpu-time", action="store_true", help="time by process CPU time / 2")
    args = ap.parse_args()
    global H
    if args.rows is not None:
        if args.rows < 1:
            ap.error("--rows must be >= 1")
        H = args.rows
    ctx = ClContext()
    print(f"device: {ctx.describe()}; {args.stage}, {D} x {H} x {W}, {args.rounds} rounds, best of 3 calls per "
          "round")
    d_l, d_r, d_vol, d_out = volume_inputs(ctx, H)
    al = ar = None
    if args.stage == "cbca":
        from mccnn_cl.stages.cross import CrossArms

        cross = CrossArms(ctx)
        if args.images == "kitti":  # the arms of a real pair with general-fst's settings (tau, eta, neighbour)
            from bench_scaling import kitti_gray

            from mccnn_cl.costs.features import normalise

            al, ar = (cross(ctx.to_device(normalise(img.astype(np.float32) / 255.0)), H, W, 0.03, 5, True)
                      for img in kitti_gray(H, W))
        else:
            al, ar = cross(d_l, H, W), cross(d_r, H, W)
    tmp = tempfile.TemporaryDirectory(prefix="kernel_ab-")
    variants = [Variant(ctx, args.stage, "tree", None, {}, args)]
    for rev in args.rev:
        folder = Path(tmp.name) / rev.replace("/", "_")
        folder.mkdir()
        checkout_kernels(rev, folder)
        variants.append(Variant(ctx, args.stage, rev, folder, {}, args))
    for spec in args.define:
        extra = dict(part.split("=", 1) for part in spec.split(","))
        variants.append(Variant(ctx, args.stage, spec, None, extra, args))
    clock = (lambda: time.process_time() / 2) if args.cpu_time else time.perf_counter
    outs = []
    for v in variants:  # warm-up: builds and the first touch; the outputs to compare
        ctx.fill(d_out, np.float32(np.nan), d_out.size)
        v(d_vol, d_l, d_r, al, ar, d_out)
        ctx.finish()
        outs.append(ctx.from_device(d_out, (D, H, W)).view(np.uint32).copy())
    times = [[] for _ in variants]
    for r in range(args.rounds):
        order = list(range(len(variants)))
        if r % 2:
            order.reverse()
        for i in order:
            best = float("inf")
            for _ in range(3):
                t = clock()
                variants[i](d_vol, d_l, d_r, al, ar, d_out)
                ctx.finish()
                best = min(best, clock() - t)
            times[i].append(best)
    for v, ts, out in zip(variants, times, outs):
        same = "same bits" if np.array_equal(out, outs[0]) else "DIFFERENT bits"
        print(f"{v.name:>24}: " + " ".join(f"{t * 1000:.0f}" for t in ts)
              + f" ms; median {np.median(ts) * 1000:.0f}, min {min(ts) * 1000:.0f} ms; {same}")
    tmp.cleanup()


if __name__ == "__main__":
    main()
