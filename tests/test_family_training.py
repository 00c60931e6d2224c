"""Training on several dataset families: the crop sampler's balance and per-dataset recipe.

Synthetic pairs (random texture shifted by a known constant disparity) stand for a KITTI, a
Middlebury and an ETH3D pair; what is checked is where crops come from and which offsets and
augmentation each pair's examples get.
"""

import numpy as np
import pytest

from mccnn_cl.evaluation.datasets import StereoPair
from mccnn_cl.errors import InputError
from mccnn_cl.train.crops import KITTI_AUGMENT, MIDDLEBURY_AUGMENT, CropSampler, pair_weights
from mccnn_cl.train.train import FAMILY_AUGMENT, FAMILY_OFFSETS, TrainConfig, crop_sampler


def _pair(kind, name, h, w, d, seed):
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (h, w + d), dtype=np.uint8)
    left, right = base[:, :w].copy(), base[:, d:].copy()  # left(x) = right(x - d)
    disp = np.full((h, w), np.float32(d))
    disp[:, :d + 4] = np.nan
    valid = np.isfinite(disp)
    return StereoPair(name=name, left=left, right=right, disp=disp, valid_noc=None, valid_all=valid,
                      ndisp=32, calib=None, kind=kind)


@pytest.fixture(scope="module")
def pairs():
    # a big KITTI pair, two small Middlebury pairs, one ETH3D pair
    return [_pair("kitti2015", "a", 120, 300, 7, 0), _pair("middlebury", "b", 60, 90, 5, 1),
            _pair("middlebury", "c", 60, 90, 5, 2), _pair("eth3d", "d_1s", 80, 120, 6, 3)]


def test_pair_weights():
    counts, ds = [800, 100, 100, 200], ["kitti", "middlebury", "middlebury", "eth3d"]
    np.testing.assert_allclose(pair_weights(counts, ds, "pixels"), np.array(counts) / 1200)
    np.testing.assert_allclose(pair_weights(counts, ds, "pixels", max_per_pair=150), [150, 100, 100, 150] / np.float64(500))
    np.testing.assert_allclose(pair_weights(counts, ds, "pair"), [0.25] * 4)
    np.testing.assert_allclose(pair_weights(counts, ds, "dataset"), [1 / 3, 1 / 6, 1 / 6, 1 / 3])
    # a pair without usable GT gets nothing and its dataset's share goes to the others
    np.testing.assert_allclose(pair_weights([800, 0, 0, 200], ds, "dataset"), [0.5, 0, 0, 0.5])
    with pytest.raises(InputError, match="balance"):
        pair_weights(counts, ds, "by-size")


def test_dataset_balance_draws_each_family_alike(pairs):
    s = CropSampler(pairs, 9, crop=(7, 7), spread=12, per_crop=4, balance="dataset")
    assert s.datasets == ["kitti", "middlebury", "middlebury", "eth3d"]
    b = s.sample(np.random.default_rng(0), 600)
    first = np.unique(b.crop.numpy(), return_index=True)[1]
    src = b.src["pair"][first]  # each crop's pair
    share = np.bincount(src, minlength=4) / len(src)
    np.testing.assert_allclose([share[0], share[1] + share[2], share[3]], [1 / 3] * 3, atol=0.06)
    # the default (by GT pixels) lets the big KITTI pair dominate
    b = CropSampler(pairs, 9, crop=(7, 7), spread=12, per_crop=4).sample(np.random.default_rng(0), 300)
    first = np.unique(b.crop.numpy(), return_index=True)[1]
    assert np.mean(b.src["pair"][first] == 0) > 0.6


def test_per_dataset_offsets_and_augmentation(pairs):
    cfg = TrainConfig(arch="fst", sampler="crop", subpixel=True, family_offsets=True, augment=True,
                      augment_preset="family", balance="pair", n_lo=4, n_hi=10, p_hi=1, crop=(9, 9), spread=16,
                      per_crop=64, negatives=3)
    s = crop_sampler(cfg, pairs, 9)
    assert s.pair_aug == [KITTI_AUGMENT, MIDDLEBURY_AUGMENT, MIDDLEBURY_AUGMENT, MIDDLEBURY_AUGMENT]
    assert s.pair_off == [FAMILY_OFFSETS["fst"][d] for d in ("kitti", "middlebury", "middlebury", "eth3d")]
    assert FAMILY_AUGMENT["eth3d"] is MIDDLEBURY_AUGMENT
    b = s.sample(np.random.default_rng(1), 80)
    pi, x, y, xp, xn = (b.src[k] for k in ("pair", "x", "y", "x_pos", "x_neg"))
    d = np.array([pairs[i].disp[int(yy), int(xx)] for i, xx, yy in zip(pi, x, y)])
    op, on = xp - (x - d), np.abs(xn - (x - d)[:, None])
    for i, (p_hi, n_lo, n_hi) in enumerate(s.pair_off):
        sel = pi == i
        assert sel.sum() > 50
        assert np.abs(op[sel]).max() <= p_hi + 1e-9 and np.abs(op[sel]).max() > 0.8 * p_hi
        assert on[sel].min() >= n_lo - 1e-9 and on[sel].max() <= n_hi + 1e-9
    with pytest.raises(InputError, match="integer mode"):
        crop_sampler(TrainConfig(arch="fst", sampler="crop", family_offsets=True), pairs, 9)
    paper = crop_sampler(TrainConfig(arch="paper", sampler="crop", subpixel=True, family_offsets=True), pairs, 9)
    assert paper.pair_off == [(1, 4, 8), (0.5, 1.5, 18), (0.5, 1.5, 18), (0.5, 1.5, 18)]


def test_arch_without_per_dataset_offsets_is_refused(pairs, monkeypatch):
    monkeypatch.delitem(FAMILY_OFFSETS, "paper")
    with pytest.raises(InputError, match="per-dataset offsets"):
        crop_sampler(TrainConfig(arch="paper", sampler="crop", subpixel=True, family_offsets=True), pairs, 9)
