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


def test_even_or_empty_kernels_and_contradicting_metadata_are_rejected(tmp_path):
    """An even kernel has no centre pixel: the cost's volume would be one row and column smaller than
    the matcher reads (a scrambled volume, no error); zero-size layers ended in a raw OpenCL error.
    Metadata that contradicts the arrays, or a bad-match class the kernels do not read, is refused."""
    import json
    w = Weights.random(conv_layers=[[4, 3], [6, 3]], fc_layers=[5, 2], seed=2)
    even = Weights(conv=[(np.zeros((4, 1, 2, 2), np.float32), np.zeros(4, np.float32)), w.conv[1]],
                   fc=w.fc, meta=dict(w.meta), architecture=w.architecture)
    with pytest.raises(WeightsError, match="odd-sized"):
        even.validate()
    empty = Weights(conv=[(np.zeros((0, 1, 3, 3), np.float32), np.zeros(0, np.float32))], fc=w.fc,
                    meta=dict(w.meta), architecture=w.architecture)
    with pytest.raises(WeightsError, match="at least 1"):
        empty.validate()
    path = tmp_path / "w.npz"
    w.save(path)
    Weights.load(path)
    files = dict(np.load(path))
    for change, words in (({"bad_match_class": 1}, "bad_match_class"), ({"patch_size": 7}, "patch_size"),
                          ({"normalisation": "none"}, "normalisation")):
        meta = {**json.loads(str(files["__meta__"])), **change}
        np.savez(tmp_path / "bad.npz", **{**files, "__meta__": np.array(json.dumps(meta))})
        with pytest.raises(WeightsError, match=words):
            Weights.load(tmp_path / "bad.npz")
