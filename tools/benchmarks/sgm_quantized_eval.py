"""``mccnn-cl evaluate`` with SGM's inputs rounded to multiples of 1/S: what a
16-bit integer SGM (sgm_int16.py) would do to accuracy, emulated in the float
kernels (BENCHMARKS.md, "SGM in 16-bit lanes").

    QUANT_S=256 .venv/bin/python tools/benchmarks/sgm_quantized_eval.py evaluate ../shared/data \
        --dataset kitti2015 --weights kitti-fst --baseline none

Before each SGM call the cost volume is rounded in place to multiples of 1/S
(a host round trip) and the penalties P1, P2 likewise.  Float SGM on such
inputs is the integer SGM scaled by 1/S (with S a power of two every sum is
exact while |value| * S < 2^24), except that stages after SGM which read the
cost volume see the rounded costs too.  QUANT_S unset or 0: unchanged.
"""

from __future__ import annotations

import os
import sys

import numpy as np

import mccnn_cl.stages.sgm as sgm_mod

S = float(os.environ.get("QUANT_S", "0") or 0)


def _round(a):
    return np.round(a * np.float32(S)) / np.float32(S)


if S > 0:
    _table = sgm_mod.penalty_table
    _call = sgm_mod.SGM.__call__

    def penalty_table(*args, **kwargs):
        p1s, p2s = _table(*args, **kwargs)
        return tuple(np.float32(_round(p)) for p in p1s), tuple(np.float32(_round(p)) for p in p2s)

    def call(self, d_cost, d_img_left, d_img_right, D, H, W, *args, **kwargs):
        host = self.ctx.from_device(d_cost, (D, H, W))
        self.ctx.cl.enqueue_copy(self.ctx.queue, d_cost, _round(host).astype(np.float32))
        return _call(self, d_cost, d_img_left, d_img_right, D, H, W, *args, **kwargs)

    sgm_mod.penalty_table = penalty_table
    sgm_mod.SGM.__call__ = call

if __name__ == "__main__":
    from mccnn_cl.cli import main

    sys.exit(main(sys.argv[1:]))
