"""The shipped, trained networks give the same cost volume on the device as
their references (torch for the paper network, numpy for fst), and the
default is the fst network."""

import pytest
import cv2
import numpy as np

from mccnn_cl.reference.network import cost_volume_torch, fst_cost_volume
from mccnn_cl.settings import authors_settings
from mccnn_cl.costs.registry import make_cost
from mccnn_cl.costs.network import NetworkCost
from mccnn_cl.weights import FST, PAPER, Weights, resolve, shipped_models


def _kitti_crop(shared_data):
    # a held-out pair (KITTI 2015 000000), a textured crop: road, car and background
    left = cv2.imread(str(shared_data / "kitti2015/training/image_2/000000_10.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(shared_data / "kitti2015/training/image_3/000000_10.png"), cv2.IMREAD_GRAYSCALE)
    left, right = left[180:228, 500:580].astype(np.float32), right[180:228, 500:580].astype(np.float32)
    assert left.std() > 5 and right.std() > 5
    return left, right


def _on_device(ctx, cost, left, right, D, ref):
    """``cost``'s volume on the device into a poisoned buffer, the NaN cells checked
    against ``ref``; returns (device values, reference values) of the valid cells."""
    d_out = ctx.empty(ref.nbytes)
    ctx.fill(d_out, np.float32(-1.2345e30), ref.nbytes)
    cost(left, right, D, out=d_out)
    got = ctx.from_device(d_out, ref.shape)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    ok = ~np.isnan(ref)
    return got[ok], ref[ok]


def test_shipped_names_and_default():
    models = shipped_models()
    assert {"general-fst", "general-paper", "kitti-fst", "kitti-paper"} <= set(models)
    assert Weights.load().architecture == FST  # the default: general-fst (README, model card)
    assert Weights.load().meta["name"] == "general-fst"
    assert resolve("kitti-paper").architecture == PAPER
    assert resolve("mccnn_kitti_mb_v1").architecture == PAPER  # the paper net's earlier name


def test_general_fst_provenance():
    """general-fst: trained on every family, whole scene families held out of it (and of the kitti-fst
    it started from), carrying the authors' fst Middlebury settings with CBCA after SGM (chosen on training
    pairs, docs/training.md)."""
    from mccnn_cl.evaluation.datasets import dataset_of, scene_family
    w = resolve("general-fst")
    t = w.meta["training"]
    held, trained = set(t["held_out"]), set(t["trained_on"])
    assert not held & trained and t["init"]["name"] == "kitti-fst"
    assert {dataset_of(k) for k in trained} == {dataset_of(k) for k in held} == {"kitti", "middlebury", "middeval3",
                                                                               "eth3d"}
    assert not {scene_family(k) for k in held} & {scene_family(k) for k in trained}  # families held out whole
    assert {"kitti2015/000000", "middlebury/Cones", "middlebury/Cloth1", "eth3d/delivery_area_2s"} <= held
    assert w.stereo == dict(authors_settings(FST, "mb"), cbca_eta=5, cbca_tau=0.03, cbca_iterations_after=4)
    assert "cbca_iterations_after=4" in w.meta["stereo_source"]


def test_general_paper_provenance():
    """general-paper: the paper's network fine-tuned from kitti-paper on every family with general-fst's
    held-out families; its lineage (kitti-paper v1) saw two held-out Middlebury scenes, Cloth3 and Reindeer
    (MODEL_CARD.md), and no other held-out pair; the acrt KITTI 2015 CBCA with the acrt Middlebury SGM
    penalties and bilateral filter, chosen on training pairs."""
    from mccnn_cl.evaluation.datasets import dataset_of, scene_family
    w = resolve("general-paper")
    assert w.architecture == PAPER
    t = w.meta["training"]
    held, run = set(t["held_out"]), set(t["trained_on_this_run"])
    assert t["init"]["name"] == "kitti-paper" and held == set(resolve("general-fst").meta["training"]["held_out"])
    assert {dataset_of(k) for k in run} == {"kitti", "middlebury", "middeval3", "eth3d"}
    assert not {scene_family(k) for k in held} & {scene_family(k) for k in run}  # this run: families held out whole
    assert held & set(t["trained_on"]) == {"middlebury/Cloth3", "middlebury/Reindeer"}  # the lineage's
    k15, mb = authors_settings("mccnn-acrt", "kitti2015"), authors_settings("mccnn-acrt", "mb")
    groups = {"sgm_pi1", "sgm_pi2", "sgm_q1", "sgm_v", "sgm_tau_so", "blur_sigma", "blur_tau"}
    assert w.stereo == {k: (mb[k] if k in groups else v) for k, v in k15.items()}
    assert w.stereo["cbca_iterations_after"] == k15["cbca_iterations_after"] == 4  # not mb's 16 passes
    assert "chosen on 12 training pairs" in w.meta["stereo_source"]


@pytest.mark.slow
def test_shipped_fst_opencl_vs_reference(ctx, shared_data):
    w = resolve("kitti-fst")
    t = w.meta["training"]
    assert {"kitti2015/000000", "middlebury/Cones"} <= set(t["held_out"])
    assert not set(t["held_out"]) & set(t["trained_on"])
    assert w.stereo == authors_settings(FST, "kitti")  # the settings travel with the file
    left, right = _kitti_crop(shared_data)
    D = 24
    got, want = _on_device(ctx, make_cost(ctx, w), left, right, D, fst_cost_volume(w, left, right, D))
    # trained fst features: costs spread over most of [-1, 1] (not a constant answer)
    assert want.min() < -0.9 and want.max() > 0.0
    # 2e-5: float32 dot products of 64 unit-vector terms and 4 conv layers in another order
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5)


def test_trained_weights_torch_vs_opencl(ctx, shared_data):
    w = resolve("kitti-paper")  # the shipped paper network
    assert w.meta.get("training"), "shipped weights carry their provenance"
    left, right = _kitti_crop(shared_data)
    D = 24
    got, want = _on_device(ctx, NetworkCost(ctx, w), left, right, D, cost_volume_torch(w, left, right, D))
    # trained weights give costs spread over [0, 1] (not a constant answer)
    assert want.min() < 0.05 and want.max() > 0.95
    # 1e-4: float32 sums of up to 800 products in a different order; observed ~1e-6
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-4)
