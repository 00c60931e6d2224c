"""Timing of cross arms, CBCA and SGM on a KITTI-sized random volume.

    python tools/benchmarks/bench_aggregation.py
    python tools/benchmarks/bench_aggregation.py --H 376 --W 1240 --D 228 --repeat 1

Prints, for each stage, the wall time (queue finished), the CPU time of this
process over the same interval (PoCL's threads included: on a shared machine
wall time depends on the load, CPU time much less), and the bandwidth the
wall time achieves counting the volume bytes the stage must move at least
(reads + writes of D x H x W float32), beside the buffer-copy bandwidth
measured in the same run (copy of one volume: read + write).  Best of
``--repeat`` runs after one warm-up run.  SGM's volume traffic is that of
the kernels it runs (:func:`sgm_traffic`): the paired sweeps (the default
on devices of few compute units) read the cost volume twice and write the
output twice with one read of it, 5 V; the one-direction kernels read it
four times, write the output once and read + write it three times, 11 V.
"""

from __future__ import annotations

import argparse
import os
import resource
import time

import numpy as np

from mccnn_cl.opencl.context import ClContext
from mccnn_cl.stages.cbca import CBCA, MULTI_K
from mccnn_cl.stages.cross import CrossArms, max_arm
from mccnn_cl.stages.sgm import SGM


def _cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


CPU = {"last": float("nan")}


def timed(ctx, fn, repeat):
    """Best wall time of ``repeat`` runs (after a warm-up); CPU['last'] gets
    the CPU time of that run."""
    fn()  # warm-up (builds the program)
    ctx.finish()
    best = float("inf")
    for _ in range(repeat):
        c0, t0 = _cpu(), time.perf_counter()
        fn()
        ctx.finish()
        t = time.perf_counter() - t0
        if t < best:
            best, CPU["last"] = t, _cpu() - c0
    return best


def sgm_traffic(sgm, V) -> int:
    """Bytes an SGM call moves with ``sgm``'s kernels (V: one volume's bytes):
    the paired sweeps (sgm_paired, two launches) 2 reads of the cost volume
    + 2 writes and 1 read of the output = 5 V; the one-direction kernels 4
    reads of C + the output written once, then read + written three times =
    11 V."""
    return (5 if sgm.paired else 11) * V


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--H", type=int, default=376)
    ap.add_argument("--W", type=int, default=1240)
    ap.add_argument("--D", type=int, default=228)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--device", default=None)
    ap.add_argument("--stages", default="arms,cbca,sgm", help="comma-separated subset of arms,cbca,sgm")
    args = ap.parse_args(argv)
    D, H, W = args.D, args.H, args.W
    ctx = ClContext(args.device)
    print(f"device: {ctx.describe()}; {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
    rng = np.random.default_rng(0)
    cost = rng.random((D, H, W), dtype=np.float32)
    cost[np.broadcast_to(np.arange(W)[None, None, :] < np.arange(D)[:, None, None], cost.shape)] = np.nan
    img_l = rng.random((H, W), dtype=np.float32)
    img_r = rng.random((H, W), dtype=np.float32)
    V = cost.nbytes
    print(f"volume: D x H x W = {D} x {H} x {W}, {V / 1e6:.0f} MB")
    d_cost = ctx.to_device(cost)
    del cost
    d_l, d_r = ctx.to_device(img_l), ctx.to_device(img_r)
    d_tmp = ctx.empty(V)
    d_out = ctx.empty(V)

    t = timed(ctx, lambda: ctx.cl.enqueue_copy(ctx.queue, d_tmp, d_cost, byte_count=V), args.repeat)
    copy_bw = 2 * V / t / 1e9
    print(f"buffer copy      {t * 1e3:8.1f} ms  {copy_bw:6.2f} GB/s (read + write of one volume), "
          f"cpu {CPU['last'] * 1e3:.0f} ms")

    arms = CrossArms(ctx)
    d_al, d_ar = ctx.empty(4 * H * W), ctx.empty(4 * H * W)

    def run_arms():
        arms(d_l, H, W, out=d_al)
        arms(d_r, H, W, out=d_ar)

    t = timed(ctx, run_arms, args.repeat)
    if "arms" in args.stages:
        print(f"cross arms (x2)  {t * 1e3:8.1f} ms, cpu {CPU['last'] * 1e3:.0f} ms")

    cbca = CBCA(ctx)
    runs = [(max_arm(4), cbca), (255, cbca)]
    if cbca.path(max_arm(4)) == "multi":  # the default's one-iteration-per-launch alternative, for comparison
        runs.insert(1, (max_arm(4), CBCA(ctx, multi=False)))
    if cbca.path(max_arm(4)) != "workgroup":  # the GPU-shaped passes (the gpu column's default), forced,
        # beside the short passes, which compute the same sums in the same order
        if cbca.path(max_arm(4)) != "short":
            runs.append((max_arm(4), CBCA(ctx, fused=False, multi=False, workgroup=False)))
        runs.append((max_arm(4), CBCA(ctx, workgroup=True)))
    for bound, st in runs if "cbca" in args.stages else ():
        t = timed(ctx, lambda: st(d_cost, d_al, d_ar, D, H, W, iterations=4, max_arm=bound, out=d_out),
                  args.repeat)
        # volume passes (a read + a write each) per round of 4 iterations: the
        # multi-iteration fused kernel 1 (MULTI_K = 4 iterations per launch),
        # the one-iteration fused kernel 4, the two-pass kernels 8 (short,
        # running and work-group passes alike)
        kind = st.path(bound)
        passes = {"multi": -(-4 // MULTI_K), "fused": 4}.get(kind, 8)
        moved = passes * 2 * V
        print(f"CBCA 4 it (max_arm={bound:3d}, {kind:9s}) {t * 1e3:8.1f} ms  {moved / t / 1e9:6.2f} GB/s "
              f"({t / 4 * 1e3:.1f} ms per iteration), cpu {CPU['last'] * 1e3:.0f} ms")

    sgm = SGM(ctx)
    if "sgm" in args.stages:
        t = timed(ctx, lambda: sgm(d_cost, d_l, d_r, D, H, W, out=d_out), args.repeat)
        moved = sgm_traffic(sgm, V)
        kind = "paired" if sgm.paired else "one-direction"
        print(f"SGM 4 directions {t * 1e3:8.1f} ms  {moved / t / 1e9:6.2f} GB/s ({kind} kernels, {moved // V} V), "
              f"cpu {CPU['last'] * 1e3:.0f} ms")
    print(f"(buffer-copy bandwidth {copy_bw:.2f} GB/s)")


if __name__ == "__main__":
    main()
