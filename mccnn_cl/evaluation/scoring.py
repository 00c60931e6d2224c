"""Evaluation of MC-CNN beside OpenCV StereoSGBM on datasets with ground truth.

Used by ``mccnn-cl evaluate``.  For each pair: run the matcher (and the
baseline) on the gray images with the same disparity range, compute the
metrics of :mod:`mccnn_cl.evaluation.metrics` and optionally write error maps.

Both methods are scored the same way: their raw output's density is
reported, and the error rates are computed on the map filled the way the
KITTI devkit fills sparse submissions (:func:`~mccnn_cl.evaluation.metrics.fill_invalid`),
so a method is not rewarded or punished for leaving pixels out
(``fill=False`` counts every missing pixel as an error instead).
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from . import metrics
from .baseline import sgbm
from .datasets import DATASETS, dataset_of, scene_family, to_gray_u8

__all__ = ["training_pairs", "training_status", "default_max_disparity", "default_range", "evaluate_pair",
           "mean_metrics", "format_table", "family_means", "format_family_tables", "FAMILY_METRICS",
           "KITTI_DEFAULT_DISPARITY"]

#: The metrics each dataset family is judged by (keys of a method's result; the headline first).
FAMILY_METRICS = {
    "kitti": ("bad3_noc", "bad3_all", "d1_all"),
    "middlebury": ("bad2_noc", "bad2_all"),
    "middeval3": ("bad2_noc", "bad2_all"),
    "eth3d": ("bad1_noc", "bad1_all", "bad2_noc", "bad2_all"),
}

KITTI_DEFAULT_DISPARITY = 228

# Keys of Weights.meta["training"] that may list the pairs used for training
# and those held out (the training script records them; names or kind/name keys).
_TRAIN_KEYS = ("pairs", "train_pairs", "training_pairs", "trained_on")
_HELD_KEYS = ("held_out", "heldout", "validation_pairs", "val_pairs", "test_pairs")


def _names(value):
    if value is None:
        return None
    if isinstance(value, dict) and (all("/" in str(k) for k in value)
                                    or not all(isinstance(v, (list, tuple, str)) for v in value.values())):
        # train.py: {"kitti2015/000001": examples, ...}; converted networks: {"kitti2012/000000": {...}}
        # or, in older files, a description string per pair key
        return {str(k) for k in value}
    if isinstance(value, dict):  # {"kitti2015": ["000001"], "middlebury": [...]}
        out = set()
        for kind, names in value.items():
            for n in (names if isinstance(names, (list, tuple)) else [names]):
                out.add(f"{kind}/{n}")
        return out
    if isinstance(value, str):
        return {value}
    return {str(v) for v in value}


def training_pairs(meta: dict | None):
    """``(trained, held_out)``: sets of pair names/keys from ``Weights.meta["training"]``, or None."""
    info = (meta or {}).get("training")
    if not isinstance(info, dict):
        return None, None
    trained = held = None
    for k in _TRAIN_KEYS:
        if k in info:
            trained = _names(info[k])
            break
    for k in _HELD_KEYS:
        if k in info:
            held = _names(info[k])
            break
    return trained, held


def _match(names, pair_key, pair_name):
    if not names:
        return False
    for n in names:
        n = str(n).replace("\\", "/")
        if n == pair_key or n == pair_name or n.endswith("/" + pair_key) \
                or (n.rsplit("/", 1)[-1] == pair_name and pair_key.split("/")[0] in n):
            return True
    return False


def training_status(meta, pair_key: str, pair_name: str) -> str:
    """"trained", "held out" or "unknown" (the weights do not say) for one pair.

    Trained wins: a run may hold out a pair that the weights it started from
    (``--init``, counted in ``trained_on``) were trained on; such a pair is
    not held out of the network."""
    trained, held = training_pairs(meta)
    if _match(trained, pair_key, pair_name):
        return "trained"
    if _match(held, pair_key, pair_name):
        return "held out"
    return "unknown" if trained is None else "held out"


def default_max_disparity(pair) -> int:
    """The pair's ``ndisp`` (Middlebury calib.txt) if known, else 228 (the paper's KITTI range)."""
    return int(pair.ndisp) if pair.ndisp else KITTI_DEFAULT_DISPARITY


def default_range(pair) -> tuple:
    """``(M, D)``: disparities M .. M+D-1 covering what the layout states: 0 ..
    :func:`default_max_disparity` - 1, widened to the calib.txt's ``vmin`` /
    ``vmax`` (``pair.disp_range``) where they reach outside it (e.g. negative
    disparities)."""
    levels = default_max_disparity(pair)
    stated = getattr(pair, "disp_range", None)
    if not stated:
        return 0, levels
    lo = min(0, math.floor(stated[0]))
    hi = max(levels - 1, math.ceil(stated[1]))
    return lo, hi - lo + 1


def _score(pred, pair, fill):
    scored = metrics.fill_invalid(pred) if fill else pred
    out = metrics.evaluate_disparity(scored, pair.disp, pair.valid_noc, pair.valid_all)
    # ETH3D's headline metric: bad-1.0
    out["bad1_all"] = metrics.middlebury_bad(scored, pair.disp, pair.valid_all, threshold=1.0)
    out["bad1_noc"] = (metrics.middlebury_bad(scored, pair.disp, pair.valid_noc & pair.valid_all, threshold=1.0)
                       if pair.valid_noc is not None else float("nan"))
    out["density"] = metrics.density(pred)
    return out


def evaluate_pair(pair, matcher, max_disparity, baseline="sgbm", fill=True, error_maps=None,
                  status="unknown", min_disparity=0, others=None) -> dict:
    """Metrics of one :class:`~mccnn_cl.evaluation.datasets.StereoPair` for ``matcher`` and the baseline.

    ``matcher`` is an object with ``compute(left, right)`` returning the
    left disparity map (e.g. :class:`mccnn_cl.pipeline.StereoMatcher`), or
    None (only the baseline and ``others``); ``others``: more such matchers
    by method name (e.g. ``{"census": StereoMatcher(cost="census", ...)}``);
    ``error_maps`` is a folder for ``<kind>_<name>_<method>_err.png``.
    Returns a JSON-ready dict: pair, dataset, family, size, max_disparity,
    disparity_range, training, and per method the metrics plus ``seconds``.
    ``min_disparity``: the range's M (the baseline's too).  A matcher with
    ``max_disparity="auto"`` chooses its range (``matcher``'s is the one in
    ``disparity_range``; the coarse pass counts in its seconds), the
    baseline searches M .. M + max_disparity - 1.
    """
    left, right = to_gray_u8(pair.left), to_gray_u8(pair.right)
    result = {"pair": pair.key, "dataset": dataset_of(pair.key), "family": scene_family(pair.key),
              "size": [int(left.shape[1]), int(left.shape[0])],
              "max_disparity": int(max_disparity), "training": status, "methods": {},
              "disparity_range": [int(min_disparity), int(min_disparity + max_disparity - 1)]}
    maps = {}
    for name, m in ([("mccnn", matcher)] if matcher is not None else []) + list((others or {}).items()):
        t0 = time.perf_counter()
        if getattr(m, "auto_range", False):
            lo, hi = m.choose_range(left, right)["range"]
            if name == "mccnn":
                result["disparity_range"], result["auto"] = [lo, hi], True
                result["max_disparity"] = hi - lo + 1
            ours = np.asarray(m.compute(left, right, disparity_range=(lo, hi)), dtype=np.float32)
        else:
            ours = np.asarray(m.compute(left, right), dtype=np.float32)
        seconds = time.perf_counter() - t0
        maps[name] = ours
        result["methods"][name] = dict(_score(ours, pair, fill), seconds=seconds)
    if baseline == "sgbm":
        base, seconds = sgbm(left, right, max_disparity, return_time=True, min_disparity=min_disparity)
        maps["sgbm"] = base
        result["methods"]["sgbm"] = dict(_score(base, pair, fill), seconds=seconds)
    if error_maps:
        from ..io import write_image
        from ..visualize import error_image
        os.makedirs(error_maps, exist_ok=True)
        for method, pred in maps.items():
            scored = metrics.fill_invalid(pred) if fill else pred
            stem = f"{pair.kind}_{pair.name}".replace("/", "_").replace(os.sep, "_")
            path = os.path.join(error_maps, f"{stem}_{method}_err.png")
            thr = {"kitti": 3.0, "eth3d": 1.0}.get(dataset_of(pair.key), 2.0)
            write_image(path, error_image(scored, pair.disp, thr))
    return result


def metric_counts(results) -> dict:
    """Per method, how many pairs each metric's mean covers (:func:`mean_metrics` skips NaN
    entries: a pair without a non-occluded mask has no ``*_noc`` figure)."""
    out = {}
    for r in results:
        for m, row in r["methods"].items():
            c = out.setdefault(m, {})
            for k, v in row.items():
                c[k] = c.get(k, 0) + int(v is not None and not math.isnan(v))
    return out


def mean_metrics(results) -> dict:
    """Per method, the mean of every metric over the pairs (NaN entries skipped: the pairs each
    mean covers are :func:`metric_counts`)."""
    out = {}
    methods = sorted({m for r in results for m in r["methods"]}, key=lambda m: m != "mccnn")
    for m in methods:
        rows = [r["methods"][m] for r in results if m in r["methods"]]
        keys = list(rows[0])
        mean = {}
        for k in keys:
            vals = [row[k] for row in rows if row.get(k) is not None and not math.isnan(row[k])]
            mean[k] = float(np.mean(vals)) if vals else float("nan")
        out[m] = mean
    return out


_COLUMNS = [("bad3_noc", "3px-noc"), ("bad3_all", "3px-all"), ("d1_all", "D1-all"),
            ("bad2_noc", "bad2-noc"), ("bad2_all", "bad2-all"), ("epe_all", "EPE px"),
            ("density", "dens. %"), ("seconds", "time s")]
_SHORT = {"mccnn": "ours", "sgbm": "sgbm", "census": "cens"}
_TITLES = {"bad3_noc": "3px-noc", "bad3_all": "3px-all", "d1_all": "D1-all", "bad2_noc": "bad2-noc",
           "bad2_all": "bad2-all", "bad1_noc": "bad1-noc", "bad1_all": "bad1-all", "epe_all": "EPE px",
           "density": "dens. %", "seconds": "time s"}
_FAMILY_NAMES = {"kitti": "KITTI (3-px error, D1)", "middlebury": "Middlebury (bad-2.0)",
                 "middeval3": "MiddEval3 (bad-2.0)", "eth3d": "ETH3D two-view (bad-1.0, bad-2.0)"}
_METHOD_ORDER = ("mccnn", "sgbm", "census")


def _fmt(v, key, width=5):
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    for digits in ((1, 0) if key == "density" else (2, 1, 0)):  # as many decimals as fit
        text = f"{v:.{digits}f}"
        if len(text) <= width:
            return text
    return text


def format_table(results, mean=None, columns=None, extra_means=()) -> str:
    """A plain-text table: one row per pair (and the mean), each metric with MC-CNN and SGBM side by side.

    ``columns``: metric keys to show (default: the KITTI and Middlebury ones, EPE, density, time);
    ``extra_means``: more ``(label, mean)`` rows after the mean (e.g. the held-out pairs' mean).
    """
    methods = [m for m in _METHOD_ORDER if any(m in r["methods"] for r in results)]
    cols = _COLUMNS if columns is None else [(k, _TITLES[k]) for k in columns]
    name_w = max([len("pair")] + [len(r["pair"]) for r in results] + [len("mean")]
                 + [len(label) for label, _ in extra_means])
    cell = 5
    group = len(methods) * (cell + 1) - 1
    def shown(r):  # the range searched: D levels from 0, else MIN..MAX
        rng = r.get("disparity_range")
        return f"{rng[0]}..{rng[1]}" if rng and (rng[0] != 0 or r.get("auto")) else str(r["max_disparity"])

    dw = max([4] + [len(shown(r)) for r in results])
    head1 = f"{'':<{name_w}}  {'D':>{dw}}  {'training':<8}"
    head2 = f"{'pair':<{name_w}}  {'':>{dw}}  {'':<8}"
    for _, title in cols:
        head1 += "  " + f"{title:^{group}}"
        head2 += "  " + " ".join(f"{_SHORT[m]:>{cell}}" for m in methods)
    lines = [head1, head2, "-" * len(head2)]

    def row(label, d, status, per_method):
        s = f"{label:<{name_w}}  {d:>{dw}}  {status:<8}"
        for key, _ in cols:
            s += "  " + " ".join(f"{_fmt(per_method.get(m, {}).get(key), key, cell):>{cell}}" for m in methods)
        return s

    for r in results:
        lines.append(row(r["pair"], shown(r), r["training"], r["methods"]))
    if mean is not None and len(results) > 1:
        lines.append("-" * len(head2))
        lines.append(row("mean", "", "", mean))
    for label, m in extra_means:
        lines.append(row(label, "", "", m))
    if mean is not None and len(results) > 1:  # say which means cover fewer pairs than the rows
        counts = metric_counts(results)
        short = sorted({(title, n) for key, title in cols for m in methods
                        if 0 < (n := counts.get(m, {}).get(key, 0)) < len(results)})
        if short:
            lines.append("(" + "; ".join(f"{title}: over the {n} of {len(results)} pairs that have it"
                                         for title, n in short) + ")")
    return "\n".join(lines)


def family_means(results) -> dict:
    """Per dataset family (kitti, middlebury, middeval3, eth3d) found in ``results``: the number of
    pairs, the per-method means over all of them (``mean``; ``mean_pairs``: how many pairs
    each metric's mean covers, fewer where a pair lacks it, e.g. a non-occluded mask) and over
    the held-out ones (``mean_held_out``, absent when none is held out)."""
    out = {}
    for ds in DATASETS:
        rows = [r for r in results if r.get("dataset", dataset_of(r["pair"])) == ds]
        if not rows:
            continue
        held = [r for r in rows if r["training"] == "held out"]
        out[ds] = {"pairs": len(rows), "held_out": len(held), "metrics": list(FAMILY_METRICS[ds]),
                   "mean": mean_metrics(rows), "mean_pairs": metric_counts(rows)}
        if held:
            out[ds]["mean_held_out"] = mean_metrics(held)
    return out


def format_family_tables(results) -> str:
    """One table per dataset family with that family's metrics (all and non-occluded), the pairs'
    training status and the family mean (and the held-out pairs' mean when some are trained on)."""
    blocks = []
    fam = family_means(results)
    for ds, info in fam.items():
        rows = [r for r in results if r.get("dataset", dataset_of(r["pair"])) == ds]
        cols = list(FAMILY_METRICS[ds]) + ["density", "seconds"]
        extra = ([("mean held out", info["mean_held_out"])]
                 if 0 < info["held_out"] < info["pairs"] and len(rows) > 1 else [])
        text = format_table(rows, info["mean"] if len(rows) > 1 else None, columns=cols, extra_means=extra)
        blocks.append(f"{_FAMILY_NAMES[ds]}: {info['pairs']} pair(s), {info['held_out']} held out\n{text}")
    return "\n\n".join(blocks)
