"""Per-stage times on each OpenCL implementation (PoCL, Intel's CPU runtime), one table.

Full-size measurement (run it on an idle machine; about 10-12 minutes on 2
idle cores: per implementation the network ~250 s on PoCL, the stereo
stages ~6 s, bench_aggregation ~30 s; Intel's network time is whatever it
turns out to be, the reason to run this):

    .venv/bin/python tools/benchmarks/run_runtimes.py --json runtimes.json

The paper network's table (BENCHMARKS.md) names its weights:

    .venv/bin/python tools/benchmarks/run_runtimes.py --weights <models>/<paper network> --json runtimes.json

Without the network (stereo stages on the census cost; about 2 minutes):

    .venv/bin/python tools/benchmarks/run_runtimes.py --cost census

Quick check of the driver (tiny synthetic pair, ~1 minute):

    .venv/bin/python tools/benchmarks/run_runtimes.py --quick

For each implementation (``--impls``, default ``pocl,intel``) it gets the
environment from ``bash scripts/opencl_impls.sh --env IMPL`` (which installs
the implementation if missing: PoCL with apt, Intel's runtime with pip into
.venv) so that ``OCL_ICD_VENDORS`` names exactly that implementation's ICD,
checks that the device the tools report belongs to it, and runs

1. ``mccnn-cl bench -v`` on KITTI 2015 training 000000 (1242 x 375) with
   D = 228 (``--quick``: a synthetic 310 x 94 pair, D = 32), with
   ``--weights`` when given (default: bench's own, the shipped model).  With
   the network cost (``--cost cnn``, the default) the bench runs with
   ``--no-warmup``, because its warm-up would run the ~4-minute network once
   more; instead two runs on the same pair go first: the census pipeline
   with the same D (with its own warm-up, then timed, best of 3: the stereo
   stages in steady state, reported as "census bench"; the network run is a
   matcher's first call, whose stereo stages also map fresh volume pages)
   and, untimed, the network with D = 1.  These fill PyOpenCL's binary
   cache, but compilation is not wholly kept out of the timed run: it is a
   matcher's first call in a fresh process, so the programs the stages make
   lazily are made inside it (from that cache: 2 programs, 0.07 s, in a
   ``--quick`` run on PoCL), and a runtime may still compile a kernel on
   its first launch at a work-group size it has not cached (PoCL).  bench
   prints the seconds it spent making programs during its timed runs
   ("programs made during the timed runs"), kept in the JSON's raw output.
2. ``tools/benchmarks/bench_aggregation.py`` on a random 228 x 376 x 1240
   volume (``--quick``: 32 x 94 x 310).

and prints one table, stage x implementation, in seconds (``--json``: the
same figures, bench's in-run baselines and load averages, and each tool's
raw output).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from _paths import REPO, data_dir  # noqa: E402
DATA = data_dir()
KITTI = DATA / "kitti2015" / "training"

# What each implementation's device description must contain (isolation check).
EXPECT = {"pocl": "Portable Computing Language", "intel": "Intel(R) OpenCL", "rusticl": "rusticl",
          "oclgrind": "Oclgrind"}

# mccnn-cl bench summary lines: "<label>   <seconds>   <share>%" (share optional).
BENCH_LINE = re.compile(r"^(?P<label>\S.*?)\s{2,}(?P<sec>\d+\.\d+)(?:\s+\d+\.\d+%)?$")
# mccnn-cl bench -v per-stage lines: "  <name>   <seconds>".
RAW_LINE = re.compile(r"^  (?P<label>\S+)\s+(?P<sec>\d+\.\d+)$")
# bench_aggregation.py lines: "<label>   <ms> ms ..." (first number followed by " ms").
# The CBCA kind is padded ("multi    ", "workgroup").
AGG_LINE = re.compile(r"^(?P<label>buffer copy|cross arms \(x2\)|CBCA 4 it \(max_arm=\s*\d+(?:, [\w-]+\s*)?\)|"
                      r"SGM 4 directions)"
                      r"\s+(?P<ms>\d+\.\d+) ms")
# mccnn-cl bench's baseline lines: "  <what>: <before> / <after> <unit>, using ...".
BASELINE_LINE = re.compile(r"^  (?P<what>host CPU numpy float32 GEMM|device buffer copy)[^:]*(?:\([^)]*\))?[^:]*: "
                           r"(?P<before>\d+\.\d+) / (?P<after>\d+\.\d+) (?P<unit>GFLOP/s|GB/s)")
LOAD_LINE = re.compile(r"^host: (?P<cores>\d+) cores, load average \(1 min\) (?P<start>[\d.]+|unknown) at the start, "
                       r"(?P<end>[\d.]+|unknown) at the end")


def impl_env(impl):
    """Environment isolating ``impl`` (installs it if missing, via scripts/opencl_impls.sh)."""
    out = subprocess.run(["bash", str(REPO / "scripts" / "opencl_impls.sh"), "--env", impl],
                         capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"scripts/opencl_impls.sh --env {impl} failed (exit {out.returncode}):\n{out.stderr}")
    env = dict(os.environ)
    env.pop("PYOPENCL_CTX", None)  # the one implementation's default device
    for line in out.stdout.split():
        key, _, value = line.partition("=")
        env[key] = value
    if "OCL_ICD_VENDORS" not in env:
        sys.exit(f"scripts/opencl_impls.sh --env {impl} printed no OCL_ICD_VENDORS:\n{out.stdout}")
    env["PYTHONWARNINGS"] = "ignore::UserWarning"  # PyOpenCL's "non-empty compiler output" noise
    return env


def run(cmd, env, impl):
    """Run ``cmd``; return its stdout (exit on failure, showing the output).
    Checks that the device line names ``impl``'s implementation."""
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=REPO)
    wall = time.perf_counter() - t0
    text = p.stdout + p.stderr
    if p.returncode != 0:
        sys.exit(f"[{impl}] {' '.join(cmd)} failed (exit {p.returncode}):\n{text}")
    dev = next((ln for ln in text.splitlines() if ln.startswith("device:")), None)
    if dev is None or EXPECT.get(impl, "") not in dev:
        sys.exit(f"[{impl}] expected a device of '{EXPECT.get(impl)}', the tool reported {dev!r}:\n{text}")
    print(f"[{impl}] {wall:6.1f} s  {' '.join(Path(c).name if i == 0 else c for i, c in enumerate(cmd))}",
          flush=True)
    return text, dev.split("device:", 1)[1].split(";")[0].strip()


