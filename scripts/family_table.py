"""Per-family comparison of stereo methods on chosen pairs (docs/training.md's per-family table).

Each method is ``LABEL=SPEC``: ``sgbm`` (OpenCV StereoSGBM), ``census`` (the census cost through
the stereo method with its default settings), or a network (a shipped name, a weights ``.npz``, a
published ``.t7``/``.pt``) run with the stereo settings it carries; ``SPEC@ARCH/DATASET`` runs it
with the authors' table ``mccnn_cl.settings.AUTHORS[(ARCH, DATASET)]`` instead (e.g.
``kitti-fst@mccnn-fst/mb``), and ``SPEC[@ARCH/DATASET]+KEY=VALUE,KEY=VALUE`` overrides single
settings (e.g. ``general-fst+blur_sigma=3,cbca_iterations=2``).  Every (method, pair) result is appended to ``--out`` as one JSON line
(the :func:`mccnn_cl.evaluation.scoring.evaluate_pair` record plus ``method``), and pairs already there are
skipped, so an interrupted run continues where it stopped: each record is one write, flushed and
fsynced, and a last line left torn by a crash or a full disk is skipped with a warning (and cut off
before the next record is appended).  ``--summary`` prints the per-family
means of the records as a Markdown table (each family's metrics; seconds per pair).

    python scripts/family_table.py --data ../shared/data --pairs kitti2015/000000 'middlebury/Cloth*' \\
        --methods sgbm census kitti-fst=kitti-fst --out runs/table.jsonl
    python scripts/family_table.py --summary runs/table.jsonl
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import os
import sys
import time

import numpy as np


def _select(refs, patterns):
    return [r for r in refs if any(fnmatch.fnmatchcase(r.key, p) for p in patterns)]


class CostReuse:
    """With ``--reuse-cost``: a network's cost volume computed once per pair and copied
    into the volume buffer of every other method with the same weights on that pair, so
    that choosing among stereo settings costs the stereo method's time, not the
    network's (minutes per pair for the paper's network on a CPU).  The volume depends
    only on the weights and the images (the settings act after it), so the results are
    the same; the records say ``cost_reused`` and their seconds exclude the network."""

    def __init__(self):
        self.pair = None
        self.volumes = {}

    def for_pair(self, key):
        if key != self.pair:  # one pair's volumes at a time (a KITTI volume is ~400 MB)
            self.pair, self.volumes = key, {}

    def wrap(self, matcher, weights, ctx, rec_flag):
        import hashlib

        orig = matcher._matching_cost

        def cost(I_L, I_R, D, to_host=None, out=None, stats=None, scratch=None, rows=None):
            # rows: the network's band height under a memory limit (the same volume whatever it is)
            if to_host is not None or out is None or stats is not None:
                return orig(I_L, I_R, D, to_host=to_host, out=out, stats=stats, scratch=scratch, rows=rows)
            key = (weights, int(D), hashlib.sha1(np.ascontiguousarray(I_L).tobytes()).hexdigest(),
                   hashlib.sha1(np.ascontiguousarray(I_R).tobytes()).hexdigest())
            host = self.volumes.get(key)
            if host is not None and host.nbytes <= out.size:
                ctx.cl.enqueue_copy(ctx.queue, out, host)
                rec_flag["reused"] = True
                return out
            res = orig(I_L, I_R, D, out=out, scratch=scratch, rows=rows)
            host = np.empty(res.size, np.uint8)
            ctx.wait()
            ctx.cl.enqueue_copy(ctx.queue, host, res)
            self.volumes[key] = host
            return res

        matcher._matching_cost = cost
        return matcher


def _weights_of(spec):
    """The weights part of a network SPEC (before any @TABLE or +OVERRIDES)."""
    return spec.partition("+")[0].partition("@")[0]


def _matcher(spec, D, ctx):
    from mccnn_cl.pipeline import StereoMatcher
    from mccnn_cl.hyperparameters import parse_settings
    from mccnn_cl.settings import authors_settings
    if spec == "census":
        return StereoMatcher(max_disparity=D, cost="census", device=ctx)
    spec, _, overrides = spec.partition("+")
    weights, _, table = spec.partition("@")
    extra = {}
    if table:
        arch, ds = table.split("/")
        extra = authors_settings(arch, ds)
    extra.update(parse_settings(filter(None, overrides.split(","))))
    return StereoMatcher(max_disparity=D, weights=weights, device=ctx, **extra)


def read_records(path, repair=False):
    """The records of a JSON-lines file.  A last line that does not parse (torn by a crash or a
    full disk mid-write) is skipped with a warning on stderr; with ``repair`` it is also cut off
    and the file made to end with a newline, so that the next record starts a line of its own.
    An unreadable line before the last is an error naming the file and line (not a torn write)."""
    with open(path, "rb") as f:
        data = f.read()
    chunks = data.split(b"\n")
    lines = [c + b"\n" for c in chunks[:-1]] + ([chunks[-1]] if chunks[-1] else [])
    recs, end = [], 0  # end: bytes of the whole, readable lines
    for i, line in enumerate(lines, start=1):
        if line.strip():
            try:
                recs.append(json.loads(line))
            except ValueError as exc:
                if i < len(lines):
                    sys.exit(f"error: {path}, line {i}: not a JSON record ({exc}); only a last line "
                             "torn by a crash is skipped")
                print(f"warning: {path}, line {i}: the last record is unreadable ({len(line)} bytes, torn by "
                      f"a crash or a full disk?): skipped" + (" and cut off" if repair else ""),
                      file=sys.stderr, flush=True)
                break
        end += len(line)
    if repair and (end != len(data) or (data and not data.endswith(b"\n"))):
        with open(path, "r+b") as f:
            f.truncate(end)
            if end and not data[:end].endswith(b"\n"):
                f.seek(end)
                f.write(b"\n")  # a whole last record written without its newline
            f.flush()
            os.fsync(f.fileno())
    return recs


def append_record(path, rec) -> None:
    """One record as one line: one write, flushed and fsynced."""
    line = (json.dumps(rec, default=float) + "\n").encode()
    with open(path, "ab") as f:
        f.write(line)
        f.flush()
        os.fsync(f.fileno())


def run(args):
    from mccnn_cl.opencl.context import ClContext
    from mccnn_cl.evaluation.datasets import discover
    from mccnn_cl.evaluation.scoring import default_max_disparity, evaluate_pair
    refs = _select(discover(args.data, labeled=True), args.pairs)
    if not refs:
        sys.exit(f"error: no pair under {args.data} matches {args.pairs}")
    done = set()
    if os.path.exists(args.out):
        for r in read_records(args.out, repair=True):
            done.add((r["method"], r["pair"]))
    ctx = ClContext(args.device)
    reuse = CostReuse() if args.reuse_cost else None
    methods = [m.partition("=") for m in args.methods]
    methods = [(lab, spec or lab) for lab, _, spec in methods]
    for ref in refs:
        pair = None
        for label, spec in methods:
            if (label, ref.key) in done:
                continue
            pair = pair or ref.load()
            D = default_max_disparity(pair)
            t0 = time.time()
            flag = {}
            if spec == "sgbm":
                rec = evaluate_pair(pair, None, D, baseline="sgbm")
            else:
                m = _matcher(spec, D, ctx)
                if reuse is not None and spec != "census":
                    reuse.for_pair(ref.key)
                    m = reuse.wrap(m, _weights_of(spec), ctx, flag)
                rec = evaluate_pair(pair, m, D, baseline=None)
                rec["methods"] = {"sgbm" if k == "sgbm" else "method": v for k, v in rec["methods"].items()}
            (res,) = rec["methods"].values()
            rec.update(method=label, spec=spec, result=res)
            if flag.get("reused"):
                rec["cost_reused"] = True
            del rec["methods"]
            append_record(args.out, rec)
            print(f"{time.strftime('%H:%M:%S')} {label:<14} {ref.key:<36} D={D:<4} "
                  f"bad1 {res['bad1_all']:.2f} bad2 {res['bad2_all']:.2f} bad3 {res['bad3_all']:.2f} "
                  f"({res['seconds']:.1f} s, {time.time() - t0:.0f} s with loading)", flush=True)


def summary(paths, held_only_of=None, methods=None):
    from mccnn_cl.evaluation.scoring import FAMILY_METRICS
    recs = {}
    for path in paths:
        for r in read_records(path):
            recs[(r["method"], r["pair"])] = r  # the last record of a (method, pair) wins
    order = methods or list(dict.fromkeys(m for m, _ in recs))
    fams = {}
    for (m, p), r in recs.items():
        fams.setdefault(r["dataset"], {}).setdefault(m, []).append(r)
    out = []
    for ds, by_m in fams.items():
        keys = FAMILY_METRICS[ds]
        pairs = sorted({r["pair"] for rs in by_m.values() for r in rs})
        out.append(f"\n**{ds}** ({len(pairs)} pairs: {', '.join(p.split('/', 1)[1] for p in pairs)})\n")
        out.append("| method | " + " | ".join(keys) + " | s / pair | pairs |")
        out.append("|---" * (len(keys) + 3) + "|")
        for m in order:
            rs = [r for r in by_m.get(m, []) if r["pair"] in pairs]
            if not rs:
                continue
            cells = []
            for k in keys:
                v = [r["result"][k] for r in rs if r["result"].get(k) is not None and not math.isnan(r["result"][k])]
                cells.append(f"{np.mean(v):.2f}" if v else "–")
            sec = np.mean([r["result"]["seconds"] for r in rs])
            out.append(f"| {m} | " + " | ".join(cells) + f" | {sec:.1f} | {len(rs)}{'' if len(rs) == len(pairs) else ' (incomplete)'} |")
    return "\n".join(out)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default="../shared/data")
    p.add_argument("--pairs", nargs="+", default=["*"], help="pair keys or shell patterns")
    p.add_argument("--methods", nargs="+", default=["sgbm", "census"], help="LABEL=SPEC (see the module doc)")
    p.add_argument("--out", help="JSON-lines file to append to")
    p.add_argument("--device", default=None)
    p.add_argument("--reuse-cost", action="store_true",
                   help="compute a network's cost volume once per pair for all methods with the same weights "
                        "(settings candidates; their seconds then exclude the network)")
    p.add_argument("--summary", nargs="+", metavar="JSONL", help="print per-family means of these files")
    p.add_argument("--order", nargs="+", help="--summary: methods in this order")
    args = p.parse_args(argv)
    if args.summary:
        print(summary(args.summary, methods=args.order))
        return 0
    if not args.out:
        p.error("--out is required")
    run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
