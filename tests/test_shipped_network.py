"""The shipped, trained checkpoint gives the same cost volume in torch and in OpenCL."""

import cv2
import numpy as np

from mccnn_cl.reference.network import cost_volume_torch
from mccnn_cl.stages.network import NetworkCost
from mccnn_cl.weights import Weights


def test_trained_weights_torch_vs_opencl(ctx, shared_data):
    w = Weights.load()  # the shipped model
    assert w.meta.get("training"), "shipped weights carry their provenance"
    # a held-out pair (KITTI 2015 000000), a textured crop: road, car and background
    left = cv2.imread(str(shared_data / "kitti2015/training/image_2/000000_10.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(shared_data / "kitti2015/training/image_3/000000_10.png"), cv2.IMREAD_GRAYSCALE)
    left, right = left[180:228, 500:580].astype(np.float32), right[180:228, 500:580].astype(np.float32)
    assert left.std() > 5 and right.std() > 5
    D = 24
    ref = cost_volume_torch(w, left, right, D)
    d_out = ctx.empty(ref.nbytes)
    ctx.fill(d_out, np.float32(-1.2345e30), ref.nbytes)
    NetworkCost(ctx, w)(left, right, D, out=d_out)
    got = ctx.from_device(d_out, ref.shape)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    ok = ~np.isnan(ref)
    # trained weights give costs spread over [0, 1] (not a constant answer)
    assert ref[ok].min() < 0.05 and ref[ok].max() > 0.95
    # 1e-4: float32 sums of up to 800 products in a different order; observed ~1e-6
    np.testing.assert_allclose(got[ok], ref[ok], rtol=0, atol=1e-4)
