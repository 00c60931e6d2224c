"""OpenCV's semi-global block matching (StereoSGBM), the yardstick beside MC-CNN.

Parameters (:func:`sgbm_parameters`), chosen as OpenCV's documentation and
its ``stereo_match`` sample recommend and fixed so that comparisons are
repeatable:

* ``blockSize`` 5 (matching window 5×5);
* ``P1 = 8·cn·blockSize²``, ``P2 = 32·cn·blockSize²`` (cn = image channels),
  the smoothness penalties the docs suggest;
* ``uniquenessRatio`` 10 %, ``speckleWindowSize`` 100 px, ``speckleRange`` 2
  (×16 internally), ``disp12MaxDiff`` 1 px, ``preFilterCap`` 63;
* ``mode = MODE_SGBM_3WAY`` (the fast 3-way variant of full SGBM);
* ``minDisparity`` 0 and the *same* disparity range as MC-CNN: OpenCV wants
  ``numDisparities`` to be a multiple of 16, so it is rounded up and any
  disparity ≥ ``max_disparity`` is then marked invalid.

The output follows :mod:`mccnn_cl.evaluation.metrics`' conventions: float32 pixels,
NaN where SGBM gives no disparity (its left border of ``numDisparities``
columns, failed uniqueness / left-right checks, removed speckles).
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from ..errors import InputError

__all__ = ["sgbm_parameters", "sgbm", "SGBM_DESCRIPTION"]

SGBM_DESCRIPTION = ("OpenCV StereoSGBM, MODE_SGBM_3WAY, blockSize 5, P1 = 8·cn·5², P2 = 32·cn·5², "
                    "uniqueness 10, speckle 100/2, disp12MaxDiff 1")


def sgbm_parameters(max_disparity, channels=1, block_size=5, min_disparity=0) -> dict:
    """Keyword arguments of ``cv2.StereoSGBM_create`` used by :func:`sgbm`."""
    max_disparity = int(max_disparity)
    if max_disparity < 1:
        raise InputError(f"disparity range must be >= 1, got {max_disparity}")
    num = ((max_disparity + 15) // 16) * 16
    cn = int(channels)
    return dict(minDisparity=int(min_disparity), numDisparities=num, blockSize=block_size,
                P1=8 * cn * block_size ** 2, P2=32 * cn * block_size ** 2,
                disp12MaxDiff=1, preFilterCap=63, uniquenessRatio=10,
                speckleWindowSize=100, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def sgbm(left, right, max_disparity, block_size=5, return_time=False, min_disparity=0):
    """Disparity of ``left`` against ``right`` (8-bit gray or BGR) with OpenCV StereoSGBM.

    Returns float32 (H, W) disparities in pixels, NaN where invalid; with
    ``return_time`` also the seconds the matching took.  ``min_disparity``:
    the range is min_disparity .. min_disparity + max_disparity - 1.
    """
    left = np.ascontiguousarray(left)
    right = np.ascontiguousarray(right)
    if left.shape != right.shape:
        raise InputError(f"left {left.shape} and right {right.shape} images differ in size")
    if left.dtype != np.uint8 or right.dtype != np.uint8:
        raise InputError("sgbm: images must be 8-bit")
    channels = 1 if left.ndim == 2 else left.shape[2]
    params = sgbm_parameters(max_disparity, channels, block_size, min_disparity)
    if params["numDisparities"] >= left.shape[1]:
        raise InputError(f"disparity range {params['numDisparities']} (rounded up to a multiple of 16 "
                         f"for SGBM) is not smaller than the image width {left.shape[1]}")
    matcher = cv2.StereoSGBM_create(**params)
    t0 = time.perf_counter()
    try:
        raw = matcher.compute(left, right)
    except cv2.error as exc:
        raise InputError(f"OpenCV StereoSGBM failed: {str(exc).strip().splitlines()[-1]}") from exc
    seconds = time.perf_counter() - t0
    disp = raw.astype(np.float32) / np.float32(16.0)
    disp[(disp < min_disparity) | (disp > min_disparity + max_disparity - 1)] = np.nan
    return (disp, seconds) if return_time else disp
