"""Importers of published networks, on the real files of the shared models folder
(skipped with a reason without them) and on small synthetic .t7/.pt files written
here (run everywhere): dataset identification from a .t7's name and stored options,
licence and authorship by sha256, multi-channel networks refused.

The authors' Torch7 MC-CNN-fst (KITTI 2012) and CNES's PyTorch fast and
accurate Middlebury nets convert to Weights whose arrays are checked against
readings that do not go through the importers: the .t7's storages parsed
straight from its text, and torch's own Conv2d/Linear modules built in the CNES
layout from the checkpoint's state_dict.  Damaged copies of the real files,
other networks, other files and pickles that need foreign globals each give
one WeightsError that says what was expected.
"""

import os
import pickle
import re
import subprocess
import sys
import warnings
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest

from mccnn_cl.cli import main
from mccnn_cl.errors import InputWarning, WeightsError
from mccnn_cl.cli import convert as commands
from mccnn_cl.importers import convert, pytorch, torch7
from mccnn_cl.settings import authors_settings
from mccnn_cl.weights import ACRT, FST, Weights, resolve, shipped_models

REPO = Path(__file__).resolve().parents[1]


def models_folder() -> Path:
    """The published networks' folder, as conftest treats ``$MCCNN_DATA``:
    ``$MCCNN_MODELS`` when set (``.ci/run`` sets ``../shared/models``), and then
    it must exist (a usage error otherwise, never a skip); unset, the
    ``../shared/models`` of a checkout beside ``../shared``."""
    value = os.environ.get("MCCNN_MODELS")
    if not value:
        return REPO.parent / "shared" / "models"
    p = Path(value).resolve()
    if not p.is_dir():
        raise pytest.UsageError(f"MCCNN_MODELS={value}: no such folder")
    return p


MODELS = models_folder()
#: the published networks are not in the repository: a clone without ../shared
#: (and MCCNN_MODELS unset) skips the tests that read them with this reason (-rs
#: lists it), as conftest skips the full_data tests without MCCNN_DATA; the
#: tests on small synthetic .t7/.pt files run everywhere
needs_models = pytest.mark.skipif(not MODELS.is_dir(), reason=f"needs the published networks: set MCCNN_MODELS "
                                  f"to their folder (CI: ../shared/models); {MODELS} not found")
T7 = MODELS / "net_kitti_fast_-a_train_all.t7"
FAST_PT = MODELS / "cnes_mccnn_1.4.1" / "mc_cnn_fast_mb_weights.pt"
ACRT_PT = MODELS / "cnes_mccnn_1.4.1" / "mc_cnn_accurate_mb_weights.pt"


@pytest.fixture(scope="module")
def t7_bytes():
    if not T7.is_file():
        pytest.fail(f"shared model files not found at {MODELS}; set MCCNN_MODELS")
    return T7.read_bytes()


@pytest.fixture(scope="module")
def t7_weights(t7_bytes):
    return convert(T7)


@pytest.fixture(scope="module")
def torch():
    """torch (the train extra, which the set-up installs): missing, the .pt tests fail, never skip."""
    try:
        import torch
    except ImportError as exc:
        pytest.fail(f"the .pt importer tests need torch, which the set-up installs (bash scripts/setup.sh: "
                    f"torch and the train extra); import failed: {exc}", pytrace=False)
    return torch


@pytest.fixture(scope="module")
def fast_weights(torch):
    return convert(FAST_PT)


@pytest.fixture(scope="module")
def acrt_weights(torch):
    return convert(ACRT_PT)


@pytest.fixture(scope="module")
def state_dicts(torch):
    return {p: torch.load(p, map_location="cpu", weights_only=True)["model"] for p in (FAST_PT, ACRT_PT)}


def one_error(path, *words, dataset=None):
    """Converting ``path`` raises exactly one WeightsError mentioning ``words``."""
    with pytest.raises(WeightsError) as info:
        convert(path, dataset=dataset)
    msg = str(info.value)
    assert type(info.value) is WeightsError and "\n" not in msg, msg
    for w in words:
        assert w in msg, msg
    return msg


# -- numpy forward passes of converted weights (independent of the importers) ------

def tower(weights, img):
    """Valid 3x3 convs in float64; ReLU between layers (and after the last for acrt)."""
    x = np.asarray(img, np.float64)[None] if img.ndim == 2 else np.asarray(img, np.float64)
    for i, (W, b) in enumerate(weights.conv):
        k = W.shape[2]
        win = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(1, 2))  # (C, h, w, k, k)
        x = np.tensordot(W.astype(np.float64), win, axes=([1, 2, 3], [0, 3, 4])) + b[:, None, None]
        if i < len(weights.conv) - 1 or weights.relu_after_last_conv:
            x = np.maximum(x, 0)
    return x  # (maps, h, w)


def head(weights, fl, fr):
    x = np.concatenate([fl, fr])
    for i, (W, b) in enumerate(weights.fc):
        x = W.astype(np.float64) @ x + b
        if i < len(weights.fc) - 1:
            x = np.maximum(x, 0)
    return 1 / (1 + np.exp(-x))


# -- Torch7 .t7 --------------------------------------------------------------------

