"""Stereo-method settings that belong to a network.

A network is tuned together with the stereo method that consumes its cost
volume: penalties, thresholds and iteration counts differ by architecture and
dataset.  A weights file carries the settings it was tuned with in
``meta["stereo"]`` (:attr:`mccnn_cl.weights.Weights.stereo`), as
:class:`mccnn_cl.pipeline.Hyperparameters` field names;
``StereoMatcher(weights=...)`` applies them unless the caller overrides a
name.

``AUTHORS`` holds the authors' per-network settings from the released code
(jzbontar/mc-cnn, ``main.lua``; tabulated in the shared models README),
translated to this project's names:

==============  ==========================================================
released code   here
==============  ==========================================================
L1, tau1        ``cbca_eta`` (exclusive arm limit), ``cbca_tau``, with
                ``cross_include_neighbor=True``
cbca_i1 / i2    ``cbca_iterations`` / ``cbca_iterations_after``
pi1, pi2        ``sgm_pi1``, ``sgm_pi2`` (the sgm2 kernel uses P2 = pi2)
sgm_q1, q2      ``sgm_q1``, ``sgm_q2`` with ``sgm_variant="code"``
                (P / q1 when one gradient is large, P / (q1 q2) when both)
alpha1          ``sgm_v`` (vertical P1 divisor)
tau_so          ``sgm_tau_so``
blur_sigma, t   ``blur_sigma``, ``blur_tau`` with
                ``bilateral_guide="disparity"`` (blur_t is in pixels)
==============  ==========================================================

Every intensity threshold of the released code (tau1, tau_so) compares the
*standardised* images ((I - mean) / std per image), hence
``intensity_scale="standardised"``.  The remaining released-code variants
(left-right threshold 1.1, the code's mismatch fill, the clamped subpixel
step) come with them.
"""

from __future__ import annotations

#: Released-code behaviour shared by every authors' network.
CODE_VARIANTS = {
    "intensity_scale": "standardised",
    "cross_include_neighbor": True,
    "sgm_variant": "code",
    "sgm_p2_times_pi1": False,
    "sgm_outside_large": True,
    "lr_threshold": 1.1,
    "interpolation": "code",
    "subpixel_min_denominator": 1e-5,
    "subpixel_clamp": True,
    "median_size": 5,
    "bilateral_guide": "disparity",
}


def _code(eta, tau, it1, it2, pi1, pi2, q1, q2, v, tau_so, sigma, blur_t) -> dict:
    s = dict(CODE_VARIANTS)
    s.update(cbca_eta=eta, cbca_tau=tau, cbca_iterations=it1, cbca_iterations_after=it2,
             sgm_pi1=pi1, sgm_pi2=pi2, sgm_q1=q1, sgm_q2=q2, sgm_v=v, sgm_tau_so=tau_so,
             blur_sigma=sigma, blur_tau=blur_t)
    return s


#: (architecture, dataset) -> Hyperparameters overrides, the released code's values.
#: The fst pipelines run no cross-based aggregation (L1 = 0, no iterations).
AUTHORS = {
    ("mccnn-fst", "kitti"): _code(0, 0.0, 0, 0, 4.0, 55.72, 3.0, 2.5, 1.5, 0.02, 7.74, 5.0),
    ("mccnn-fst", "kitti2015"): _code(0, 0.0, 0, 0, 2.3, 18.38, 3.0, 2.0, 1.25, 0.08, 4.64, 5.0),
    ("mccnn-fst", "mb"): _code(0, 0.0, 0, 0, 2.3, 24.3, 4.0, 2.0, 1.5, 0.08, 6.0, 2.0),
    ("mccnn-acrt", "kitti"): _code(5, 0.13, 2, 0, 1.32, 24.25, 3.0, 2.0, 2.0, 0.08, 5.99, 6.0),
    ("mccnn-acrt", "kitti2015"): _code(5, 0.03, 2, 4, 2.3, 24.25, 3.0, 2.0, 1.75, 0.08, 5.99, 5.0),
    ("mccnn-acrt", "mb"): _code(14, 0.02, 2, 16, 1.3, 13.9, 4.5, 2.0, 2.75, 0.13, 1.67, 2.0),
}


def authors_settings(architecture: str, dataset: str) -> dict:
    """The released code's stereo settings for an architecture and dataset
    (``"kitti"``, ``"kitti2015"`` or ``"mb"``), as Hyperparameters overrides."""
    try:
        return dict(AUTHORS[(architecture, dataset)])
    except KeyError:
        known = ", ".join(f"{a}/{d}" for a, d in AUTHORS)
        raise KeyError(f"no authors' settings for {architecture}/{dataset} (known: {known})") from None
