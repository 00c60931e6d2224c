"""scripts/family_table.py: per-family records of methods on labeled pairs, and --reuse-cost
(a network's cost volume computed once per pair for every settings candidate of the same
weights: the same results, the records marked)."""

import importlib.util
import os
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _family_table():
    spec = importlib.util.spec_from_file_location("family_table", REPO / "scripts" / "family_table.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.full_data
def test_reused_cost_gives_the_same_records(shared_data, tmp_path, capsys):
    ft = _family_table()
    methods = ["a=kitti-fst", "b=kitti-fst@mccnn-fst/mb", "c=kitti-fst+cbca_iterations_after=2", "census"]
    args = ["--data", str(shared_data), "--pairs", "middlebury/Tsukuba", "--methods", *methods]
    ft.main(args + ["--out", str(tmp_path / "plain.jsonl")])
    ft.main(args + ["--out", str(tmp_path / "reused.jsonl"), "--reuse-cost"])
    plain = [json.loads(x) for x in open(tmp_path / "plain.jsonl")]
    reused = [json.loads(x) for x in open(tmp_path / "reused.jsonl")]
    assert [r["method"] for r in plain] == [r["method"] for r in reused] == ["a", "b", "c", "census"]
    for p, r in zip(plain, reused):
        assert {k: v for k, v in p["result"].items() if k != "seconds"} == \
               {k: v for k, v in r["result"].items() if k != "seconds"}, p["method"]
        assert "cost_reused" not in p
    assert [r.get("cost_reused", False) for r in reused] == [False, True, True, False]
    # the settings differ, so the records must too: the reuse did not hand back a disparity map
    assert plain[0]["result"]["bad2_all"] != plain[1]["result"]["bad2_all"]
    capsys.readouterr()
    ft.main(["--summary", str(tmp_path / "reused.jsonl")])
    out = capsys.readouterr().out
    assert "**middlebury** (1 pairs: Tsukuba)" in out and "| b |" in out and "| census |" in out


# -- a torn last record (a crash or a full disk mid-write) ---------------------------------------

def _result(bad):
    return {"bad1_all": bad + 1, "bad2_all": bad, "bad2_noc": bad - 1, "bad3_all": bad - 2, "seconds": 0.5}


def _record(pair, bad):
    return {"pair": pair, "dataset": "middlebury", "method": "sgbm", "spec": "sgbm", "result": _result(bad)}


@pytest.fixture
def fake_pairs(monkeypatch):
    """run() on two fake Middlebury pairs A and B, SGBM 'scored' without any image or device."""
    import types

    import mccnn_cl.evaluation.datasets as datasets
    import mccnn_cl.evaluation.scoring as scoring
    import mccnn_cl.opencl.context as context
    refs = [types.SimpleNamespace(key=f"middlebury/{n}", load=lambda n=n: types.SimpleNamespace(key=n))
            for n in "AB"]
    scored = []

    def evaluate_pair(pair, matcher, D, baseline=None):
        scored.append(pair.key)
        return {"pair": f"middlebury/{pair.key}", "dataset": "middlebury", "methods": {"sgbm": _result(7.0)}}

    monkeypatch.setattr(datasets, "discover", lambda root, labeled=None: refs)
    monkeypatch.setattr(scoring, "evaluate_pair", evaluate_pair)
    monkeypatch.setattr(scoring, "default_max_disparity", lambda pair: 16)
    monkeypatch.setattr(context, "ClContext", lambda device=None: None)
    return scored


def test_torn_last_record_is_skipped_cut_off_and_the_run_goes_on(tmp_path, fake_pairs, capsys, monkeypatch):
    """The last line torn (disk full mid-write): --summary still reads the file, with a warning; a
    run cuts the torn line off, redoes that pair and appends whole lines (one write, fsynced)."""
    ft = _family_table()
    out = tmp_path / "t.jsonl"
    whole = json.dumps(_record("middlebury/A", 3.0)) + "\n"
    out.write_text(whole + json.dumps(_record("middlebury/B", 4.0))[:40])
    ft.main(["--summary", str(out)])
    cap = capsys.readouterr()
    assert "| sgbm | 2.00 | 3.00 |" in cap.out and "line 2: the last record is unreadable" in cap.err
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd))[1])
    ft.main(["--data", str(tmp_path), "--methods", "sgbm", "--out", str(out)])
    assert fake_pairs == ["B"]  # A was done, B's torn record is redone
    assert "skipped and cut off" in capsys.readouterr().err
    text = out.read_text()
    assert text.startswith(whole) and text.endswith("\n")
    assert [json.loads(x)["pair"] for x in text.splitlines()] == ["middlebury/A", "middlebury/B"]
    assert len(synced) == 2  # the cut, and the appended record
    ft.main(["--summary", str(out)])
    cap = capsys.readouterr()
    assert "| sgbm | 4.00 | 5.00 | 0.5 | 2 |" in cap.out and cap.err == ""


def test_whole_last_record_without_its_newline_gets_one(tmp_path, fake_pairs):
    ft = _family_table()
    out = tmp_path / "t.jsonl"
    out.write_text(json.dumps(_record("middlebury/A", 3.0)))  # torn just before its newline
    ft.main(["--data", str(tmp_path), "--methods", "sgbm", "--out", str(out)])
    assert fake_pairs == ["B"]
    assert [json.loads(x)["pair"] for x in out.read_text().splitlines()] == ["middlebury/A", "middlebury/B"]


def test_unreadable_line_before_the_last_is_an_error(tmp_path):
    ft = _family_table()
    out = tmp_path / "t.jsonl"
    out.write_text("{not json\n" + json.dumps(_record("middlebury/A", 3.0)) + "\n")
    with pytest.raises(SystemExit, match=r"t.jsonl, line 1: not a JSON record"):
        ft.main(["--summary", str(out)])