@needs_models
def test_t7_converts_to_fst(t7_weights):
    w = t7_weights
    assert w.architecture == FST and w.fc == [] and not w.relu_after_last_conv
    assert w.conv_layers() == [[64, 3]] * 4
    assert w.input_channels == 1 and w.patch_size == 9
    assert all(np.isfinite(W).all() and np.isfinite(b).all() for W, b in w.conv)
    assert w.num_parameters() == 64 * 10 + 3 * (64 * 64 * 9 + 64)
    assert w.meta["stereo"] == authors_settings(FST, "kitti")
    assert w.meta["source"]["file"] == T7.name and len(w.meta["source"]["sha256"]) == 64
    assert w.meta["source"]["padding"] == [[1, 1]] * 4
    assert "BSD-2-Clause" in w.meta["licence"] and "importers.torch7" in w.meta["converted_by"]
    # the file's own options are the settings table's kitti fst column
    opts = w.meta["training"]["options"]
    s = w.meta["stereo"]
    assert (opts["pi1"], opts["pi2"], opts["sgm_q1"], opts["sgm_q2"], opts["alpha1"], opts["tau_so"],
            opts["blur_sigma"], opts["blur_t"]) == (s["sgm_pi1"], s["sgm_pi2"], s["sgm_q1"], s["sgm_q2"],
                                                    s["sgm_v"], s["sgm_tau_so"], s["blur_sigma"], s["blur_tau"])
    assert opts["color"] == "gray" and opts["fm"] == 64 and opts["l1"] == 4
    # -a train_all: every KITTI 2012 training pair, so evaluate can say which pairs it saw
    from mccnn_cl.evaluation.scoring import training_status

    assert opts["a"] == "train_all" and len(w.meta["training"]["trained_on"]) == 194
    assert isinstance(w.meta["training"]["trained_on"], dict)  # the project's form: pair key -> description
    assert training_status(w.meta, "kitti2012/000193", "000193") == "trained"
    assert training_status(w.meta, "kitti2015/000000", "000000") == "held out"


@needs_models
def test_t7_arrays_equal_the_storages_in_the_text(t7_bytes, t7_weights):
    """Every CudaStorage, parsed from the text with a regex, is one converted array, in order."""
    found = []
    for m in re.finditer(rb"torch\.CudaStorage\n(\d+)\n([^\n]*)\n", t7_bytes):
        values = np.array(m.group(2).split(), dtype=np.float64).astype(np.float32)
        assert values.size == int(m.group(1))
        found.append(values)
    arrays = [a for W, b in t7_weights.conv for a in (W, b)]
    assert [v.size for v in found] == [a.size for a in arrays] == [576, 64, 36864, 64] + [36864, 64] * 2
    for v, a in zip(found, arrays):
        np.testing.assert_array_equal(v, a.ravel())  # weight (out, in, kH, kW) is contiguous in Torch7
    assert t7_weights.conv[0][0].std() > 0.1  # not zeros: the first layer's filters are large


@needs_models
def test_t7_tree(t7_bytes):
    root = torch7.read_t7(T7)
    assert isinstance(root, torch7.T7Table) and set(root) == {1.0, 2.0}
    mods = root[1.0].fields["modules"]
    assert [mods[float(i)].class_name for i in range(1, 10)] == (
        ["cudnn.SpatialConvolution", "cudnn.ReLU"] * 3 + ["cudnn.SpatialConvolution", "nn.Normalize2", "nn.StereoJoin"])
    conv = mods[1.0].fields
    assert conv["weight"].size == (64, 1, 3, 3) and conv["weight"].storage.class_name == "torch.CudaStorage"
    fn = conv["accUpdateGradParameters"]
    assert isinstance(fn, torch7.T7Function) and fn.bytecode.startswith(b"\x1bLJ")  # LuaJIT, kept as bytes


@needs_models
def test_t7_reader_needs_no_torch(tmp_path):
    code = ("import sys; sys.modules['torch'] = None\n"
            "from mccnn_cl.importers import convert\n"
            f"w = convert({str(T7)!r}); assert w.architecture == 'mccnn-fst'; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr


@needs_models
def test_t7_dataset_override_and_round_trip(t7_bytes, t7_weights, tmp_path):
    w = convert(T7, dataset="kitti2015")
    assert w.meta["dataset"] == "kitti2015" and w.stereo == authors_settings(FST, "kitti2015")
    w.save(tmp_path / "fst.npz")
    back = Weights.load(tmp_path / "fst.npz")
    assert back.architecture == FST and back.stereo == w.stereo and back.meta["source"] == w.meta["source"]
    for (a, b), (c, d) in zip(back.conv, t7_weights.conv):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, d)
    one_error(T7, "dataset 'sintel'", "kitti", dataset="sintel")


def _damage(tmp_path, data, name="bad.t7"):
    p = tmp_path / name
    p.write_bytes(bytes(data))
    return p


@needs_models
@pytest.mark.parametrize("frac", [0.0005, 0.003, 0.2, 0.5, 0.9, 0.9999])
def test_t7_truncated(t7_bytes, tmp_path, frac):
    one_error(_damage(tmp_path, t7_bytes[:int(len(t7_bytes) * frac)]), "expected")


