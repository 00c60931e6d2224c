"""The stereo method's hyperparameters (:class:`Hyperparameters`) and the one
check a network's settings and a caller's overrides go through
(:func:`check_settings`), shared by the API, the command line and weights files."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .errors import InputError, WeightsError
from .validate import check_hyperparameters

__all__ = ["Hyperparameters", "check_settings"]


@dataclass
class Hyperparameters:
    """Stereo-method hyperparameters; defaults are the paper's KITTI values.

    ``intensity_scale`` says what ``cbca_tau`` and ``sgm_tau_so`` compare:
    "unit" gray in [0, 1], or "standardised" each image as (I - mean) / std,
    the network's own normalisation (the released code's scale; see
    docs/method.md, "Intensity scale");
    ``blur_tau`` is on the 0..255 scale (the paper's tau_BF = 5) when
    ``bilateral_guide="image"``, in pixels when ``"disparity"``.

    Variant switches (paper default first; see docs/method.md):
    ``right_reference`` "aggregated" (paper: D^R is "obtained by treating the
    right image as the reference image"; the right-reference cost is derived
    from C_CNN by the index shift, never by rerunning the network, then goes
    through cross arms, CBCA, SGM and CBCA guided by the right image, as in
    the released code) | "derived" (D^R = argmin_d C(d, y, x + d) on the
    final left volume C: half the CBCA/SGM time, but left-guided SGM makes
    D^R worse and the left-right check then rejects good pixels);
    ``cross_include_neighbor`` False (code True); ``sgm_variant`` "paper" |
    "code", ``sgm_p2_times_pi1`` False, ``sgm_outside_large`` True, ``sgm_int16``
    False (True: SGM's paired sweeps in 16-bit integer steps; see
    :mod:`mccnn_cl.stages.sgm`);
    ``lr_threshold`` 1.0 (code: 1.1, identical on integer maps);
    ``interpolation`` "paper" | "code" (half-pixel direction steps, walk stops
    at any non-mismatch pixel); ``subpixel_min_denominator`` 0.0 (code 1e-5)
    and ``subpixel_clamp`` True (the paper is silent; unclamped, the step at a pixel whose
    D_INT was interpolated, not a cost minimum, reached hundreds of pixels); ``bilateral_guide`` "image" |
    "disparity" (code); ``blur_radius`` None = ceil(3 sigma).
    """

    cbca_eta: int = 4                 # eta: max arm length (exclusive)
    cross_include_neighbor: bool = False  # code: the +-1 neighbour always joins the arm
    cbca_tau: float = 0.0442          # tau: arm intensity threshold, [0, 1] scale
    cbca_iterations: int = 4          # CBCA iterations before SGM
    cbca_iterations_after: int = 4    # CBCA iterations after SGM
    sgm_pi1: float = 1.0              # Pi_1
    sgm_pi2: float = 32.0             # Pi_2
    sgm_tau_so: float = 0.0625        # tau_SO, [0, 1] scale
    sgm_q1: float = 4.0               # P divisor when one gradient >= tau_SO
    sgm_q2: float = 10.0              # P divisor when both are
    sgm_v: float = 2.0                # extra P1 divisor in the vertical directions
    sgm_variant: str = "paper"        # "paper" | "code" (P / (q1 q2) when both gradients are large)
    sgm_p2_times_pi1: bool = False    # P2 = Pi1 * Pi2 instead of Pi2
    sgm_outside_large: bool = True    # pd - r outside the right image counts as a large D2
    sgm_int16: bool = False           # SGM in 16-bit integer steps where the stage can (docs/method.md)
    right_reference: str = "aggregated"  # D^R: "aggregated" | "derived" (see docs/method.md)
    lr_threshold: float = 1.0         # |d - D^R(pd)| <= this is consistent
    interpolation: str = "paper"      # "paper" | "code"
    subpixel_min_denominator: float = 0.0
    subpixel_clamp: bool = True        # code as well; the paper gives no bound
    median_size: int = 5
    blur_sigma: float = 5.656         # sigma of the bilateral filter
    blur_tau: float = 5.0             # tau_BF (0..255 scale for the image guide)
    blur_radius: int | None = None    # None: ceil(3 sigma)
    bilateral_guide: str = "image"    # "image" (paper) | "disparity" (code)
    intensity_scale: str = "unit"     # "unit" | "standardised": the images cbca_tau, sgm_tau_so compare

    def __post_init__(self):
        if self.interpolation not in ("paper", "code"):
            raise InputError(f"interpolation must be 'paper' or 'code', not {self.interpolation!r}")
        if self.intensity_scale not in ("unit", "standardised"):
            raise InputError(f"intensity_scale must be 'unit' or 'standardised', not {self.intensity_scale!r}")
        if self.right_reference not in ("derived", "aggregated"):
            raise InputError(f"right_reference must be 'derived' or 'aggregated', not {self.right_reference!r}")
        if self.sgm_variant not in ("paper", "code"):
            raise InputError(f"sgm_variant must be 'paper' or 'code', not {self.sgm_variant!r}")
        if self.bilateral_guide not in ("image", "disparity"):
            raise InputError(f"bilateral_guide must be 'image' or 'disparity', not {self.bilateral_guide!r}")
        for name in ("cross_include_neighbor", "sgm_p2_times_pi1", "sgm_outside_large", "subpixel_clamp"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"{name} must be true or false, not {getattr(self, name)!r}")
        check_hyperparameters(self)  # every numeric field in its range (validate.HYPERPARAMETER_RANGES)

    @classmethod
    def names(cls) -> list:
        return [f.name for f in dataclasses.fields(cls)]


def check_settings(weights=None, overrides=None, source: str = "weights"):
    """The Hyperparameters a matcher would run with: a weights file's ``stereo``
    settings (each name known and in range, else :class:`~mccnn_cl.errors.WeightsError`
    naming ``source``), then ``overrides`` (``--set`` / keyword arguments; an
    unknown name is a ``TypeError``, a bad value an InputError).  The one place
    the API, the command line (before any OpenCL work) and weights files share."""
    names = set(Hyperparameters.names())
    settings = weights.stereo if weights is not None else {}
    if weights is not None:
        bad = sorted(set(settings) - names)
        if bad:
            raise WeightsError(f"{source}: the stereo settings name unknown hyperparameter(s) "
                               f"{', '.join(map(repr, bad))}")  # repr: a name may hold a newline
        try:
            Hyperparameters(**settings)
        except InputError as exc:
            raise WeightsError(f"{source}: stereo settings: {exc}") from exc
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise TypeError(f"unknown hyperparameter(s) {', '.join(map(repr, unknown))}; valid names: "
                        + ", ".join(Hyperparameters.names()))
    settings.update(overrides)
    return Hyperparameters(**settings)


def parse_settings(items, option: str = "--set") -> dict:
    """``["sgm_pi2=64", "interpolation=code"]`` -> ``{"sgm_pi2": 64, "interpolation": "code"}``:
    ints, floats, true/false and none where the text is one, else the text.  ``option``
    names the flag in the error for an item without ``=``."""
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        name, value = name.strip(), value.strip()
        if not sep or not name:
            raise InputError(f"{option} expects NAME=VALUE, got {item!r}")
        low = value.lower()
        if low in ("true", "false"):
            out[name] = low == "true"
        elif low in ("none", "null"):
            out[name] = None
        else:
            try:
                out[name] = int(value)
            except ValueError:
                try:
                    out[name] = float(value)
                except ValueError:
                    out[name] = value
    return out