def parse_bench(text):
    """{label: seconds} from ``mccnn-cl bench -v`` (summary rows, then the raw stages as 'stage X')."""
    rows = {}
    for ln in text.splitlines():
        m = RAW_LINE.match(ln)
        if m:
            rows[f"stage {m['label']}"] = float(m["sec"])
            continue
        m = BENCH_LINE.match(ln)
        if m and not ln.startswith("cost volume"):
            rows[m["label"]] = float(m["sec"])
    if not any(k.startswith("total") for k in rows):
        sys.exit(f"could not read the stage times from mccnn-cl bench's output:\n{text}")
    return rows


def parse_baselines(text):
    """bench's in-run baselines and load: {"host CPU numpy GEMM (GFLOP/s)": [before, after],
    "device buffer copy (GB/s, read + write)": [before, after], "load average (1 min)": [start, end],
    "cores": N, "warnings": [...]} (the GEMM only where bench measured it: a CPU device and the network)."""
    out = {"warnings": [ln for ln in text.splitlines() if ln.startswith("warning:")]}
    for ln in text.splitlines():
        m = BASELINE_LINE.match(ln)
        if m:
            key = ("host CPU numpy GEMM (GFLOP/s)" if m["what"].startswith("host")
                   else "device buffer copy (GB/s, read + write)")
            out[key] = [float(m["before"]), float(m["after"])]
            continue
        m = LOAD_LINE.match(ln)
        if m:
            out["cores"] = int(m["cores"])
            out["load average (1 min)"] = [None if v == "unknown" else float(v) for v in (m["start"], m["end"])]
    return out


