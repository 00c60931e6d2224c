"""``mccnn-cl adapt``: fine-tune a network to the user's own camera without ground truth.

The user's rectified pairs (``LEFT_GLOB`` / ``RIGHT_GLOB``, paired by sorted
order) are pseudo-labeled by the network itself through the whole stereo
method (left-right correct and confident pixels, :mod:`mccnn_cl.train.selftrain`),
the network is fine-tuned on them with the crop sampler, and the labels are
redrawn with the new network, ``--rounds`` times.  The output ``.npz`` keeps
the source's stereo settings and records the provenance in
``meta["training"]``.  Needs PyTorch (``pip install mccnn_cl[train]``).
Every input problem is an :class:`~mccnn_cl.errors.InputError` checked
before any training starts.
"""

from __future__ import annotations

import os
import time

from ..errors import InputError

__all__ = ["run"]


def _inputs(args):
    from .commands import _expand
    from ..io import read_image
    from ..validate import check_pair

    lefts, rights = _expand(args.left_glob, "left"), _expand(args.right_glob, "right")
    if len(lefts) != len(rights):
        raise InputError(f"{len(lefts)} left but {len(rights)} right images; they are paired by sorted "
                         "order and must be as many")
    same = set(lefts) & set(rights)
    if same:
        raise InputError(f"{sorted(same)[0]} is both a left and a right image")
    return lefts, rights, read_image, check_pair


def run(args):
    from ..models import resolve

    for name in ("rounds", "steps", "ndisp", "threads"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise InputError(f"--{name} must be >= 1, got {v}")
    if args.min_confidence is None:
        from ..train.selftrain import DEFAULT_MIN_CONFIDENCE
        args.min_confidence = DEFAULT_MIN_CONFIDENCE
    if not 0.0 <= args.min_confidence <= 1.0:
        raise InputError(f"--min-confidence must lie in [0, 1], got {args.min_confidence:g}")
    if not args.lr > 0:
        raise InputError(f"--lr must be positive, got {args.lr:g}")
    out = args.output
    if not out.lower().endswith(".npz"):
        raise InputError(f"{out}: the adapted weights are written as .npz (-o NAME.npz)")
    folder = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(folder):
        raise InputError(f"output folder does not exist: {folder}")
    if os.path.isdir(out):
        raise InputError(f"-o {out} is a folder; name the .npz file to write")
    if os.path.exists(out) and not args.force:
        raise InputError(f"{out} exists; pass --force to overwrite it")
    if str(args.weights).lower() == "census":
        raise InputError("census has no network to fine-tune; pass a network's weights "
                         "(--weights kitti-fst, a .npz, .t7 or .pt)")
    try:
        import torch
    except ImportError:
        raise InputError("mccnn-cl adapt trains with PyTorch, which is not installed "
                         "(pip install 'mccnn_cl[train]')") from None
    weights = resolve(args.weights)
    lefts, rights, read_image, check_pair = _inputs(args)
    from ..train.selftrain import UnlabeledPair, default_config, json_safe, self_train

    patch = weights.patch_size
    pairs, shapes = [], set()
    for i, (lp, rp) in enumerate(zip(lefts, rights)):
        left, right = read_image(lp), read_image(rp)
        check_pair(left, right, args.ndisp, patch, names=(lp, rp))
        name = os.path.splitext(os.path.basename(lp))[0]
        pairs.append(UnlabeledPair(name=f"{i:03d}_{name}", left=left, right=right, ndisp=int(args.ndisp)))
        shapes.add(left.shape[:2])
    if args.threads:
        torch.set_num_threads(args.threads)
        try:
            torch.set_num_interop_threads(1)
        except RuntimeError:
            pass
    print(f"adapting {args.weights} ({weights.architecture}) to {len(pairs)} pair(s), D = {args.ndisp}, "
          f"{args.rounds} round(s) x {args.steps} steps, confidence >= {args.min_confidence:g}", flush=True)
    from ..opencl.context import ClContext
    ctx = ClContext(args.device)
    cfg = default_config(weights, lr=args.lr, seed=args.seed)
    tdev = "cuda" if torch.cuda.is_available() else "cpu"
    import tempfile
    t0 = time.time()
    with tempfile.TemporaryDirectory(prefix="mccnn_adapt_") as tmp:
        w2, prov = self_train(weights, pairs, cfg, args.rounds, args.steps, args.min_confidence,
                              device=tdev, out_dir=args.run_dir or tmp, ctx=ctx,
                              source_name=str(args.weights), log=lambda *a: print(*a, flush=True))
    prov["pairs"] = [[lp, rp] for lp, rp in zip(lefts, rights)]
    prov["options"] = {k: getattr(args, k) for k in ("ndisp", "rounds", "steps", "min_confidence", "lr", "seed")}
    w2.meta["training"] = json_safe(prov)
    w2.save(out)
    print(f"wrote {out} ({time.time() - t0:.0f} s); use it with: mccnn-cl match L R -o D --weights {out} "
          f"--max-disp {args.ndisp}", flush=True)
    return 0
