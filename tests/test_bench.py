"""mccnn_cl.benchmark: the one stage-grouping table and the synthetic pair."""

import numpy as np
import pytest

from mccnn_cl.benchmark import GROUPS, STAGE_GROUP, group_timings, stage_group, synthetic_pair
from mccnn_cl.pipeline import StereoMatcher


@pytest.mark.parametrize("kw", [{}, {"right_reference": "derived"}, {"memory_limit": 2 << 20, "tile_overlap": 8}])
def test_every_timed_stage_has_a_group(ctx, kw):
    left, right = synthetic_pair(120, 90, 16)
    res = StereoMatcher(cost="census", max_disparity=16, device=ctx, **kw).compute(left, right, timings=True)
    assert res.plan.tiled == ("memory_limit" in kw)
    missing = sorted(set(res.timings) - set(STAGE_GROUP))
    assert not missing, f"add these stage names to mccnn_cl.benchmark.STAGE_GROUP: {missing}"
    groups = group_timings(res.timings)
    assert list(groups) == list(GROUPS)
    assert sum(groups.values()) == pytest.approx(sum(res.timings.values()))
    assert groups["CBCA"] > 0 and groups["SGM"] > 0 and groups["cost"] > 0


def test_groups():
    assert [stage_group(n) for n in ("C_CNN", "C_CNN_upload", "cross_R", "C_R_SGM", "right_volume", "D_BF")] == \
        ["cost", "cost", "CBCA", "SGM", "rest", "rest"]
    assert [stage_group(n) for n in ("census_extra", "my_cbca", "sgm2", "whatever")] == ["cost", "CBCA", "SGM", "rest"]
    assert set(STAGE_GROUP.values()) <= set(GROUPS)


def test_synthetic_pair_shifts_by_the_slanted_field():
    left, right = synthetic_pair(80, 40, 20, seed=1)
    assert left.shape == right.shape == (40, 80) and left.dtype == right.dtype == np.uint8
    assert left.std() > 20
    # row 0's disparity is 0.15 (D - 1) = 2.85: right(x) ~ left(x + d) away from the borders
    d = 0.15 * 19
    x = np.arange(10, 60)
    interp = np.interp(x + d, np.arange(80), left[0].astype(np.float64))
    assert np.abs(interp - right[0, 10:60].astype(np.float64)).mean() < 4
