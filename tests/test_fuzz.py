"""Fuzzing the public entry points with Hypothesis (issue 28).

Generated inputs within the declared ranges (and some outside them):
hyperparameter sets (:data:`mccnn_cl.validate.HYPERPARAMETER_RANGES` and the
kernels' upper bounds), image sizes, dtypes and channels, disparity counts,
the matching cost (census or a small random network of each architecture),
``--set`` strings and weights-file metadata.  Each matcher run is on a small
crop of the eighth-size Cones pair (tests/cones_eighth) on the session's OpenCL device.

The properties: a call returns a finite float32 map of the left image's
shape, or raises :class:`~mccnn_cl.errors.InputError` (``WeightsError``
included) with a one-line message -- never another exception type, a NaN,
or a crash (a crash takes the pytest process with it: the run fails).

Profiles (``$MCCNN_FUZZ``): ``short`` (default, the everyday tier: well
under 2 minutes on 2 CPU cores) and ``long`` (on demand:
``MCCNN_FUZZ=long pytest tests/test_fuzz.py``; its time is in docs/cli.md,
"What you can rely on").  Examples are derandomised in the short profile
(the same ones every run: no flaky everyday tier); the long profile draws new
ones each run and prints the seed of a failure.
"""

import json
import os
from pathlib import Path

import numpy as np
import pytest

from hypothesis import HealthCheck, given, settings  # noqa: E402 (a dev dependency: missing = an error)
from hypothesis import strategies as st  # noqa: E402

from mccnn_cl.errors import InputError, WeightsError  # noqa: E402
from mccnn_cl.imageops import to_gray  # noqa: E402
from mccnn_cl.io import read_image  # noqa: E402
from mccnn_cl.pipeline import Hyperparameters, StereoMatcher  # noqa: E402
from mccnn_cl.validate import HYPERPARAMETER_RANGES, hyperparameter_maxima  # noqa: E402
from mccnn_cl.weights import ACRT, FST, PAPER, Weights  # noqa: E402

DEMO = Path(__file__).resolve().parent / "cones_eighth"  # Middlebury Cones, 225x188 (README there)

