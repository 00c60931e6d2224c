"""Metrics against hand-computed values on small synthetic maps."""

import math

import numpy as np
import pytest

from mccnn_cl.evaluation import metrics
from mccnn_cl.errors import InputError
from mccnn_cl.evaluation.scoring import format_table, mean_metrics, training_status

nan, inf = np.nan, np.inf

# 2 x 5 ground truth: one unknown pixel (NaN) and one +inf (also unknown)
GT = np.array([[10.0, 20.0, 40.0, nan, 100.0],
               [10.0, 10.0, 10.0, inf, 60.0]], np.float32)
# errors:        0     3.5   2.5   -    4.5
#                1     nan   10    -    2.9  (pred NaN = invalid)
PRED = np.array([[10.0, 23.5, 37.5, 5.0, 104.5],
                 [11.0, nan, 20.0, 7.0, 62.9]], np.float32)
NOC = np.array([[1, 1, 1, 1, 0],
                [1, 1, 0, 1, 1]], bool)


def test_evaluated_set_excludes_unknown_gt():
    ev = metrics.evaluated(GT)
    assert ev.sum() == 8 and not ev[0, 3] and not ev[1, 3]
    assert metrics.evaluated(GT, NOC).sum() == 6


def test_bad3_counts_errors_and_invalid_predictions():
    # > 3 px among 8 known: 3.5, 4.5, 10, and the NaN prediction -> 4/8
    assert metrics.kitti_3px(PRED, GT) == pytest.approx(50.0)
    # noc (6 px: (0,0) (0,1) (0,2) (1,0) (1,1) (1,4)): 3.5 and NaN -> 2/6
    assert metrics.kitti_3px(PRED, GT, NOC) == pytest.approx(100 * 2 / 6)


def test_threshold_is_strict():
    gt = np.array([[10.0, 10.0]], np.float32)
    pred = np.array([[13.0, 13.0001]], np.float32)
    assert metrics.kitti_3px(pred, gt) == pytest.approx(50.0)  # exactly 3 px is not an error


def test_d1_needs_both_3px_and_5_percent():
    # 3.5 on gt 20 (17.5 %: bad), 4.5 on gt 100 (4.5 %: fine), 10 on 10 (bad), NaN (bad) -> 3/8
    assert metrics.kitti_d1(PRED, GT) == pytest.approx(100 * 3 / 8)
    gt = np.array([[100.0, 100.0, 40.0]], np.float32)
    pred = np.array([[104.0, 106.0, 44.0]], np.float32)  # 4 % ok, 6 % bad, 10 % bad
    assert metrics.kitti_d1(pred, gt) == pytest.approx(100 * 2 / 3)


def test_bad2():
    # > 2 among 8: 3.5, 2.5, 4.5, NaN, 10, 2.9 -> 6/8
    assert metrics.middlebury_bad(PRED, GT) == pytest.approx(75.0)
    assert metrics.middlebury_bad(PRED, GT, threshold=4.0) == pytest.approx(100 * 3 / 8)


def test_epe_ignores_invalid_predictions():
    errs = [0, 3.5, 2.5, 4.5, 1, 10, 2.9]  # the NaN prediction is left out
    assert metrics.end_point_error(PRED, GT) == pytest.approx(np.mean(errs), rel=1e-6)


def test_density():
    assert metrics.density(PRED) == pytest.approx(90.0)  # 1 NaN of 10
    assert metrics.density(PRED, NOC) == pytest.approx(100 * 7 / 8)
    assert metrics.density(np.full((2, 2), np.inf)) == 0.0


def test_no_gt_gives_nan():
    gt = np.full((3, 3), np.nan, np.float32)
    assert math.isnan(metrics.kitti_3px(np.zeros((3, 3)), gt))
    assert math.isnan(metrics.end_point_error(np.zeros((3, 3)), gt))


def test_evaluate_disparity_keys_and_noc_absent():
    out = metrics.evaluate_disparity(PRED, GT, valid_noc=NOC)
    assert set(out) == set(metrics.METRIC_NAMES)
    assert out["bad3_all"] == pytest.approx(50.0)
    assert out["bad3_noc"] == pytest.approx(100 * 2 / 6)
    assert out["d1_all"] == pytest.approx(37.5)
    assert out["density"] == pytest.approx(90.0)
    no_noc = metrics.evaluate_disparity(PRED, GT)
    assert math.isnan(no_noc["bad3_noc"]) and math.isnan(no_noc["bad2_noc"])
    # valid_all restricts "all" further
    va = np.ones_like(NOC)
    va[1, 2] = False  # drop the 10 px error
    assert metrics.evaluate_disparity(PRED, GT, valid_all=va)["bad3_all"] == pytest.approx(100 * 3 / 7)


def test_shape_mismatch_is_input_error():
    with pytest.raises(InputError):
        metrics.kitti_3px(np.zeros((2, 3)), np.zeros((3, 2)))
    with pytest.raises(InputError):
        metrics.kitti_3px(np.zeros((2, 3)), np.zeros((2, 3)), np.ones((3, 3), bool))


def test_bad_pixel_map():
    m = metrics.bad_pixel_map(PRED, GT, 3.0)
    expected = np.array([[0, 1, 0, -1, 1],
                         [0, 1, 1, -1, 0]], np.int8)
    np.testing.assert_array_equal(m, expected)


