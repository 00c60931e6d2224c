"""One 64 -> 64 3 x 3 layer of a shipped fst network: the package's direct
kernel (``network_conv``, RM 4) against its Winograd F(2x2, 3x3) kernel
(``network_conv_wino``, the CPU devices' rule) at several register blocks,
in turn in one process; each output checked against a float64 direct sum
(BENCHMARKS.md, "Winograd F(2x2, 3x3) for the conv stack").

    .venv/bin/python tools/benchmarks/winograd_ab.py [--blocks 4x4,4x2,4x1] [--rn 16] [--layer 1] [--rounds 3]
    .venv/bin/python tools/benchmarks/winograd_ab.py --stacks [--blocks ...]

``--stacks``: whole conv stacks instead (``ConvStack`` on a 375 x 1242 random
image, best of 3 after a warm-up): ``kitti-fst``, ``general-paper`` and an
acrt-shaped stack (1 -> 112, four 112 -> 112 layers, random weights), each on
the direct GEMM, the device's rule and every block.

``--blocks RTxXA``: RT tiles per work-item, XA of the 16 Winograd products per
pass (XA x RT accumulators of RN floats).  The input is a random map of the
size general-fst's second layer sees on a KITTI pair (373 x 1240 x 64).  Times
are the best of 3 calls per round.  ``POCL_KERNELLIB_NAME=avx2`` runs the
AVX2 code on an AVX-512 CPU.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

os.environ.setdefault("MCCNN_BINARY_CACHE", "off")  # blocks the package does not use stay out of the cache

from mccnn_cl.costs.features import CONV_WINO_CL, launch_winograd, winograd_weights  # noqa: E402
from mccnn_cl.models import resolve  # noqa: E402
from mccnn_cl.opencl.context import ClContext  # noqa: E402
from mccnn_cl.reference.network import conv_layer as reference  # noqa: E402


class WinogradLayer:
    """The package's Winograd kernel built for one layer shape (``cin`` -> ``cout`` maps, ReLU or not) with
    register block ``rt`` x ``xa`` and ``rn`` channels per work-item: :meth:`__call__` runs it
    on uploaded buffers."""

    def __init__(self, ctx, cin, cout, relu, rt, xa, rn):
        if cin % rn or cout % rn:
            raise ValueError(f"the Winograd kernel needs channels in multiples of RN={rn}, got {cin} -> {cout}")
        self.ctx, self.cout, self.rt, self.rn = ctx, cout, rt, rn
        self.kernel = ctx.kernel(CONV_WINO_CL, "network_conv_wino", CIN=cin, CS=cin, NP=cout, RELU=int(relu),
                                 RN=rn, RT=rt, XA=xa)

    def __call__(self, d_x, h_in, w_in, d_u, d_b, d_out, p=0):
        launch_winograd(self.ctx, self.kernel, self.rt, self.rn, d_x, w_in, d_u, d_b, d_out, w_in - 2, h_in - 2,
                        self.cout, p)


def parse_blocks(text):
    """"4x4,4x1" -> [(4, 4), (4, 1)]: the --blocks list of (RT, XA)."""
    return [tuple(int(v) for v in spec.split("x")) for spec in text.split(",")]


def stacks(ctx, args):
    """Each stack on the direct GEMM, the rule's block and every --blocks block (module docstring)."""
    from mccnn_cl.costs.features import ConvStack, normalise
    from mccnn_cl.weights import Weights

    img = normalise(np.random.default_rng(0).random((375, 1242)).astype(np.float32))[:, :, None]
    d_img = ctx.to_device(np.ascontiguousarray(img))
    nets = {"kitti-fst": resolve("kitti-fst"), "general-paper": resolve("general-paper"),
            "acrt-shaped, 112 maps": Weights.random([[112, 3]] * 5, [384, 384, 1], architecture="mccnn-acrt",
                                                   seed=1)}
    blocks = parse_blocks(args.blocks)
    print(f"the rule's block here: {ctx.profile.winograd()}")
    for name, w in nets.items():
        print(f"{name}: {[tuple(W.shape) for W, _ in w.conv]}")
        for choice in [False, None] + blocks:
            st = ConvStack(ctx, w, args.rn, 4, winograd=choice)
            feat = st(d_img, 375, 1242)
            ctx.finish()
            best = float("inf")
            for _ in range(3):
                st.give(feat)
                t = time.perf_counter()
                feat = st(d_img, 375, 1242)
                ctx.finish()
                best = min(best, time.perf_counter() - t)
            label = "direct" if choice is False else "rule" if choice is None else f"{choice}"
            print(f"  {label:>8}: layers {[l[0].wino for l in st.layers]}: {best:.3f} s")
            st.release_buffers()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", default="4x4,4x2,4x1", help="RTxXA register blocks of the Winograd kernel")
    ap.add_argument("--rn", type=int, choices=(8, 16), default=16, help="channels per work-item (both kernels)")
    ap.add_argument("--layer", type=int, choices=(1, 2, 3), default=1, help="general-fst's conv layer")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--stacks", action="store_true", help="time whole conv stacks (above) instead of one layer")
    args = ap.parse_args()
    ctx = ClContext()
    q, rn = ctx.queue, args.rn
    print(f"device: {ctx.describe()}")
    if args.stacks:
        return stacks(ctx, args)
    wts = resolve("general-fst")  # the shipped Weights
    W, b = wts.conv[args.layer]
    W, b = np.asarray(W, np.float32), np.asarray(b, np.float32)
    cout, cin = W.shape[:2]
    h_in, w_in = 373, 1240
    x = np.random.default_rng(0).standard_normal((h_in, w_in, cin)).astype(np.float32)
    h_out, w_out = h_in - 2, w_in - 2
    m_total = h_out * w_out
    relu = int(args.layer < len(wts.conv) - 1 or wts.relu_after_last_conv)
    ref = reference(x, W, b, relu)
    d_x, d_b = ctx.to_device(x), ctx.to_device(b)
    d_wt = ctx.to_device(W.transpose(2, 3, 1, 0).reshape(9 * cin, cout).copy())
    d_u = ctx.to_device(winograd_weights(W, cout))
    d_out = ctx.empty(m_total * cout * 4)
    defs = dict(KS=3, CIN=cin, CS=cin, NP=cout, RELU=relu, RN=rn)
    direct = ctx.kernel("network_conv.cl", "network_conv", RM=4, **defs)
    runs = {"network_conv (RM 4)": lambda: direct(q, (cout // rn, math.ceil(m_total / 4)), None, d_x, np.int32(w_in),
                                                   d_wt, d_b, d_out, np.int32(w_out), np.int32(m_total))}
    for rt, xa in parse_blocks(args.blocks):
        layer = WinogradLayer(ctx, cin, cout, relu, rt, xa, rn)
        runs[f"Winograd RT {rt} XA {xa}"] = lambda layer=layer: layer(d_x, h_in, w_in, d_u, d_b, d_out)
    for name, run in runs.items():
        ctx.fill(d_out, np.float32(np.nan), m_total * cout * 4)
        run()
        got = ctx.from_device(d_out, (m_total, cout))
        err = np.abs(got - ref).max() / np.abs(ref).max()
        print(f"{name}: max error {err:.1e} of the largest output{' (NaN left)' if np.isnan(got).any() else ''}")
    times = {name: [] for name in runs}
    for _ in range(args.rounds):
        for name, run in runs.items():
            best = float("inf")
            for _ in range(3):
                t = time.perf_counter()
                run()
                ctx.finish()
                best = min(best, time.perf_counter() - t)
            times[name].append(best)
    for name, ts in times.items():
        print(f"{name:>28}: " + " ".join(f"{t * 1000:.0f}" for t in ts) + f" ms; median {np.median(ts) * 1000:.0f}")


if __name__ == "__main__":
    main()
