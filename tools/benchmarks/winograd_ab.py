"""One 64 -> 64 3 x 3 layer of a shipped fst network: the package's direct
kernel (``network_conv``, the device's rule tiles) against the Winograd
F(2x2, 3x3) prototype ``winograd_proto.cl`` (not used by the package) at
several register blocks, in turn in one process; each output checked against
a float64 direct sum (BENCHMARKS.md, "The lever left for the network").

    .venv/bin/python tools/benchmarks/winograd_ab.py [--blocks 4x4,4x2,4x1] [--rn 16] [--layer 1] [--rounds 3]

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
from pathlib import Path

import numpy as np

os.environ.setdefault("MCCNN_BINARY_CACHE", "off")  # prototype builds stay out of the cache

from mccnn_cl.models import resolve  # noqa: E402
from mccnn_cl.opencl.context import ClContext  # noqa: E402

HERE = Path(__file__).resolve().parent
#: Winograd F(2x2, 3x3)'s weight transform (U = G g G^T)
G = np.array([[1, 0, 0], [.5, .5, .5], [.5, -.5, .5], [0, 0, 1]], np.float64)


def reference(x, W, b):
    """float64 valid 3 x 3 convolution + bias + ReLU of a channel-last map, [h_out * w_out][cout]."""
    h, w, _ = x.shape
    out = np.zeros((h - 2, w - 2, W.shape[0]))
    for ky in range(3):
        for kx in range(3):
            out += x[ky:ky + h - 2, kx:kx + w - 2].astype(np.float64) @ W[:, :, ky, kx].T.astype(np.float64)
    return np.maximum(out + b, 0).reshape(-1, W.shape[0])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", default="4x4,4x2,4x1", help="RTxXA register blocks of the prototype")
    ap.add_argument("--rn", type=int, choices=(8, 16), default=16, help="channels per work-item (both kernels)")
    ap.add_argument("--layer", type=int, choices=(1, 2, 3), default=1, help="general-fst's conv layer")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    ctx = ClContext()
    cl, q, rn = ctx.cl, ctx.queue, args.rn
    print(f"device: {ctx.describe()}")
    wts = resolve("general-fst")  # the shipped Weights
    W, b = wts.conv[args.layer]
    W, b = np.asarray(W, np.float32), np.asarray(b, np.float32)
    cout, cin = W.shape[:2]
    h_in, w_in = 373, 1240
    x = np.random.default_rng(0).standard_normal((h_in, w_in, cin)).astype(np.float32)
    h_out, w_out = h_in - 2, w_in - 2
    m_total = h_out * w_out
    ref = reference(x, W, b)
    relu = int(args.layer < len(wts.conv) - 1 or wts.relu_after_last_conv)
    if not relu:
        raise SystemExit("the reference here applies ReLU: pick a layer followed by one (1 or 2 for fst)")
    d_x, d_b = ctx.to_device(x), ctx.to_device(b)
    d_wt = ctx.to_device(W.transpose(2, 3, 1, 0).reshape(9 * cin, cout).copy())
    U = np.einsum("ai,kcij,bj->cabk", G, W.astype(np.float64), G).reshape(cin, 16, cout).astype(np.float32)
    d_u = ctx.to_device(np.ascontiguousarray(U))
    d_out = ctx.empty(m_total * cout * 4)
    th, tw = (h_out + 1) // 2, (w_out + 1) // 2
    defs = dict(KS=3, CIN=cin, CS=cin, NP=cout, RELU=relu, RN=rn)
    direct = ctx.kernel("network_conv.cl", "network_conv", RM=4, **defs)
    opts = ["-I", ctx.kernel_dir] + [f"-D{k}={v}" for k, v in defs.items()]
    src = (HERE / "winograd_proto.cl").read_text()
    runs = {"network_conv (RM 4)": lambda: direct(q, (cout // rn, math.ceil(m_total / 4)), None, d_x, np.int32(w_in),
                                                   d_wt, d_b, d_out, np.int32(w_out), np.int32(m_total))}
    for spec in args.blocks.split(","):
        rt, xa = (int(v) for v in spec.split("x"))
        k = cl.Program(ctx.context, src).build(options=opts + [f"-DRT={rt}", f"-DXA={xa}"]).winograd_conv3
        nq = (tw + rt - 1) // rt
        runs[f"Winograd RT {rt} XA {xa}"] = (
            lambda k=k, nq=nq: k(q, (cout // rn, nq, th), (cout // rn, 1, 1), d_x, np.int32(w_in), np.int32(h_in),
                                 d_u, d_b, d_out, np.int32(w_out), np.int32(h_out), np.int32(tw), np.int32(th)))
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