settings.register_profile("short", max_examples=12, deadline=None, derandomize=True, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
settings.register_profile("long", max_examples=300, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
PROFILE = os.environ.get("MCCNN_FUZZ", "short")
if PROFILE not in ("short", "long"):
    raise ValueError(f"MCCNN_FUZZ must be 'short' or 'long', not {PROFILE!r}")
#: examples per test (the short profile's metadata and --set tests are cheap: more of them)
CHEAP = {"short": 150, "long": 3000}[PROFILE]
MATCH = {"short": 10, "long": 300}[PROFILE]
if os.environ.get("MCCNN_FUZZ_EXAMPLES"):  # a shorter (or longer) long run: examples per test
    CHEAP = MATCH = int(os.environ["MCCNN_FUZZ_EXAMPLES"])

#: small random networks, one per architecture (kernels compiled once per session)
NETS = {
    PAPER: dict(conv_layers=[[8, 3], [8, 3]], fc_layers=[8, 2], architecture=PAPER),
    FST: dict(conv_layers=[[8, 3], [8, 3]], architecture=FST),
    ACRT: dict(conv_layers=[[8, 3], [8, 3]], fc_layers=[8, 1], architecture=ACRT),
}


#: Fields whose value is compiled into a kernel (median window, arm bound):
#: the short profile draws them from a few values (the long one: the whole range).
COMPILED = {"median_size": 7, "cbca_eta": 6}
#: matching costs and volume storage drawn per profile (each a set of kernel builds)
COSTS = {"short": ["census", FST], "long": ["census", PAPER, FST, ACRT]}[PROFILE]
VOLUMES = {"short": ["float32"], "long": ["float32", "float16"]}[PROFILE]


def one_line(exc):
    text = str(exc)
    assert text.strip() and "\n" not in text.strip(), repr(text)


@pytest.fixture(scope="module")
def demo():
    return read_image(DEMO / "im0.png"), read_image(DEMO / "im1.png")


@pytest.fixture(scope="module")
def nets():
    return {a: Weights.random(**kw, seed=1) for a, kw in NETS.items()}


# -- strategies -----------------------------------------------------------------

def _value(name):
    """A value of one numeric hyperparameter within its declared range (edges included)."""
    integer, low, inclusive = HYPERPARAMETER_RANGES[name]
    high = hyperparameter_maxima()[name][0]
    if PROFILE == "short" and name in COMPILED:
        high = COMPILED[name]  # each value is a kernel build (seconds on PoCL): a few in the everyday tier
    if name == "median_size":
        return st.integers(0, (high - 1) // 2).map(lambda k: 2 * k + 1)
    if name in ("cbca_iterations", "cbca_iterations_after"):
        high = 6  # declared up to 2^31 - 1; each iteration is a pass over the volume: keep examples short
    if name == "blur_radius":
        return st.one_of(st.none(), st.integers(0, 64), st.just(10 ** 9))
    if integer:
        return st.integers(int(low) + (0 if inclusive else 1), int(high))
    lo = 1e-6 if name in ("sgm_q1", "sgm_q2", "sgm_v", "blur_sigma") else low
    return st.floats(lo, high, exclude_min=not inclusive and lo == low, allow_nan=False)


CHOICES = {"interpolation": ("paper", "code"), "intensity_scale": ("unit", "standardised"),
           "right_reference": ("aggregated", "derived"), "sgm_variant": ("paper", "code"),
           "bilateral_guide": ("image", "disparity")}
FLAGS = ("cross_include_neighbor", "sgm_p2_times_pi1", "sgm_outside_large", "subpixel_clamp")


@st.composite
def hyperparameters(draw):
    out = {}
    for name in draw(st.sets(st.sampled_from(sorted(HYPERPARAMETER_RANGES)), max_size=6)):
        out[name] = draw(_value(name))
    for name in draw(st.sets(st.sampled_from(sorted(CHOICES)), max_size=3)):
        out[name] = draw(st.sampled_from(CHOICES[name]))
    for name in draw(st.sets(st.sampled_from(FLAGS), max_size=2)):
        out[name] = draw(st.booleans())
    return out


@st.composite
def pairs(draw, demo):
    """A crop of the Cones pair: size, dtype (uint8, uint16, float32/64 in [0, 1]), gray or colour."""
    left, right = demo
    H = draw(st.integers(1, 40))
    W = draw(st.integers(1, 56))
    y0 = draw(st.integers(0, left.shape[0] - H))
    x0 = draw(st.integers(0, left.shape[1] - W))
    L, R = left[y0:y0 + H, x0:x0 + W], right[y0:y0 + H, x0:x0 + W]
    if draw(st.booleans()):
        L, R = to_gray(L), to_gray(R)  # float32 gray in [0, 1]
        kind = draw(st.sampled_from(["float32", "float64", "uint16", "uint8"]))
        if kind == "uint16":
            L, R = (np.round(a * 65535).astype(np.uint16) for a in (L, R))
        elif kind == "uint8":
            L, R = (np.round(a * 255).astype(np.uint8) for a in (L, R))
        else:
            L, R = L.astype(kind), R.astype(kind)
    return np.ascontiguousarray(L), np.ascontiguousarray(R)


# -- the matcher ------------------------------------------------------------------

@settings(settings.get_profile(PROFILE), max_examples=MATCH)
@given(data=st.data())
def test_matcher_returns_a_finite_map_or_one_input_error(ctx, demo, nets, data):
    left, right = data.draw(pairs(demo), label="pair")
    W = left.shape[1]
    D = data.draw(st.one_of(st.integers(1, max(1, W - 1)), st.integers(-2, 3 * W + 2)), label="D")
    cost = data.draw(st.sampled_from(COSTS), label="cost")
    hyper = data.draw(hyperparameters(), label="hyperparameters")
    half = data.draw(st.sampled_from(VOLUMES), label="volume_dtype")
    try:
        if cost == "census":
            m = StereoMatcher(cost="census", max_disparity=D, device=ctx, volume_dtype=half, **hyper)
        else:
            m = StereoMatcher(nets[cost], max_disparity=D, device=ctx, volume_dtype=half, **hyper)
        out = m.compute(left, right)
    except InputError as exc:
        one_line(exc)
        return
    assert isinstance(out, np.ndarray) and out.dtype == np.float32, type(out)
    assert out.shape == left.shape[:2]
    assert np.isfinite(out).all(), f"{np.isnan(out).sum()} NaN, {np.isinf(out).sum()} inf"


# -- hyperparameters as the command line gives them ---------------------------------

TEXT = st.one_of(st.text(max_size=12), st.sampled_from(["1e309", "-0", "nan", "inf", "None", "true", "0x10",
                                                         "1_000", "5.", "  7 ", "31", "33", "256", "257"]))


@settings(settings.get_profile(PROFILE), max_examples=CHEAP)
@given(items=st.lists(st.tuples(st.one_of(st.sampled_from(Hyperparameters.names()), st.text(max_size=8)), TEXT),
                      max_size=4))
def test_set_options_are_accepted_or_one_input_error(items):
    from mccnn_cl.cli.commands import _hyperparameters
    from mccnn_cl.hyperparameters import check_settings
    try:
        hyper = _hyperparameters([f"{k}={v}" for k, v in items])
        params = check_settings(None, hyper)
    except TypeError as exc:  # an unknown name: the command line turns it into an InputError
        assert "unknown hyperparameter" in str(exc)
        return
    except InputError as exc:
        one_line(exc)
        return
    assert isinstance(params, Hyperparameters)


# -- weights metadata ------------------------------------------------------------------

JSON = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(-3, 300), st.floats(allow_nan=False),
                              st.text(max_size=6)),
                    lambda inner: st.one_of(st.lists(inner, max_size=4),
                                            st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                    max_leaves=8)
KEYS = ["format", "version", "architecture", "conv_layers", "fc_layers", "patch_size", "input_channels",
        "stereo", "normalisation", "bad_match_class"]


@st.composite
def stereo_settings(draw):
    """Valid or invalid names and values for meta["stereo"]."""
    names = st.one_of(st.sampled_from(Hyperparameters.names()), st.text(max_size=6))
    return draw(st.dictionaries(names, st.one_of(JSON, st.integers(-5, 400), st.floats(-1e7, 1e7)), max_size=3))


@settings(settings.get_profile(PROFILE), max_examples=CHEAP)
@given(arch=st.sampled_from(sorted(NETS)), changes=st.dictionaries(st.sampled_from(KEYS), JSON, max_size=3),
       stereo=st.one_of(st.none(), stereo_settings()), drop=st.sets(st.sampled_from(KEYS), max_size=2))
def test_weights_metadata_loads_or_one_weights_error(tmp_path_factory, arch, changes, stereo, drop):
    path = tmp_path_factory.mktemp("w") / "w.npz"
    Weights.random(**NETS[arch]).save(path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["__meta__"]))
    meta.update(changes)
    if stereo is not None:
        meta["stereo"] = stereo
    for k in drop:
        meta.pop(k, None)
    arrays["__meta__"] = np.array(json.dumps(meta))
    np.savez(path, **arrays)
    try:
        w = Weights.load(path)
    except WeightsError as exc:
        one_line(exc)
        return
    assert w.architecture in NETS and w.patch_size >= 1
    Hyperparameters(**w.stereo)  # settings a loaded file carries are valid ones