@needs_models
def test_t7_damaged_header_and_numbers(t7_bytes, tmp_path):
    one_error(_damage(tmp_path, b"9" + t7_bytes[1:]), "type tag", "out of range")
    one_error(_damage(tmp_path, t7_bytes.replace(b"nn.Sequential", b"nn.Sequentia!", 1)), "class name")
    i = t7_bytes.index(b"torch.CudaStorage\n576\n")  # first layer's weights
    one_error(_damage(tmp_path, t7_bytes.replace(b"torch.CudaStorage\n576\n", b"torch.CudaStorage\n577\n", 1)),
              "expected 577 numbers, found 576")
    j = t7_bytes.index(b".", i + 30)
    one_error(_damage(tmp_path, t7_bytes[:j] + b"x" + t7_bytes[j + 1:]), "not a number")
    # the weight tensor claims 65 output maps: its storage of 576 floats is too short
    one_error(_damage(tmp_path, t7_bytes.replace(b"torch.CudaTensor\n4\n64 1 3 3\n",
                                                 b"torch.CudaTensor\n4\n65 1 3 3\n", 1)),
              "weight", "storage of 576")


@needs_models
def test_t7_other_modules(t7_bytes, tmp_path):
    # same-length substitutions keep the file parseable; the network check names what it found
    msg = one_error(_damage(tmp_path, t7_bytes.replace(b"cudnn.ReLU", b"nn.Sigmoid", 1)), "expected an nn.Sequential")
    assert "found SpatialConvolution, Sigmoid" in msg
    one_error(_damage(tmp_path, t7_bytes.replace(b"nn.Normalize2", b"nn.Normalize1")), "Normalize1")
    # a ReLU after the last conv is not MC-CNN-fst
    msg = one_error(_damage(tmp_path, t7_bytes.replace(b"13\nnn.Normalize2", b"10\ncudnn.ReLU", 1)), "expected")
    assert "found SpatialConvolution, ReLU" in msg and msg.endswith("SpatialConvolution, ReLU, StereoJoin")


@needs_models
def test_t7_not_a_network(tmp_path, t7_bytes):
    one_error(_damage(tmp_path, b""), "empty file")
    rng = np.random.default_rng(1)
    one_error(_damage(tmp_path, rng.integers(0, 256, 5000, dtype=np.uint8).tobytes()), "not a Torch7")
    # a valid Torch7 file holding a table of numbers, and one holding a lone FloatTensor
    one_error(_damage(tmp_path, b"3\n1\n1\n1\n1\n1\n2.5\n"), "expected an nn.Sequential",
              "holds a table whose first entry is a float")
    one_error(_damage(tmp_path, b"4\n1\n3\nV 1\n17\ntorch.FloatTensor\n1\n2\n1\n1\n4\n2\n3\nV 1\n"
                                b"18\ntorch.FloatStorage\n2\n1.5 2.5\n"), "holds torch.FloatTensor")
    # a back-reference to an object that was never written
    one_error(_damage(tmp_path, b"3\n1\n1\n1\n1\n4\n7\n"), "refers to no object")


@needs_models
def test_t7_random_damage_only_weights_errors(t7_bytes, tmp_path):
    """Random cuts, deletions and byte changes: a WeightsError or (in float digits) a valid network."""
    rng = np.random.default_rng(7)
    for trial in range(24):
        b = bytearray(t7_bytes)
        i = int(rng.integers(0, 15000 if trial % 2 else len(b)))
        if trial % 3 == 0:
            b = b[:i]
        elif trial % 3 == 1:
            b[i] = int(rng.integers(0, 256))
        else:
            del b[i:i + int(rng.integers(1, 40))]
        try:
            with warnings.catch_warnings():  # one that still converts is not the published file
                warnings.simplefilter("ignore", InputWarning)
                convert(_damage(tmp_path, b))
        except WeightsError as exc:
            assert "\n" not in str(exc)


# -- PyTorch .pt ---------------------------------------------------------------------

def cnes_modules(torch, sd):
    """The CNES layout rebuilt from a state_dict with torch modules (ReLU at the odd indices)."""
    nn = torch.nn
    convs = sorted({int(k.split(".")[1]) for k in sd if k.startswith("conv_blocks.")})
    fls = sorted({int(k.split(".")[1]) for k in sd if k.startswith("fl_blocks.")})
    layers = []
    for i in convs:
        w = sd[f"conv_blocks.{i}.weight"]
        layers += [nn.Conv2d(w.shape[1], w.shape[0], w.shape[2]), nn.ReLU()]
    if not fls:
        layers = layers[:-1]  # FastMcCnn ends on a Conv2d
    conv = nn.Sequential(*layers)
    conv.load_state_dict({k[len("conv_blocks."):]: v for k, v in sd.items() if k.startswith("conv_blocks.")})
    fc = None
    if fls:
        lin = []
        for i in fls:
            w = sd[f"fl_blocks.{i}.weight"]
            lin += [nn.Linear(w.shape[1], w.shape[0]), nn.ReLU()]
        fc = nn.Sequential(*lin[:-1], nn.Sigmoid())
        fc.load_state_dict({k[len("fl_blocks."):]: v for k, v in sd.items() if k.startswith("fl_blocks.")})
    return conv.double(), (fc.double() if fc is not None else None)


