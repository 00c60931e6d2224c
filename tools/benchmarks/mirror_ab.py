"""The right reference with SGM reading the volume mirrored (the paired
sweeps' ``mirror=True``; ``SGM(mirror_reads=True)``, the rules' choice on CPUs)
against the same pipeline mirroring the volume in place and back
(``RightReference.volume``; ``mirror_reads=False``, rule ``sgm_mirror_reads``),
in one process, calls alternating, on KITTI 2015 000000 (BENCHMARKS.md,
"The right reference reads the volume mirrored").  Both give the same bits
(checked first).

    .venv/bin/python tools/benchmarks/mirror_ab.py [cnn|census] [ROUNDS] [--data=DIR]
"""
import os
import sys
import time

import numpy as np

from _paths import data_dir  # noqa: E402
from mccnn_cl.io import read_image
from mccnn_cl.pipeline import StereoMatcher
from mccnn_cl.cli.commands import _gray
from mccnn_cl.opencl.context import ClContext
from mccnn_cl.stages.sgm import SGM


args = [a for a in sys.argv[1:] if not a.startswith("--data")]
data = next((a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--data=")),
            str(data_dir()))
L = os.path.join(data, "kitti2015", "training", "image_2", "000000_10.png")
R = L.replace("image_2", "image_3")
ga,gb=_gray(read_image(L)),_gray(read_image(R))
ctx=ClContext(None)
cost = args[0] if args else "cnn"
a=StereoMatcher(device=ctx, cost=cost); b=StereoMatcher(device=ctx, cost=cost)
a.sgm=SGM(ctx, mirror_reads=True); b.sgm=SGM(ctx, mirror_reads=False)  # whatever the device's tuned choice
assert a.sgm.reads_mirrored and not b.sgm.reads_mirrored
ra=a.compute(ga,gb); rb=b.compute(ga,gb); assert np.array_equal(ra, rb)
ta, tb = [], []
for r in range(int(args[1]) if len(args) > 1 else 6):
    for m, t in ((a, ta), (b, tb)) if r % 2 == 0 else ((b, tb), (a, ta)):
        s=time.perf_counter(); m.compute(ga,gb); t.append(time.perf_counter()-s)
    print(f"round {r}: read mirrored {ta[-1]:.3f}  explicit mirror {tb[-1]:.3f}  diff {1000*(tb[-1]-ta[-1]):+.0f} ms", flush=True)
d = np.array(tb) - np.array(ta)
print(f"{cost}: median read mirrored {np.median(ta):.3f} s, explicit {np.median(tb):.3f} s; per-round saving median {1000*np.median(d):.0f} ms, range {1000*d.min():.0f}..{1000*d.max():.0f}")
