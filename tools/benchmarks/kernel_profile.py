"""Each OpenCL kernel's device time in one matcher call on KITTI 2015 000000, from
the queue's profiling events (BENCHMARKS.md, "Machine C, a thirteenth session"):
the kernels' sums per call, the best of ``--rounds`` calls after a warm-up, beside
the wall time of each call.

    .venv/bin/python tools/benchmarks/kernel_profile.py [--weights general-fst | --cost census] [--rounds 3]
        [--set NAME=VALUE] [--data ../shared/data]

Every kernel launch the package makes goes through PyOpenCL's
``enqueue_nd_range_kernel`` or ``Kernel.__call__``; this script wraps both to keep
each launch's event.  Profiling events serialise nothing on an in-order queue,
but they are the device's own clock: on a CPU they include the time a kernel
waited for the cores.  Pause other work on the machine.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time

import pyopencl as cl

from _paths import kitti_000000  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default="general-fst", help="network (default: general-fst)")
    ap.add_argument("--cost", choices=("cnn", "census"), default="cnn")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="a hyperparameter")
    ap.add_argument("--data", default=None, help="shared data (default: $MCCNN_DATA, else ../shared/data)")
    args = ap.parse_args()

    from mccnn_cl import StereoMatcher
    from mccnn_cl.hyperparameters import parse_settings
    from mccnn_cl.opencl.context import ClContext

    pair = kitti_000000(args.data)

    events = []
    enqueue, call = cl.enqueue_nd_range_kernel, cl.Kernel.__call__

    def enqueue_kept(queue, kernel, *a, **kw):
        ev = enqueue(queue, kernel, *a, **kw)
        events.append((kernel.function_name, ev))
        return ev

    def call_kept(self, queue, *a, **kw):
        ev = call(self, queue, *a, **kw)
        events.append((self.function_name, ev))
        return ev

    cl.enqueue_nd_range_kernel, cl.Kernel.__call__ = enqueue_kept, call_kept
    ctx = ClContext(profiling=True)
    hp = parse_settings(args.set)
    if args.cost == "census":
        m = StereoMatcher(device=ctx, cost="census", **hp)
    else:
        m = StereoMatcher(device=ctx, weights=args.weights, **hp)
    m.compute(pair.left, pair.right)  # programs, buffers
    ctx.finish()
    per = collections.defaultdict(list)
    walls = []
    for _ in range(args.rounds):
        events.clear()
        t = time.perf_counter()
        m.compute(pair.left, pair.right)
        ctx.finish()
        walls.append(time.perf_counter() - t)
        sums, counts = collections.defaultdict(float), collections.Counter()
        for name, ev in events:
            sums[name] += (ev.profile.end - ev.profile.start) * 1e-9
            counts[name] += 1
        for name in sums:
            per[name].append((sums[name], counts[name]))
    what = "census" if args.cost == "census" else args.weights
    print(f"{ctx.describe()}\n{what}, KITTI 2015 000000, {hp or 'defaults'}; wall per call: "
          + ", ".join(f"{w:.3f}" for w in walls) + " s")
    print("| kernel | launches | best of the calls | each call |\n|---|---|---|---|")
    for name, v in sorted(per.items(), key=lambda kv: -min(x[0] for x in kv[1])):
        print(f"| {name} | {v[0][1]} | {min(x[0] for x in v) * 1e3:.1f} ms | "
              + ", ".join(f"{x[0] * 1e3:.1f}" for x in v) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