@needs_models
def test_fast_pt(fast_weights, state_dicts, torch):
    w = fast_weights
    assert w.architecture == FST and w.conv_layers() == [[64, 3]] * 5 and w.fc == []
    assert w.input_channels == 1 and w.patch_size == 11
    assert w.stereo == authors_settings(FST, "mb") and "Apache-2.0" in w.meta["licence"]
    conv, _ = cnes_modules(torch, state_dicts[FAST_PT])
    rng = np.random.default_rng(3)
    img = rng.normal(size=(23, 31))  # a random image: every 11x11 patch of it
    with torch.no_grad():
        ref = torch.nn.functional.normalize(conv(torch.from_numpy(img)[None, None]), p=2, dim=1)[0].numpy()
    ours = tower(w, img)
    ours /= np.linalg.norm(ours, axis=0, keepdims=True)
    assert ours.shape == ref.shape == (64, 13, 21)
    np.testing.assert_allclose(ours, ref, atol=1e-6)


@needs_models
def test_accurate_pt(acrt_weights, state_dicts, torch):
    w = acrt_weights
    assert w.architecture == ACRT and w.relu_after_last_conv
    assert w.conv_layers() == [[112, 3]] * 5 and w.fc_layers() == [384, 384, 384, 1]
    assert w.input_channels == 1 and w.patch_size == 11 and w.stereo == authors_settings(ACRT, "mb")
    conv, fc = cnes_modules(torch, state_dicts[ACRT_PT])
    rng = np.random.default_rng(4)
    for _ in range(3):
        left, right = rng.normal(size=(2, 11, 11))
        with torch.no_grad():
            fl = conv(torch.from_numpy(left)[None, None])
            fr = conv(torch.from_numpy(right)[None, None])
            ref = fc(torch.cat((fl, fr), dim=1).flatten(1))[0, 0].item()  # CNES: P(match)
        ours_l, ours_r = tower(w, left), tower(w, right)
        np.testing.assert_allclose(ours_l[:, 0, 0], fl[0, :, 0, 0].numpy(), atol=1e-6)
        cost = head(w, ours_l[:, 0, 0], ours_r[:, 0, 0])[0]  # mccnn-acrt: P(bad match)
        assert abs(cost - (1 - ref)) < 1e-6
    # the [left; right] order matters: swapping the patches changes the output
    assert abs(head(w, ours_l[:, 0, 0], ours_r[:, 0, 0])[0] - head(w, ours_r[:, 0, 0], ours_l[:, 0, 0])[0]) > 1e-4


@needs_models
def test_pt_round_trip(acrt_weights, tmp_path):
    acrt_weights.save(tmp_path / "acrt.npz")
    back = Weights.load(tmp_path / "acrt.npz")
    assert back.architecture == ACRT and back.stereo == acrt_weights.stereo
    for (a, b), (c, d) in zip(back.conv + back.fc, acrt_weights.conv + acrt_weights.fc):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, d)
    assert back.meta["source"]["sha256"] == acrt_weights.meta["source"]["sha256"]


@needs_models
def test_restricted_unpickler_reads_the_real_files(torch, state_dicts):
    for p in (FAST_PT, ACRT_PT):
        ck = torch.load(p, map_location="cpu", weights_only=False, pickle_module=pytorch.restricted)
        assert ck["model"].keys() == state_dicts[p].keys()
        assert all(torch.equal(ck["model"][k], v) for k, v in state_dicts[p].items())


@needs_models
def test_pt_fallback_for_numpy_scalars(torch, state_dicts, tmp_path):
    """torch's weights_only refuses numpy scalars; the allow-list reads them."""
    p = tmp_path / "np.pt"
    torch.save({"model": state_dicts[FAST_PT], "epoch": np.int64(3)}, p)
    with pytest.raises(pickle.UnpicklingError):
        torch.load(p, map_location="cpu", weights_only=True)
    w = quiet_convert(p, dataset="mb")  # not the published file: its dataset is the user's to say
    assert w.architecture == FST and w.meta["training"]["epoch"] == 3


class Payload:
    """A class of this test module: unpickling it would import and build it."""

    def __reduce__(self):
        return (os.getcwd, ())


@needs_models
def test_pt_foreign_global_refused_by_name(torch, state_dicts, tmp_path):
    p = tmp_path / "evil.pt"
    torch.save({"model": state_dicts[FAST_PT], "extra": Payload()}, p)
    one_error(p, "posix.getcwd", "not allowed")
    p2 = tmp_path / "evil2.pt"
    torch.save({"model": state_dicts[FAST_PT], "extra": OrderedDict(a=sys.modules[__name__].Payload)}, p2)
    one_error(p2, "Payload", "not allowed")


