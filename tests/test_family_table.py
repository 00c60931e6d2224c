"""scripts/family_table.py: per-family records of methods on labeled pairs, and --reuse-cost
(a network's cost volume computed once per pair for every settings candidate of the same
weights: the same results, the records marked)."""

import importlib.util
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
