"""The one input validator (mccnn_cl.validate) and Hyperparameters' ranges."""

import dataclasses

import numpy as np
import pytest

from mccnn_cl.errors import InputError
from mccnn_cl.pipeline import Hyperparameters
from mccnn_cl.validate import HYPERPARAMETER_RANGES, check_pair, patch_size
from mccnn_cl.weights import Weights


@pytest.mark.parametrize("name, bad, words", [
    ("sgm_pi1", -1.0, ">= 0.0"), ("sgm_pi2", -1, ">= 0.0"), ("sgm_tau_so", -0.01, ">= 0.0"),
    ("sgm_q1", 0.0, "> 0.0"), ("sgm_q2", -2.0, "> 0.0"), ("sgm_v", 0, "> 0.0"),
    ("cbca_tau", -0.1, ">= 0.0"), ("cbca_eta", -1, ">= 0"), ("cbca_eta", 2.5, "integer"),
    ("cbca_iterations", -1, ">= 0"), ("cbca_iterations_after", 1.5, "integer"),
    ("lr_threshold", -1.0, ">= 0.0"), ("subpixel_min_denominator", -1e-5, ">= 0.0"),
    ("blur_sigma", 0.0, "> 0.0"), ("blur_tau", -5.0, ">= 0.0"), ("blur_radius", -1, ">= 0"),
    ("median_size", 4, "odd"), ("median_size", 0, ">= 1"), ("sgm_pi2", float("nan"), "finite"),
    ("sgm_pi2", float("inf"), "finite"), ("sgm_pi2", "32", "number"), ("sgm_q1", True, "number"),
    ("subpixel_clamp", 1, "true or false"),
])
def test_out_of_range_hyperparameter_is_one_clear_line(name, bad, words):
    with pytest.raises(InputError) as info:
        Hyperparameters(**{name: bad})
    msg = str(info.value)
    assert name in msg and words in msg and "\n" not in msg, msg


def test_range_edges_and_defaults_accepted():
    Hyperparameters()  # the paper's values
    Hyperparameters(sgm_pi1=0, sgm_pi2=0.0, sgm_tau_so=0, cbca_eta=0, cbca_tau=0.0, cbca_iterations=0,
                    cbca_iterations_after=0, lr_threshold=0, blur_tau=0.0, blur_radius=0, median_size=1,
                    sgm_q1=1e-6, blur_sigma=1e-3)
    Hyperparameters(cbca_eta=np.int64(5), sgm_pi2=np.float32(16))


def test_every_numeric_field_has_a_range():
    """A numeric field added later without a range would pass unchecked: this fails then."""
    defaults = Hyperparameters()
    for f in dataclasses.fields(Hyperparameters):
        value = getattr(defaults, f.name)
        numeric = (isinstance(value, (int, float)) and not isinstance(value, bool)) or f.name == "blur_radius"
        assert not numeric or f.name in HYPERPARAMETER_RANGES, f.name


def test_check_pair():
    a, b = np.zeros((40, 50)), np.zeros((40, 50, 3), np.uint8)
    check_pair(a, b, 49)  # colour and gray of one size: only H, W are compared
    for left, right, D, patch, words in [
        (a, np.zeros((40, 51)), 16, 9, "differ in size"),
        (np.zeros((8, 50)), np.zeros((8, 50)), 4, 9, "smaller than the 9x9 patch"),
        (a, a, 16, 41, "smaller than the 41x41 patch"),
        (a, a, 50, 9, "not smaller than the image width 50"),
    ]:
        with pytest.raises(InputError, match=words):
            check_pair(left, right, D, patch)
    assert patch_size(None) == 9
    assert patch_size(Weights.random(conv_layers=[[8, 3], [8, 3]], fc_layers=[8, 2])) == 9
    assert patch_size(Weights.random(seed=0)) == 9


def test_check_pair_range_from_a_nonzero_minimum():
    """D < W applies to ranges from M >= 0 only: from M < 0 the method works on a
    W - M wide frame, so D may exceed W (a 250-level range from -150 on a 225-px
    image was refused), but the largest disparity must stay below W - 1 (no
    pixel matches beyond, as with D >= W from 0); disprange.check_range holds
    too; the message names the range as the caller gave it."""
    a = np.zeros((40, 225))
    check_pair(a, a, 250, 9, min_disparity=-150)
    check_pair(a, a, 254, 9, min_disparity=-30)  # -30 .. 223
    with pytest.raises(InputError, match=r"disparities -30\.\.224 \(--min-disp, --max-disp\) reach the image width 225"):
        check_pair(a, a, 255, 9, min_disparity=-30)
    with pytest.raises(InputError, match="is not smaller than the image width 225"):
        check_pair(a, a, 239, 9, min_disparity=2)
    with pytest.raises(InputError, match="leave no pixel a match"):
        check_pair(a, a, 100, 9, min_disparity=-400)
    with pytest.raises(InputError, match=r"disparity range 225 \(disparity_range=\(0, 224\)\) is not smaller"):
        check_pair(a, a, 225, 9, range_name="disparity_range=(0, 224)")
    with pytest.raises(InputError, match=r"\(max_disparity, --max-disp\)"):  # the command line's default
        check_pair(a, a, 225, 9)