def test_fill_invalid_like_kitti_devkit():
    d = np.array([[nan, 5, nan, nan, 3, nan],
                  [nan, nan, nan, nan, nan, nan],
                  [1, nan, 2, nan, nan, inf]], np.float32)
    f = metrics.fill_invalid(d)
    # row 0: border takes the nearest valid, interior gap the smaller neighbour (background)
    np.testing.assert_array_equal(f[0], [5, 5, 3, 3, 3, 3])
    np.testing.assert_array_equal(f[2], [1, 1, 2, 2, 2, 2])
    # row 1 (empty, between valid rows): the devkit leaves it unfilled, read as 0
    np.testing.assert_array_equal(f[1], [0, 0, 0, 0, 0, 0])
    assert np.isnan(d[0, 0])  # input untouched
    # empty rows above the first and below the last valid row take the column's nearest value
    e = np.full((5, 3), nan, np.float32)
    e[1] = [4, nan, 6]
    e[3] = [7, 8, nan]
    np.testing.assert_array_equal(metrics.fill_invalid(e), [[4, 4, 6], [4, 4, 6], [0, 0, 0], [7, 8, 8], [7, 8, 8]])
    np.testing.assert_array_equal(metrics.fill_invalid(np.full((2, 2), nan)), np.zeros((2, 2)))


def test_mean_and_table():
    r1 = {"pair": "middlebury/A", "size": [5, 2], "max_disparity": 16, "training": "held out",
          "methods": {"mccnn": {**metrics.evaluate_disparity(PRED, GT), "seconds": 1.0},
                      "sgbm": {**metrics.evaluate_disparity(GT, GT), "seconds": 0.5}}}
    r2 = {"pair": "middlebury/B", "size": [5, 2], "max_disparity": 16, "training": "trained",
          "methods": {"mccnn": {**metrics.evaluate_disparity(GT, GT), "seconds": 3.0},
                      "sgbm": {**metrics.evaluate_disparity(GT, GT), "seconds": 0.5}}}
    mean = mean_metrics([r1, r2])
    assert mean["mccnn"]["bad3_all"] == pytest.approx(25.0)
    assert mean["mccnn"]["seconds"] == pytest.approx(2.0)
    assert math.isnan(mean["sgbm"]["bad3_noc"])  # no noc masks: NaN, not 0
    text = format_table([r1, r2], mean)
    assert "ours" in text and "sgbm" in text and "mean" in text and "held out" in text
    assert "50.00" in text and "90.0" in text
    assert "over the" not in text  # every mean covers both pairs (the noc ones none)


def test_means_say_when_they_cover_fewer_pairs():
    """A mean over the pairs that have a metric (e.g. KITTI frames without disp_noc) says so."""
    from mccnn_cl.evaluation.scoring import family_means, format_family_tables, metric_counts
    with_noc = {**metrics.evaluate_disparity(PRED, GT, GT > 0), "seconds": 1.0}
    without = {**metrics.evaluate_disparity(GT, GT), "seconds": 1.0}
    rows = [{"pair": f"kitti2015/00000{i}", "size": [5, 2], "max_disparity": 16, "training": "held out",
             "methods": {"mccnn": m}} for i, m in enumerate((with_noc, without))]
    assert metric_counts(rows)["mccnn"]["bad3_noc"] == 1 and metric_counts(rows)["mccnn"]["bad3_all"] == 2
    fam = family_means(rows)["kitti"]
    assert fam["mean"]["mccnn"]["bad3_noc"] == pytest.approx(with_noc["bad3_noc"])
    assert fam["mean_pairs"]["mccnn"]["bad3_noc"] == 1
    text = format_family_tables(rows)
    assert "3px-noc: over the 1 of 2 pairs that have it" in text and "3px-all: over" not in text


def test_table_cells_fit():
    from mccnn_cl.evaluation.scoring import _fmt
    assert _fmt(100.0, "bad3_all") == "100.0"  # 100 % fits the 5-wide column with one decimal
    assert _fmt(3.14159, "bad3_all") == "3.14"
    assert _fmt(1234.5, "seconds") == "1234"
    assert _fmt(89.004, "density") == "89.0"
    assert _fmt(float("nan"), "epe_all") == "-"


def test_training_status_from_metadata():
    meta = {"training": {"pairs": ["kitti2015/000001", "middlebury/Tsukuba"],
                         "held_out": ["kitti2015/000000", "middlebury/Cones"]}}
    assert training_status(meta, "middlebury/Tsukuba", "Tsukuba") == "trained"
    assert training_status(meta, "middlebury/Cones", "Cones") == "held out"
    assert training_status(meta, "kitti2012/000000", "000000") == "held out"  # not listed
    # train.py's provenance: trained_on = {key: examples}, held_out = [keys]
    meta = {"training": {"trained_on": {"kitti2015/000001": 900, "middlebury/Tsukuba": 40},
                         "held_out": ["kitti2015/000000", "middlebury/Cones"]}}
    assert training_status(meta, "middlebury/Tsukuba", "Tsukuba") == "trained"
    assert training_status(meta, "kitti2015/000000", "000000") == "held out"
    assert training_status(meta, "middlebury/Aloe", "Aloe") == "held out"
    assert training_status({"training": {"note": "random"}}, "middlebury/Cones", "Cones") == "unknown"
    assert training_status({}, "middlebury/Cones", "Cones") == "unknown"
    # a converted network's trained_on: {key: {"by": .., "how": ..}}, or a description string per key
    for value in ({"by": "the authors", "how": "main.lua -a train_all"}, "the authors' training"):
        meta = {"training": {"trained_on": {"kitti2012/000000": value, "kitti2012/000001": value}}}
        assert training_status(meta, "kitti2012/000000", "000000") == "trained"
        assert training_status(meta, "kitti2015/000000", "000000") == "held out"
    # the by-kind form stays as it was: {"kitti2015": ["000001"]}
    meta = {"training": {"trained_on": {"kitti2015": ["000001"], "middlebury": "Tsukuba"}}}
    assert training_status(meta, "kitti2015/000001", "000001") == "trained"
    assert training_status(meta, "middlebury/Tsukuba", "Tsukuba") == "trained"