@needs_models
def test_pt_other_networks(torch, state_dicts, tmp_path):
    nn = torch.nn

    def save(obj):
        p = tmp_path / "other.pt"
        torch.save(obj, p)
        return p

    net = nn.Sequential(nn.Conv2d(1, 8, 3), nn.BatchNorm2d(8), nn.Conv2d(8, 8, 3))
    one_error(save({"model": net.state_dict()}), "expected a CNES mc-cnn checkpoint", "0.weight")
    one_error(save([1, 2, 3]), "expected a CNES mc-cnn checkpoint", "found a list")
    sd = dict(state_dicts[ACRT_PT])
    del sd["fl_blocks.6.weight"], sd["fl_blocks.6.bias"]
    one_error(save({"model": sd}), "384 outputs, expected 1")
    sd = dict(state_dicts[FAST_PT])
    sd["conv_blocks.10.weight"], sd["conv_blocks.10.bias"] = sd.pop("conv_blocks.8.weight"), sd.pop("conv_blocks.8.bias")
    one_error(save({"model": sd}), "indices [0, 2, 4, 6, 10], expected [0, 2, 4, 6, 8]")
    sd = dict(state_dicts[FAST_PT])
    sd["conv_blocks.4.weight"] = sd["conv_blocks.4.weight"][:32]
    sd["conv_blocks.4.bias"] = sd["conv_blocks.4.bias"][:32]
    one_error(save({"model": sd}), "conv_blocks.6.weight", "previous layer's 32 maps")
    sd = dict(state_dicts[ACRT_PT])
    sd["fl_blocks.0.weight"] = sd["fl_blocks.0.weight"][:, :112]
    one_error(save({"model": sd}), "expected (*, 224)", "[left; right]")
    sd = dict(state_dicts[FAST_PT])
    sd["conv_blocks.0.weight"] = torch.full_like(sd["conv_blocks.0.weight"], float("nan"))
    one_error(save({"model": sd}), "non-finite")


@needs_models
@pytest.mark.parametrize("cut", [0, 10, 700, 100000, -50])
def test_pt_truncated(torch, tmp_path, cut):
    data = FAST_PT.read_bytes()
    p = _damage(tmp_path, data[:cut] if cut else b"", "cut.pt")
    one_error(p, "empty file" if cut == 0 else "expected a CNES mc-cnn checkpoint")


@needs_models
def test_pt_damaged_and_random(torch, tmp_path):
    data = bytearray(FAST_PT.read_bytes())
    data[0] ^= 0xFF  # the pickle's first opcode
    one_error(_damage(tmp_path, data, "flip.pt"), "not a readable PyTorch checkpoint", "expected a CNES")
    rng = np.random.default_rng(2)
    one_error(_damage(tmp_path, rng.integers(0, 256, 4096, dtype=np.uint8).tobytes(), "rnd.pt"),
              "not a readable PyTorch checkpoint")


@needs_models
def test_pt_without_torch(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)
    one_error(FAST_PT, "needs PyTorch")


@needs_models
def test_other_extensions(tmp_path):
    one_error(_damage(tmp_path, b"x", "net.caffemodel"), "expected a Torch7 .t7 or a PyTorch .pt")
    one_error(tmp_path / "missing.t7", "not found")


# -- resolve and the command line ---------------------------------------------------

@needs_models
def test_resolve_converts_published_files(t7_bytes):
    w = resolve(str(T7))
    assert w.architecture == FST and w.meta["dataset"] == "kitti"
    name = next(iter(shipped_models()))
    assert resolve(name).meta.get("format") == "mccnn_cl.weights"


