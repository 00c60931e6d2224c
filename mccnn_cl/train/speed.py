"""Training throughput of the patch sampler vs the crop sampler, same network, same machine.

``python -m mccnn_cl.train.speed --data DIR --arch fst --seconds 20``: for each
configuration, runs SGD steps (sampling, forward, backward, update, as the
training loop does) for about ``--seconds`` after two warm-up steps, in one
process, alternating the configurations ``--rounds`` times (this machine's
speed drifts between minutes), and prints examples/s per configuration
(an example = one positive or one negative pair).  Configurations: the patch
sampler at batch 128 and at a batch the size of a crop step, the crop sampler
at ``--crops-per-step`` crops with 1 and with ``--negatives`` negatives per GT
pixel (integer mode, no augmentation, so the crop examples are exactly the
patch sampler's kind).  The patch sampler cuts consecutive batches from one
epoch plan, as in training.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from mccnn_cl.evaluation.datasets import discover

from .crops import CropSampler, crop_loss
from .model import MCCNN
from .patches import PatchSampler
from .train import ARCH_DEFAULTS, ARCHS


class _Plan:
    """An epoch plan cut into consecutive batches, as the training loop uses it (re-planned when spent)."""

    def __init__(self, sampler, rng, n=200_000):
        self.sampler, self.rng, self.n, self.plan, self.pos = sampler, rng, n, None, 0

    def next(self, half):
        if self.plan is None or self.pos + half > len(self.plan[0]):
            self.plan, self.pos = self.sampler.epoch(self.rng, n_locations=self.n), 0
        self.pos += half
        return self.sampler.batch(self.plan, self.pos - half, self.pos)


def _patch_step(model, opt, plan, half, rng):
    b = plan.next(half)
    out = model(torch.from_numpy(b.left), torch.from_numpy(b.right))
    loss = model.loss(out[:half], out[half:])
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return 2 * half


def _crop_step(model, opt, sampler, n_crops, rng):
    cb = sampler.sample(rng, n_crops)
    loss = crop_loss(model, cb, "cpu")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return cb.n * (1 + sampler.negatives)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mccnn_cl.train.speed", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--include", default="kitti")
    ap.add_argument("--arch", choices=list(ARCHS), default="fst")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--crops-per-step", type=int, default=2)
    ap.add_argument("--crop", type=int, nargs=2, default=[47, 47])
    ap.add_argument("--negatives", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    pairs = [r.load() for root in args.data for r in discover(root, labeled=True) if r.key.startswith(args.include)]
    pairs = [p for p in pairs if p.disp is not None][:4]
    d = ARCH_DEFAULTS[args.arch]
    torch.manual_seed(0)
    model = MCCNN(d["conv_layers"], d["fc_layers"], architecture=ARCHS[args.arch]).he_init_()
    opt = torch.optim.SGD(model.parameters(), lr=1e-4, momentum=0.9)
    ps = PatchSampler(pairs, patch_size=model.patch_size, n_lo=d["n_lo"], n_hi=d["n_hi"], p_hi=d["p_hi"])
    crops = {k: CropSampler(pairs, model.patch_size, p_hi=d["p_hi"], n_lo=d["n_lo"], n_hi=d["n_hi"],
                            crop=tuple(args.crop), spread=32, negatives=k) for k in (1, args.negatives)}
    rng = np.random.default_rng(0)
    plan = _Plan(ps, rng)
    plan.next(64)  # the first plan is drawn outside the timing
    per_crop_step = np.mean([_crop_step(model, opt, crops[1], args.crops_per_step, rng) for _ in range(3)])
    big = int(per_crop_step // 2)
    configs = {"patch, batch 128": lambda: _patch_step(model, opt, plan, 64, rng),
               f"patch, batch {2 * big}": lambda: _patch_step(model, opt, plan, big, rng),
               f"crop, {args.crops_per_step} crops/step, 1 negative": lambda: _crop_step(
                   model, opt, crops[1], args.crops_per_step, rng),
               f"crop, {args.crops_per_step} crops/step, {args.negatives} negatives": lambda: _crop_step(
                   model, opt, crops[args.negatives], args.crops_per_step, rng)}
    totals = {k: [0, 0.0] for k in configs}
    for _ in range(args.rounds):
        for name, step in configs.items():
            step()
            step()
            t0, n = time.perf_counter(), 0
            while time.perf_counter() - t0 < args.seconds / args.rounds:
                n += step()
            totals[name][0] += n
            totals[name][1] += time.perf_counter() - t0
    res = {k: round(n / t) for k, (n, t) in totals.items()}
    base = res["patch, batch 128"]
    print(json.dumps({"arch": args.arch, "threads": args.threads, "examples_per_s": res,
                      "speedup_vs_patch_128": {k: round(v / base, 1) for k, v in res.items()}}, indent=1))
    return 0


if __name__ == "__main__":
    from ..cli import run_entry_point  # a reader of stdout gone: exit 141, quietly

    raise SystemExit(run_entry_point(main))
