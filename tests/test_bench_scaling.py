"""tools/benchmarks/bench_scaling.py at tiny sizes (--quick) in a subprocess: its JSON is
complete and self-consistent (sizes, cell counts, stage sums, the fits
recomputed here).  Timings at these sizes are noise, so linearity itself is
not asserted; the full-size run in BENCHMARKS.md shows it."""

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "tools" / "benchmarks" / "bench_scaling.py"


def _module():
    spec = importlib.util.spec_from_file_location("bench_scaling", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_fit_line_and_deviation():
    fit = _module().fit
    exact = fit([1.0, 2.0, 4.0], [3.0, 5.0, 9.0])  # t = 1 + 2x
    assert exact["a"] == pytest.approx(1.0) and exact["b"] == pytest.approx(2.0)
    assert exact["max_rel_dev"] < 1e-12
    bent = fit([1.0, 2.0, 3.0], [1.0, 3.0, 3.0])  # least squares: t = 1/3 + x
    assert bent["a"] == pytest.approx(1 / 3) and bent["b"] == pytest.approx(1.0)
    # deviations 1/3, 2/3, 1/3 over t = 1, 3, 3
    np.testing.assert_allclose(bent["rel_dev"], [1 / 3, 2 / 9, 1 / 9], rtol=1e-9)
    assert bent["max_rel_dev"] == pytest.approx(1 / 3)


def _cells(method, W, H, D):
    h, w = H - 8, W - 8
    if method == "stereo":
        return D * h * w
    return int(sum(h * (w - d) for d in range(D) if d < w))


def _check_fit(f, x, t):
    b, a = np.polyfit(np.asarray(x, float), np.asarray(t, float), 1)
    scale = max(t)
    assert f["a"] == pytest.approx(a, abs=1e-9 * scale + 1e-12)
    assert f["b"] * max(x) == pytest.approx(b * max(x), abs=1e-9 * scale + 1e-12)
    dev = np.abs(np.asarray(t) - (a + b * np.asarray(x, float))) / np.asarray(t)
    np.testing.assert_allclose(f["rel_dev"], dev, rtol=1e-6, atol=1e-9)
    assert f["max_rel_dev"] == pytest.approx(dev.max(), rel=1e-6, abs=1e-9)


@pytest.mark.slow
def test_quick_run_json_is_consistent(tmp_path, shared_data, request):
    out, png = tmp_path / "scaling.json", tmp_path / "scaling.png"
    cmd = [sys.executable, str(SCRIPT), "--quick", "--json", str(out), "--plot", str(png)]
    device = request.config.getoption("--cl-device")
    if device:
        cmd += ["--device", device]
    env = dict(os.environ, MCCNN_DATA=str(shared_data))
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout + p.stderr
    r = json.loads(out.read_text())

    assert r["quick"] is True and r["repeat"] == 1 and r["device"]
    assert len(r["load_average"]) == 2
    names = [s["name"] for s in r["series"]]
    assert names == ["stereo_area", "stereo_disp", "network_area", "network_disp"]
    for s in r["series"]:
        pts = s["points"]
        assert len(pts) == 3, s["name"]
        method = s["method"]
        assert s["name"].startswith(method)
        xs = [pt[s["x_key"]] for pt in pts]
        assert all(x1 < x2 for x1, x2 in zip(xs, xs[1:])), (s["name"], xs)
        if s["vary"] == "area":
            assert s["x_key"] == "area_mpx" and {pt["D"] for pt in pts} == {s["fixed"]["D"]}
        else:
            assert s["x_key"] == "D"
            assert {(pt["width"], pt["height"]) for pt in pts} == {(s["fixed"]["width"], s["fixed"]["height"])}
        for pt in pts:
            assert pt["area_mpx"] == pytest.approx(pt["width"] * pt["height"] / 1e6)
            assert pt["cells"] == _cells(method, pt["width"], pt["height"], pt["D"])
            t = pt["times"]
            assert all(np.isfinite(v) for v in t.values()), t
            if method == "stereo":
                assert min(t["CBCA"], t["SGM"], t["cost"]) > 0, t
                # stage times are parts of the wall time of the same run
                assert t["cost"] + t["CBCA"] + t["SGM"] < t["total"], t
                assert t["total_excl_cost"] == pytest.approx(t["total"] - t["cost"], abs=1e-9)
                assert t["rest"] == pytest.approx(t["total_excl_cost"] - t["CBCA"] - t["SGM"], abs=1e-9)
            else:
                assert set(t) == {"network"} and t["network"] > 0
        want = {"CBCA", "SGM", "rest", "total_excl_cost"} if method == "stereo" else {"network"}
        assert set(s["fits"]) == want
        for q, f in s["fits"].items():
            t = [pt["times"][q] for pt in pts]
            _check_fit(f["x"], xs, t)
            _check_fit(f["cells"], [pt["cells"] for pt in pts], t)

    assert "| stereo_area" in p.stdout and "| network_disp" in p.stdout
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert r["plot"] is None and "NOT written" in p.stdout
    else:
        assert r["plot"] == str(png)
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