@needs_models
def test_cli_convert_weights(tmp_path, capsys, t7_bytes):
    out = tmp_path / "kitti_fst.npz"
    assert main(["convert-weights", str(T7), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    for words in ("architecture: mccnn-fst", "4 x 64 maps 3x3", "ReLU between", "9x9", "111,424",
                  "dataset kitti", "BSD-2-Clause", f"wrote:        {out}"):
        assert words in text, text
    assert Weights.load(out).architecture == FST
    assert main(["convert-weights", str(T7), "-o", str(out), "--dataset", "mb"]) == 2  # exists
    assert "exists" in capsys.readouterr().err
    assert main(["convert-weights", str(T7), "-o", str(out), "--dataset", "mb", "--force"]) == 0
    assert Weights.load(out).stereo == authors_settings(FST, "mb")
    assert main(["convert-weights", str(T7), "-o", str(tmp_path / "x.bin")]) == 2
    bad = _damage(tmp_path, t7_bytes[:5000])
    assert main(["convert-weights", str(bad), "-o", str(tmp_path / "y.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and err[-1].startswith("mccnn-cl: error:") and "Torch7" in err[-1], err
    assert not (tmp_path / "y.npz").exists()


@needs_models
def test_cli_models(capsys):
    assert main(["models"]) == 0
    text = capsys.readouterr().out
    for name, path in shipped_models().items():
        w = Weights.load(path)
        assert f"{name}: {w.architecture}, {w.num_parameters():,} parameters" in text
    lines = text.strip().splitlines()
    assert len(lines) == 2 * len(shipped_models()) and all(l.startswith("    ") for l in lines[1::2])
    assert "no description" not in text


@needs_models
def test_cli_weights_option_resolves(t7_bytes, tmp_path):
    """--weights takes a .t7, a shipped model's name, or fails in one line for an unknown name."""
    from mccnn_cl.cli import build_parser
    from mccnn_cl.cli.commands import _load_weights

    p = build_parser()
    args = p.parse_args(["match", "l.png", "r.png", "-o", "o.pfm", "--weights", str(T7)])
    assert _load_weights(args).architecture == FST
    name = next(iter(shipped_models()))
    args = p.parse_args(["bench", "--weights", name])
    assert _load_weights(args).meta["format"] == "mccnn_cl.weights"
    args = p.parse_args(["evaluate", str(tmp_path), "--weights", "no_such_model"])
    with pytest.raises(WeightsError, match="no weights file or shipped model named 'no_such_model'"):
        _load_weights(args)


@needs_models
def test_describe_lines(acrt_weights):
    text = "\n".join(commands.describe(acrt_weights))
    assert "5 x 112 maps 3x3 (ReLU after each)" in text and "[384, 384, 384, 1]" in text and "11x11" in text


# -- small synthetic networks (no published file needed) --------------------------------
#
# A Torch7 ASCII writer for the tests: the format as the module docstring of
# mccnn_cl/importers/torch7.py describes it (type tag, object index, "V 1" and
# class name for torch objects, tensors' sizes / strides / 1-based offset, then
# their storage).  The authors' settings columns are written literally from the
# shared models README, not taken from the package.

#: main.lua's stored options of the authors' fst networks (README table), per dataset
FST_OPTIONS = {
    "kitti": dict(pi1=4.0, pi2=55.72, sgm_q1=3.0, sgm_q2=2.5, alpha1=1.5, tau_so=0.02, blur_sigma=7.74, blur_t=5.0),
    "kitti2015": dict(pi1=2.3, pi2=18.38, sgm_q1=3.0, sgm_q2=2.0, alpha1=1.25, tau_so=0.08, blur_sigma=4.64,
                      blur_t=5.0),
    "mb": dict(pi1=2.3, pi2=24.3, sgm_q1=4.0, sgm_q2=2.0, alpha1=1.5, tau_so=0.08, blur_sigma=6.0, blur_t=2.0),
}


class Mod:
    """A torch object to write: class name and fields."""

    def __init__(self, cls, **fields):
        self.cls, self.fields = cls, fields


def t7_text(obj) -> bytes:
    out, count = [], [0]

    def index():
        count[0] += 1
        return b"%d\n" % count[0]

    def string(b):
        out.append(b"%d\n" % len(b) + b + b"\n")

    def write(v):
        if v is None:
            out.append(b"0\n")
        elif isinstance(v, bool):
            out.append(b"5\n%d\n" % int(v))
        elif isinstance(v, (int, float)):
            out.append(b"1\n" + repr(float(v)).encode() + b"\n")
        elif isinstance(v, str):
            out.append(b"2\n")
            string(v.encode())
        elif isinstance(v, dict):
            out.append(b"3\n" + index() + b"%d\n" % len(v))
            for k, x in v.items():
                write(k)
                write(x)
        elif isinstance(v, np.ndarray):
            a = np.ascontiguousarray(v, np.float32)
            out.append(b"4\n" + index())
            string(b"V 1")
            string(b"torch.FloatTensor")
            out.append(b"%d\n%s\n%s\n1\n" % (a.ndim, " ".join(map(str, a.shape)).encode(),
                                             " ".join(str(st // 4) for st in a.strides).encode()))
            out.append(b"4\n" + index())
            string(b"V 1")
            string(b"torch.FloatStorage")
            out.append(b"%d\n%s\n" % (a.size, " ".join(repr(float(x)) for x in a.ravel()).encode()))
        elif isinstance(v, Mod):
            out.append(b"4\n" + index())
            string(b"V 1")
            string(v.cls.encode())
            write(v.fields)
        else:
            raise TypeError(v)

    write(obj)
    return b"".join(out)


def fst_t7(path, options, maps=(8, 8), channels=1, seed=0):
    """A main.lua-style file {net, opt} of a small MC-CNN-fst: 3x3 convs of ``maps``, ReLU between."""
    rng = np.random.default_rng(seed)
    mods, cin = [], channels
    for i, m in enumerate(maps):
        mods.append(Mod("cudnn.SpatialConvolution", weight=rng.normal(size=(m, cin, 3, 3)),
                        bias=rng.normal(size=m), nInputPlane=cin, nOutputPlane=m, kW=3, kH=3, dW=1, dH=1,
                        padW=1, padH=1))
        if i < len(maps) - 1:
            mods.append(Mod("cudnn.ReLU"))
        cin = m
    mods += [Mod("nn.Normalize2"), Mod("nn.StereoJoin1")]
    net = Mod("nn.Sequential", modules={float(i + 1): m for i, m in enumerate(mods)})
    path = Path(path)
    path.write_bytes(t7_text({1.0: net, 2.0: dict(options)}))
    return path


def cnes_pt(torch, path, channels=1, maps=(8, 8), seed=0):
    """A checkpoint in CNES's FastMcCnn layout (conv_blocks.0/2/..., ReLU at the odd indices)."""
    g = torch.Generator().manual_seed(seed)
    sd, cin = OrderedDict(), channels
    for i, m in enumerate(maps):
        sd[f"conv_blocks.{2 * i}.weight"] = torch.randn(m, cin, 3, 3, generator=g)
        sd[f"conv_blocks.{2 * i}.bias"] = torch.randn(m, generator=g)
        cin = m
    torch.save({"model": sd, "epoch": 7}, path)
    return Path(path)


def quiet_convert(path, **kw):
    """convert() of a file that is not one of the published networks: it warns so (checked here)."""
    with pytest.warns(InputWarning, match="not one of the published networks"):
        return convert(path, **kw)


def test_synthetic_t7_reads_back(tmp_path):
    """The writer above makes files the reader reads as written (the tests below rely on it)."""
    p = fst_t7(tmp_path / "net_kitti_fast_-a_train_all.t7", dict(FST_OPTIONS["kitti"], a="train_all"))
    w = quiet_convert(p)
    rng = np.random.default_rng(0)
    W0 = rng.normal(size=(8, 1, 3, 3))
    np.testing.assert_array_equal(w.conv[0][0], W0.astype(np.float32))
    assert w.conv_layers() == [[8, 3], [8, 3]] and w.meta["training"]["options"]["pi2"] == 55.72


def test_t7_dataset_from_its_stored_options(tmp_path):
    """A .t7 whose name is not main.lua's gets the dataset its stored options identify (kitti2015
    here, the old importer said kitti for every such name), with that dataset's training pairs."""
    from mccnn_cl.evaluation.scoring import training_status

    for ds, pairs in (("kitti2015", ("kitti2015", 200)), ("mb", None), ("kitti", ("kitti2012", 194))):
        p = fst_t7(tmp_path / f"mynet_{ds}.t7", dict(FST_OPTIONS[ds], a="train_all", L1=0.0, cbca_i1=0.0))
        w = quiet_convert(p)
        assert w.meta["dataset"] == ds and w.stereo == authors_settings(FST, ds), ds
        assert f"authors' {ds} column" in w.meta["dataset_source"]
        t = w.meta["training"]
        if pairs is None:  # Middlebury: no fixed list of pairs to name
            assert "trained_on" not in t and t["data"].startswith("Middlebury")
        else:
            kind, n = pairs
            assert isinstance(t["trained_on"], dict) and len(t["trained_on"]) == n
            assert training_status(w.meta, f"{kind}/000001", "000001") == "trained"
    # the name alone (main.lua's) identifies it too, when the options are none of the columns
    p = fst_t7(tmp_path / "net_kitti2015_fast_-a_train_all.t7", dict(FST_OPTIONS["kitti2015"], pi2=30.0))
    w = quiet_convert(p)
    assert w.meta["dataset"] == "kitti2015" and "file name" in w.meta["dataset_source"]


def test_t7_name_and_options_must_agree(tmp_path):
    p = fst_t7(tmp_path / "net_mb_fast_-a_train_all.t7", dict(FST_OPTIONS["kitti"], a="train_all"))
    msg = one_error(p, "file name says dataset mb", "kitti column")
    assert "pi1 = 4, pi2 = 55.72" in msg
    # same options under a name that agrees: converted
    q = fst_t7(tmp_path / "net_kitti_fast_-a_train_all.t7", dict(FST_OPTIONS["kitti"], a="train_all"))
    assert quiet_convert(q).meta["dataset"] == "kitti"


def test_t7_that_identifies_no_dataset_needs_one(tmp_path, capsys):
    """No main.lua name, options of no column: an error asking for --dataset (not kitti by default);
    given, it sets the settings but lists no training pairs (the file does not say them)."""
    opts = dict(FST_OPTIONS["kitti"], pi1=3.0, pi2=30.0, a="train_all")
    p = fst_t7(tmp_path / "mynet.t7", opts)
    one_error(p, "not known", "none of the authors' columns", "--dataset kitti|kitti2015|mb")
    w = quiet_convert(p, dataset="kitti")
    assert w.meta["dataset"] == "kitti" and w.stereo == authors_settings(FST, "kitti")
    assert "given by the user" in w.meta["dataset_source"]
    assert "trained_on" not in w.meta["training"] and w.meta["training"]["data"].startswith("unknown")
    fst_t7(tmp_path / "bare.t7", {})  # no options at all
    one_error(tmp_path / "bare.t7", "no pi1 and pi2", "--dataset")
    # the command line: one error line without --dataset, converted with it
    out = tmp_path / "mine.npz"
    assert main(["convert-weights", str(p), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--dataset" in err[0] and not out.exists(), err
    assert main(["convert-weights", str(p), "-o", str(out), "--dataset", "kitti2015"]) == 0
    text = capsys.readouterr()
    assert "dataset kitti2015" in text.out and "given by the user" in text.out
    assert Weights.load(out).stereo == authors_settings(FST, "kitti2015")


def test_unknown_files_have_unknown_licence_and_author(tmp_path, capsys):
    """Licence and authorship come from the sha256 of the published files, not from the extension:
    any other .t7 / .pt is 'unknown', and the console says so."""
    from mccnn_cl.importers import UNKNOWN_LICENCE

    p = fst_t7(tmp_path / "net_kitti_fast_-a_train_all.t7", dict(FST_OPTIONS["kitti"], a="train_all"))
    w = quiet_convert(p)
    assert w.meta["licence"] == UNKNOWN_LICENCE and "state the licence" in w.meta["licence"]
    assert w.meta["training"]["by"].startswith("unknown") and "Zbontar" not in str(w.meta["training"])
    assert w.meta["source"]["published"] is None and "Zbontar" not in w.meta["source"]["what"]
    assert main(["convert-weights", str(p), "-o", str(tmp_path / "o.npz")]) == 0
    text = capsys.readouterr()
    assert "licence:      unknown" in text.out and "BSD" not in text.out
    assert "warning:" in text.err and "state the licence of your network yourself" in text.err


def test_unknown_pt_has_unknown_licence(tmp_path, torch):
    p = cnes_pt(torch, tmp_path / "mine.pt")
    one_error(p, "not known", "--dataset")  # a checkpoint says nothing of its dataset
    w = quiet_convert(p, dataset="mb")
    from mccnn_cl.importers import UNKNOWN_LICENCE

    assert w.meta["licence"] == UNKNOWN_LICENCE and "Apache" not in w.meta["licence"]
    assert w.meta["training"]["by"].startswith("unknown") and "CNES" not in w.meta["training"]["by"]
    assert w.meta["training"]["epoch"] == 7 and w.stereo == authors_settings(FST, "mb")


def test_multichannel_networks_are_refused(tmp_path, torch):
    """A first layer of 3 input channels (CNES's DataFusion variants, colour .t7) is not the gray
    network mccnn_cl runs: one error naming the channel count."""
    msg = one_error(cnes_pt(torch, tmp_path / "fusion3.pt", channels=3), "3 input channels", "1 gray channel",
                    dataset="mb")
    assert "conv_blocks.0.weight" in msg
    one_error(fst_t7(tmp_path / "net_kitti_fast_-a_train_all.t7", FST_OPTIONS["kitti"], channels=3),
              "3 input channels")
    # one channel converts
    assert quiet_convert(cnes_pt(torch, tmp_path / "gray.pt"), dataset="mb").input_channels == 1


def test_folders_are_named_as_folders(tmp_path, capsys):
    (tmp_path / "x.t7").mkdir()
    msg = one_error(tmp_path / "x.t7", "is a folder")
    assert "not found" not in msg
    # convert-weights -o a folder: refused before converting, --force or not
    (tmp_path / "out.npz").mkdir()
    p = fst_t7(tmp_path / "net_kitti_fast_-a_train_all.t7", FST_OPTIONS["kitti"])
    assert main(["convert-weights", str(p), "-o", str(tmp_path / "out.npz"), "--force"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a folder" in err[0], err


@needs_models
def test_published_files_are_recognised_by_sha256(t7_bytes, tmp_path):
    """The published .t7 under another name is still the authors' (kitti, BSD-2-Clause, its 194
    pairs); the same file with one weight's digit changed is not: unknown licence and author."""
    from mccnn_cl.importers import BSD2, UNKNOWN_LICENCE

    renamed = _damage(tmp_path, t7_bytes, "mynet.t7")
    w = convert(renamed)
    assert w.meta["licence"] == BSD2 and "Zbontar" in w.meta["training"]["by"]
    assert w.meta["source"]["published"] == T7.name and len(w.meta["training"]["trained_on"]) == 194
    i = t7_bytes.index(b"torch.CudaStorage\n576\n") + len(b"torch.CudaStorage\n576\n")
    j = next(k for k in range(i, i + 40) if t7_bytes[k:k + 1].isdigit() and t7_bytes[k + 1:k + 2].isdigit())
    changed = bytearray(t7_bytes)
    changed[j + 1] = ord("7") if changed[j + 1] != ord("7") else ord("3")
    w2 = quiet_convert(_damage(tmp_path, changed, "net_kitti_fast_-a_train_all.t7"))
    assert w2.meta["licence"] == UNKNOWN_LICENCE and w2.meta["training"]["by"].startswith("unknown")
    assert w2.meta["dataset"] == "kitti"  # the name and the options still say kitti


@needs_models
def test_published_copies_with_other_options(t7_bytes, tmp_path):
    """The authors' .t7 with its stored options changed to the kitti2015 column (a name main.lua did
    not write): kitti2015, not the old importer's kitti; saved as net_mb_...: an error."""
    src = t7_bytes
    for k, v in {b"pi1": b"2.3", b"pi2": b"18.38", b"sgm_q2": b"2", b"alpha1": b"1.25", b"tau_so": b"0.08",
                 b"blur_sigma": b"4.64"}.items():
        pat = re.compile(b"\n2\n%d\n%s\n1\n([^\n]+)\n" % (len(k), k))
        assert len(pat.findall(src)) == 1, k
        src = pat.sub(lambda m: b"\n2\n%d\n%s\n1\n%s\n" % (len(k), k, v), src)
    w = quiet_convert(_damage(tmp_path, src, "kitti2015_fast.t7"))
    assert w.meta["dataset"] == "kitti2015" and w.stereo == authors_settings(FST, "kitti2015")
    one_error(_damage(tmp_path, t7_bytes, "net_mb_fast_-a_train_all.t7"), "file name says dataset mb")
