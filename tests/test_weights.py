"""The weights format: round trip, validation, torch export."""

import numpy as np
import pytest
import torch

from mccnn_cl.errors import WeightsError
from mccnn_cl.train.model import MCCNN
from mccnn_cl.weights import Weights


def test_round_trip_and_torch_export(tmp_path):
    torch.manual_seed(3)
    model = MCCNN()
    assert sum(p.numel() for p in model.parameters()) > 500_000  # "almost 600 thousand"
    w = model.to_weights({"training": {"note": "test"}})
    path = tmp_path / "w.npz"
    w.save(path)
    back = Weights.load(path)
    assert back.patch_size == 9 and back.margin == 4 and back.feature_maps == 200
    assert back.meta["training"] == {"note": "test"}
    for (a, b), (c, d) in zip(w.conv + w.fc, back.conv + back.fc):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, d)
    m2 = MCCNN.from_weights(back)
    x = torch.randn(4, 1, 9, 9), torch.randn(4, 1, 9, 9)
    torch.testing.assert_close(model(*x), m2(*x), rtol=0, atol=0)
    assert model(*x).shape == (4, 2)


def test_truncated_and_foreign_files(tmp_path):
    w = Weights.random(seed=1)
    path = tmp_path / "w.npz"
    w.save(path)
    data = path.read_bytes()
    (tmp_path / "trunc.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(WeightsError):
        Weights.load(tmp_path / "trunc.npz")
    np.savez(tmp_path / "foreign.npz", a=np.zeros(3))
    with pytest.raises(WeightsError, match="__meta__"):
        Weights.load(tmp_path / "foreign.npz")
    with pytest.raises(WeightsError, match="not found"):
        Weights.load(tmp_path / "missing.npz")


def test_shape_mismatch_is_rejected():
    w = Weights.random(conv_layers=[[4, 3], [6, 3]], fc_layers=[5, 2], seed=2)
    w.fc[0] = (w.fc[0][0][:, :-1].copy(), w.fc[0][1])
    with pytest.raises(WeightsError, match="fc0"):
        w.validate()
