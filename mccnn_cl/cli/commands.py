"""Bodies of ``mccnn-cl match``, ``evaluate`` and ``devices`` and the helpers
every sub-command shares (the parser and the dispatch live in :mod:`mccnn_cl.cli`).

:func:`cmd_match` writes one pair or a batch (disparity by extension, colour
picture, depth and point cloud with ``--calib``, confidence and labels);
:func:`cmd_evaluate` scores a dataset beside OpenCV SGBM; :func:`cmd_devices`
lists OpenCL devices and the choice.  The shared helpers -- :func:`_load_weights`
(weights checked before any OpenCL work), :func:`_make_matcher` (options and
``--set`` hyperparameters to a StereoMatcher), :func:`_check_outputs`,
:func:`_gray`, :func:`_tty`, :func:`_say` -- are also used by
:mod:`mccnn_cl.cli.bench` and :mod:`mccnn_cl.cli.demo`.  Bad input raises
:class:`~mccnn_cl.errors.InputError`; :func:`mccnn_cl.cli.main` turns it into
one line and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

from ..errors import InputError
from .common import (  # noqa: F401 (re-exported: the commands' helpers)
    DISPARITY_FORMATS,
    IMAGE_EXTENSIONS,
    CONFIDENCE_FORMATS,
    LABEL_FORMATS,
    PNG_MAX_DISPARITY,
    _builds_note,
    _say,
    _positive,
    _load_weights,
    _check_settings,
    _memory_limit,
    _make_matcher,
    _hyperparameters,
    _check_pair,
    _auto_output_range,
    _range_request,
    _range_text,
    _check_outputs,
    _check_png_range,
    _check_calib_size,
    _read_calibration,
    write_disparity,
    _write_depth,
    _expand,
    _side_outputs,
    _confidence_outputs,
    _save_confidence,
    _tty,
    _gray,
    _save_outputs,
)


# -- match -------------------------------------------------------------------

def cmd_match(args):
    from ..io import read_image
    _positive("--max-disp", args.max_disp)
    request = _range_request(args)
    single = args.left is not None or args.right is not None
    batch = args.left_glob is not None or args.right_glob is not None
    pairs_dir = getattr(args, "pairs_dir", None)
    batch = batch or pairs_dir is not None
    if single == batch:
        raise InputError("give either LEFT RIGHT -o OUT, or -l LEFT_GLOB -r RIGHT_GLOB (or --pairs-dir DIR) "
                         "--output-dir DIR")
    distributed = getattr(args, "workers", None) is not None or getattr(args, "scheduler", None) is not None
    if getattr(args, "split_tiles", False) and not distributed:  # it would be ignored: say so
        raise InputError("--split-tiles spreads a pair's tiles over Dask workers: give it with --workers N "
                         "or --scheduler ADDRESS")
    if batch and not distributed:
        from ..batch import run_batch
        return run_batch(args)
    if distributed:
        from ..distributed import run as run_distributed
        return run_distributed(args, single)
    calib = _read_calibration(args)  # Middlebury 2001-2006: the range only, no depth (a note)
    if single:
        if args.left is None or args.right is None or args.output is None:
            raise InputError("match needs LEFT RIGHT and -o OUT")
        if args.output_dir:
            raise InputError("--output-dir is for batches (-l/-r); use -o for one pair")
        if getattr(args, "resume", False):
            raise InputError("--resume is for batches (-l/-r or --pairs-dir)")
        jobs = [(args.left, args.right, args.output)]
    taken, inputs = {}, [f for job in jobs for f in job[:2]]
    for lp, rp, out in jobs:
        for f in (lp, rp):
            if not os.path.isfile(f):
                raise InputError(f"not a file: {f}" if os.path.exists(f) else f"file not found: {f}")
        if os.path.splitext(out)[1].lower() not in DISPARITY_FORMATS:
            raise InputError(f"{out}: output must end in {', '.join(DISPARITY_FORMATS)}")
        if request != "auto":
            lo, levels = request
            if levels is None:
                levels = calib.ndisp if (calib is not None and calib.ndisp) else 228
            _check_png_range(out, levels, lo or 0)
        color, depth, ply = _side_outputs(out, args)
        if color is not None and not color.lower().endswith((".png", ".jpg", ".jpeg", ".bmp")):
            raise InputError(f"{color}: the colour picture must be a .png/.jpg/.bmp file")
        _check_outputs([out, color, depth, ply, *_confidence_outputs(out, args)], args.force, inputs, taken)

    weights = _load_weights(args)
    from ..opencl.context import ClContext
    matchers, ctx = {}, None
    progress = None
    if batch:
        from tqdm import tqdm
        progress = tqdm(total=len(jobs), unit="pair", desc="matching", disable=None)
    try:
        for lp, rp, out in jobs:
            left_img = read_image(lp)
            right_img = read_image(rp)
            _check_calib_size(calib, left_img, lp, args.calib)
            if request == "auto":
                key, min_disp, max_disp = "auto", 0, "auto"
                _check_pair(left_img, right_img, 1, weights, (lp, rp))
            else:
                min_disp, max_disp = request
                if max_disp is None:
                    max_disp = calib.ndisp if (calib is not None and calib.ndisp) else 228
                key = (min_disp, max_disp)
                _check_pair(left_img, right_img, max_disp, weights, (lp, rp), min_disparity=min_disp)
            if key not in matchers:
                if ctx is None:
                    ctx = ClContext(args.device)
                matchers[key] = _make_matcher(args, max_disp, weights, progress=single and _tty(),
                                              ctx=ctx, min_disparity=min_disp)
            t0 = time.perf_counter()
            want = args.confidence is not None or args.labels is not None
            gray_l, gray_r = _gray(left_img), _gray(right_img)
            auto = None
            if request == "auto":
                auto = matchers[key].choose_range(gray_l, gray_r)
                lo, hi = _auto_output_range(out, auto)  # a PNG holds no negative disparity
            else:
                lo, hi = min_disp, min_disp + max_disp - 1
            range_line = _range_text(lo, hi, auto)
            if auto is not None and progress is not None:
                progress.write(f"{out}: {range_line}")
            res = matchers[key].compute(gray_l, gray_r, confidence=want,
                                        disparity_range=(lo, hi) if auto is not None else None)
            disp = res.disparity if want else res
            seconds = time.perf_counter() - t0
            if want:
                _save_confidence(out, res, args)
            _save_outputs(out, disp, left_img, args, calib, (lo, hi))  # the disparity file last
            fin = np.isfinite(disp)
            levels = f"{hi - lo + 1} disparities" if (lo == 0 and auto is None) else range_line
            msg = (f"{out}: {disp.shape[1]}x{disp.shape[0]}, {levels}, "
                   f"{fin.mean():.1%} valid, {seconds:.2f} s")
            if progress is not None:
                progress.update(1)
                if args.verbose:
                    progress.write(msg)
            else:
                _say(msg)
    finally:
        if progress is not None:
            progress.close()
    if batch:
        _say(f"wrote {len(jobs)} disparity maps to {args.output_dir}")
    _builds_note(ctx)
    return 0


# -- evaluate ----------------------------------------------------------------

def cmd_evaluate(args):
    from ..evaluation.datasets import discover
    from ..evaluation.scoring import (default_range, evaluate_pair, family_means, format_family_tables, mean_metrics,
                                      training_status)
    _positive("--max-disp", args.max_disp)
    request = _range_request(args)
    refs = discover(args.dataset_dir, args.dataset, labeled=True)  # scores need ground truth
    if args.pairs:
        wanted = [w.strip() for w in args.pairs.split(",") if w.strip()]
        def names(r):  # "Cones", "middlebury/Cones"; MiddEval3 "trainingQ/Motorcycle" also as "Motorcycle"
            return {r.name, r.key, r.name.rsplit("/", 1)[-1]}
        refs = [r for r in refs if names(r) & set(wanted)]
        found = set().union(*(names(r) for r in refs)) if refs else set()
        missing = [w for w in wanted if w not in found]
        if missing:
            raise InputError(f"pairs not found under {args.dataset_dir}: {', '.join(missing)}")
    if not refs:
        raise InputError(f"no stereo pairs with ground truth found under {args.dataset_dir}"
                         + (f" for dataset {args.dataset}" if args.dataset else ""))
    baselines = [b.strip() for b in str(args.baseline).split(",") if b.strip()]
    bad = [b for b in baselines if b not in ("sgbm", "census", "none")]
    if bad or not baselines or ("none" in baselines and len(baselines) > 1):
        raise InputError(f"--baseline: expected a comma-separated list of sgbm, census, or none; got {args.baseline!r}")
    if args.cost == "census" and "census" in baselines:  # the method itself is census: no second run
        baselines.remove("census")
    weights = _load_weights(args)
    meta = weights.meta if weights is not None else None
    from ..batch import describe_failure
    from ..errors import OpenCLError
    from ..opencl.context import ClContext
    results, failed, matchers, census, ctx = [], [], {}, {}, None
    interrupted = False
    from tqdm import tqdm
    bar = tqdm(refs, unit="pair", desc="evaluating", disable=None if not args.json else True)
    try:
        for ref in bar:
            try:
                pair = ref.load()
                if pair.disp is None:
                    bar.write(f"{pair.key}: no ground truth, skipped", file=sys.stderr)
                    continue
                stated_min, stated_levels = default_range(pair)  # the layout's range (calib.txt), else 0..227
                if request == "auto":
                    key, min_disp, max_disp = "auto", 0, "auto"
                    _check_pair(pair.left, pair.right, 1, weights, (pair.key + " left", "right"))
                else:
                    min_disp = stated_min if args.min_disp is None and args.disp_range is None else request[0]
                    max_disp = request[1] or stated_levels
                    key = (min_disp, max_disp)
                    _check_pair(pair.left, pair.right, max_disp, weights, (pair.key + " left", "right"),
                                min_disparity=min_disp)
                if key not in matchers:
                    if ctx is None:
                        ctx = ClContext(args.device)
                    matchers[key] = _make_matcher(args, max_disp, weights, ctx=ctx, min_disparity=min_disp)
                    if "census" in baselines:
                        census[key] = _make_matcher(argparse.Namespace(**{**vars(args), "cost": "census", "hyper": []}),
                                                    max_disp, None, ctx=ctx, min_disparity=min_disp)
                status = training_status(meta, pair.key, pair.name) if weights is not None else "n/a"
                base_min, base_levels = (stated_min, stated_levels) if request == "auto" else (min_disp, max_disp)
                results.append(evaluate_pair(pair, matchers[key], base_levels,
                                             baseline="sgbm" if "sgbm" in baselines else None,
                                             fill=not args.no_fill, error_maps=args.error_maps, status=status,
                                             min_disparity=base_min,
                                             others={"census": census[key]} if "census" in baselines else None))
            except (KeyboardInterrupt, SystemExit):
                raise
            except OpenCLError as exc:
                if ctx is None:  # no device at all: no pair can run (said as before, exit 1)
                    raise
                _failed(failed, ref, exc, describe_failure, bar)
            except Exception as exc:  # noqa: BLE001 - this pair fails, the others go on
                _failed(failed, ref, exc, describe_failure, bar)
    except KeyboardInterrupt:
        interrupted = True  # what was done is written, marked incomplete, then exit 130
    finally:
        bar.close()
    if not results and not failed and not interrupted:
        raise InputError("none of the pairs has ground truth")
    mean = mean_metrics(results)
    complete = not interrupted
    if args.json:
        doc = {"cost": args.cost, "weights": _weights_label(args), "fill": not args.no_fill,
               "baselines": [b for b in baselines if b != "none"], "pairs": results, "mean": mean,
               "families": family_means(results), "failed": failed, "complete": complete,
               "pairs_total": len(refs)}
        _say(json.dumps(_jsonable(doc), indent=2))
    else:
        who = f"MC-CNN ({_weights_label(args)})" if args.cost == "cnn" else "census cost + the MC-CNN stereo method"
        beside = " and ".join({"sgbm": "OpenCV SGBM", "census": "census (cens)"}[b] for b in baselines if b != "none")
        _say(f"{who}" + (f" beside {beside}" if beside else "") + "; errors in % of GT pixels, "
             + ("holes filled as the KITTI devkit does" if not args.no_fill else "holes counted as errors"))
        if results:
            _say(format_family_tables(results))
        for f in failed:
            _say(f"failed {f['pair']}: {f['reason']}")
        if failed or interrupted:
            _say(f"INCOMPLETE: {len(results)} of {len(refs)} pair(s) evaluated"
                 + (f", {len(failed)} failed" if failed else "")
                 + (", interrupted" if interrupted else "") + "; the means cover the evaluated pairs only")
        _say("training: whether the weights' metadata lists the pair as a training pair "
             "(held out = not used); n/a for --cost census")
    if interrupted:
        print("mccnn-cl: interrupted", file=sys.stderr, flush=True)
        return 130
    if failed:
        print(f"mccnn-cl: error: {len(failed)} of {len(refs)} pair(s) failed: "
              + ", ".join(f["pair"] for f in failed), file=sys.stderr, flush=True)
        return 2 if all(f["bad_input"] for f in failed) else 1
    return 0


def _failed(failed, ref, exc, describe_failure, bar):
    """A pair that failed: recorded (``pair``, ``reason``, ``bad_input``) and said on stderr."""
    reason, bad_input = describe_failure(exc)
    failed.append({"pair": ref.key, "reason": reason, "bad_input": bad_input})
    bar.write(f"{ref.key}: failed: {reason}", file=sys.stderr)


def _weights_label(args):
    if args.cost != "cnn":
        return "census cost, no network"
    return os.path.basename(args.weights) if args.weights else "shipped weights"


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, (np.floating, np.integer)):
        return _jsonable(obj.item())
    return obj


# -- devices -----------------------------------------------------------------

def cmd_devices(args):
    from ..opencl.context import list_devices, select_device
    devices = list_devices()
    chosen, reason = select_device(args.device)
    _say("OpenCL devices (P:D indices for --device / PYOPENCL_CTX), in order of preference:")
    for d in devices:
        mark = "*" if d.handle == chosen else " "
        _say(f" {mark} {d.platform_index}:{d.device_index}  {d}")
    name = next((str(d) for d in devices if d.handle == chosen), chosen.name.strip())
    _say(f"would use: {name}")
    _say(f"because:   {reason}")
    from .tune import describe_choices
    for line in describe_choices(chosen):
        _say(line)
    workers = getattr(args, "workers", None)
    if workers is not None:
        _positive("--workers", workers)
        from ..distributed import worker_device
        for i in range(workers):
            info, why = worker_device(args.device, i)
            _say(f"worker {i}: {info.platform_index}:{info.device_index}  {info}  ({why})")
    return 0