def parse_aggregation(text):
    """{label: seconds} from tools/benchmarks/bench_aggregation.py."""
    rows = {}
    for ln in text.splitlines():
        m = AGG_LINE.match(ln)
        if m:
            label = re.sub(r"\s+", " ", m["label"]).replace("= ", "=").replace(" )", ")")
            rows[label] = float(m["ms"]) / 1e3
    if not any(k.startswith("SGM") for k in rows):
        sys.exit(f"could not read the times from bench_aggregation.py's output:\n{text}")
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--impls", default="pocl,intel", help="comma-separated: pocl,intel (also rusticl, oclgrind)")
    ap.add_argument("--cost", choices=("cnn", "census"), default="cnn",
                    help="matching cost of the mccnn-cl bench run (cnn: the network, ~4 min at full size)")
    ap.add_argument("--weights", default=None, metavar="FILE",
                    help="network weights for the mccnn-cl bench runs with the network (a file or a shipped "
                         "model's name; default: bench's, the shipped model)")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs of each tool (the best is kept)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes: a check of this driver, not a measurement")
    ap.add_argument("--json", default=None, help="write the figures and raw outputs to this JSON file")
    args = ap.parse_args(argv)
    impls = [s for s in args.impls.split(",") if s]
    if args.weights and args.cost != "cnn":
        ap.error("--weights is for --cost cnn")
    weights = ["--weights", args.weights] if args.weights else []
    unknown = [i for i in impls if i not in EXPECT]
    if unknown:
        ap.error(f"unknown implementation(s): {', '.join(unknown)}")
    py = sys.executable
    D = 32 if args.quick else 228
    if args.quick:
        pair = ["--size", "310x94"]
        agg = ["--H", "94", "--W", "310", "--D", str(D)]
        what = f"synthetic 310 x 94, D = {D}; aggregation volume {D} x 94 x 310 (--quick)"
    else:
        left, right = KITTI / "image_2" / "000000_10.png", KITTI / "image_3" / "000000_10.png"
        if not (left.exists() and right.exists()):
            sys.exit(f"KITTI 2015 000000 not found under {KITTI} (set MCCNN_DATA)")
        pair = ["--left", str(left), "--right", str(right)]
        agg = ["--H", "376", "--W", "1240", "--D", str(D)]
        what = f"KITTI 2015 000000 (1242 x 375), D = {D}; aggregation volume {D} x 376 x 1240"
    bench = [py, "-m", "mccnn_cl", "bench", "-v", "--max-disp", str(D), "--cost", args.cost,
             "--repeat", str(args.repeat)] + weights
    if args.cost == "cnn":
        bench.append("--no-warmup")
    print(f"{what}; cost {args.cost}" + (f", weights {args.weights}" if args.weights else "")
          + f"; best of {args.repeat}; {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.1f} at the start", flush=True)

    results, devices, raw, baselines = {}, {}, {}, {}
    for impl in impls:
        env = impl_env(impl)
        steady = {}
        if args.cost == "cnn":  # builds and first launches at this size (see the docstring)
            # the census pipeline, timed after its warm-up: the stereo stages in
            # steady state (a matcher's later calls reuse its volumes; the
            # single network run below is a first call, which maps fresh pages)
            out_c, _ = run([py, "-m", "mccnn_cl", "bench", "-v", "--max-disp", str(D), "--cost", "census",
                            "--repeat", str(max(3, args.repeat))] + pair, env, impl)
            steady = {f"census bench (after warm-up): {k}": v for k, v in parse_bench(out_c).items()}
            run([py, "-m", "mccnn_cl", "bench", "--max-disp", "1", "--cost", "cnn", "--no-warmup"] + weights + pair,
                env, impl)
        out_b, devices[impl] = run(bench + pair, env, impl)
        out_a, _ = run([py, str(REPO / "tools" / "benchmarks" / "bench_aggregation.py"), "--repeat", str(args.repeat)] + agg,
                       env, impl)
        raw[impl] = {"mccnn-cl bench": out_b, "bench_aggregation": out_a}
        baselines[impl] = parse_baselines(out_b)
        if steady:
            raw[impl]["mccnn-cl bench (census)"] = out_c
        results[impl] = {**{f"bench: {k}": v for k, v in parse_bench(out_b).items()}, **steady,
                         **{f"aggregation: {k}": v for k, v in parse_aggregation(out_a).items()}}

    labels = []
    for impl in impls:
        labels += [k for k in results[impl] if k not in labels]
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")
    for impl in impls:
        print(f"{impl}: {devices[impl]}")
        b = baselines[impl]
        for key in ("host CPU numpy GEMM (GFLOP/s)", "device buffer copy (GB/s, read + write)",
                    "load average (1 min)"):
            if key in b:
                when = "at the start / at the end" if key.startswith("load") else "before / after its timed runs"
                print(f"  bench's {key}, {when}: "
                      + " / ".join("-" if v is None else f"{v:.2f}" for v in b[key]))
        for w in b["warnings"]:
            print(f"  bench: {w}")
    print("\n| stage (seconds) | " + " | ".join(impls) + " |")
    print("|---|" + "---|" * len(impls))
    for lab in labels:
        cells = [f"{results[i][lab]:.3f}" if lab in results[i] else "-" for i in impls]
        print(f"| {lab} | " + " | ".join(cells) + " |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"what": what, "cost": args.cost, "weights": args.weights, "repeat": args.repeat,
                       "devices": devices, "seconds": results, "baselines": baselines, "raw_output": raw},
                      f, indent=1)
        print(f"JSON written to {args.json}")


if __name__ == "__main__":
    main()
