"""Importers of published networks, on the real files of the shared models folder.

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
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest

from mccnn_cl.cli import main
from mccnn_cl.errors import WeightsError
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
#: (and MCCNN_MODELS unset) skips these tests with this reason (-rs lists it),
#: as conftest skips the full_data tests without MCCNN_DATA
pytestmark = pytest.mark.skipif(not MODELS.is_dir(), reason=f"needs the published networks: set MCCNN_MODELS "
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
    assert training_status(w.meta, "kitti2012/000193", "000193") == "trained"
    assert training_status(w.meta, "kitti2015/000000", "000000") == "held out"


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


def test_t7_reader_needs_no_torch(tmp_path):
    code = ("import sys; sys.modules['torch'] = None\n"
            "from mccnn_cl.importers import convert\n"
            f"w = convert({str(T7)!r}); assert w.architecture == 'mccnn-fst'; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr


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


@pytest.mark.parametrize("frac", [0.0005, 0.003, 0.2, 0.5, 0.9, 0.9999])
def test_t7_truncated(t7_bytes, tmp_path, frac):
    one_error(_damage(tmp_path, t7_bytes[:int(len(t7_bytes) * frac)]), "expected")


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


def test_t7_other_modules(t7_bytes, tmp_path):
    # same-length substitutions keep the file parseable; the network check names what it found
    msg = one_error(_damage(tmp_path, t7_bytes.replace(b"cudnn.ReLU", b"nn.Sigmoid", 1)), "expected an nn.Sequential")
    assert "found SpatialConvolution, Sigmoid" in msg
    one_error(_damage(tmp_path, t7_bytes.replace(b"nn.Normalize2", b"nn.Normalize1")), "Normalize1")
    # a ReLU after the last conv is not MC-CNN-fst
    msg = one_error(_damage(tmp_path, t7_bytes.replace(b"13\nnn.Normalize2", b"10\ncudnn.ReLU", 1)), "expected")
    assert "found SpatialConvolution, ReLU" in msg and msg.endswith("SpatialConvolution, ReLU, StereoJoin")


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


def test_pt_round_trip(acrt_weights, tmp_path):
    acrt_weights.save(tmp_path / "acrt.npz")
    back = Weights.load(tmp_path / "acrt.npz")
    assert back.architecture == ACRT and back.stereo == acrt_weights.stereo
    for (a, b), (c, d) in zip(back.conv + back.fc, acrt_weights.conv + acrt_weights.fc):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, d)
    assert back.meta["source"]["sha256"] == acrt_weights.meta["source"]["sha256"]


def test_restricted_unpickler_reads_the_real_files(torch, state_dicts):
    for p in (FAST_PT, ACRT_PT):
        ck = torch.load(p, map_location="cpu", weights_only=False, pickle_module=pytorch.restricted)
        assert ck["model"].keys() == state_dicts[p].keys()
        assert all(torch.equal(ck["model"][k], v) for k, v in state_dicts[p].items())


def test_pt_fallback_for_numpy_scalars(torch, state_dicts, tmp_path):
    """torch's weights_only refuses numpy scalars; the allow-list reads them."""
    p = tmp_path / "np.pt"
    torch.save({"model": state_dicts[FAST_PT], "epoch": np.int64(3)}, p)
    with pytest.raises(pickle.UnpicklingError):
        torch.load(p, map_location="cpu", weights_only=True)
    w = convert(p)
    assert w.architecture == FST and w.meta["training"]["epoch"] == 3


class Payload:
    """A class of this test module: unpickling it would import and build it."""

    def __reduce__(self):
        return (os.getcwd, ())


def test_pt_foreign_global_refused_by_name(torch, state_dicts, tmp_path):
    p = tmp_path / "evil.pt"
    torch.save({"model": state_dicts[FAST_PT], "extra": Payload()}, p)
    one_error(p, "posix.getcwd", "not allowed")
    p2 = tmp_path / "evil2.pt"
    torch.save({"model": state_dicts[FAST_PT], "extra": OrderedDict(a=sys.modules[__name__].Payload)}, p2)
    one_error(p2, "Payload", "not allowed")


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


@pytest.mark.parametrize("cut", [0, 10, 700, 100000, -50])
def test_pt_truncated(torch, tmp_path, cut):
    data = FAST_PT.read_bytes()
    p = _damage(tmp_path, data[:cut] if cut else b"", "cut.pt")
    one_error(p, "empty file" if cut == 0 else "expected a CNES mc-cnn checkpoint")


def test_pt_damaged_and_random(torch, tmp_path):
    data = bytearray(FAST_PT.read_bytes())
    data[0] ^= 0xFF  # the pickle's first opcode
    one_error(_damage(tmp_path, data, "flip.pt"), "not a readable PyTorch checkpoint", "expected a CNES")
    rng = np.random.default_rng(2)
    one_error(_damage(tmp_path, rng.integers(0, 256, 4096, dtype=np.uint8).tobytes(), "rnd.pt"),
              "not a readable PyTorch checkpoint")


def test_pt_without_torch(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)
    one_error(FAST_PT, "needs PyTorch")


def test_other_extensions(tmp_path):
    one_error(_damage(tmp_path, b"x", "net.caffemodel"), "expected a Torch7 .t7 or a PyTorch .pt")
    one_error(tmp_path / "missing.t7", "not found")


# -- resolve and the command line ---------------------------------------------------

def test_resolve_converts_published_files(t7_bytes):
    w = resolve(str(T7))
    assert w.architecture == FST and w.meta["dataset"] == "kitti"
    name = next(iter(shipped_models()))
    assert resolve(name).meta.get("format") == "mccnn_cl.weights"


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


def test_cli_models(capsys):
    assert main(["models"]) == 0
    text = capsys.readouterr().out
    for name, path in shipped_models().items():
        w = Weights.load(path)
        assert f"{name}: {w.architecture}, {w.num_parameters():,} parameters" in text
    lines = text.strip().splitlines()
    assert len(lines) == 2 * len(shipped_models()) and all(l.startswith("    ") for l in lines[1::2])
    assert "no description" not in text


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


def test_describe_lines(acrt_weights):
    text = "\n".join(commands.describe(acrt_weights))
    assert "5 x 112 maps 3x3 (ReLU after each)" in text and "[384, 384, 384, 1]" in text and "11x11" in text
