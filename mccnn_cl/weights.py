"""The weights file format shared by the torch side and the OpenCL side.

Format ``mccnn_cl.weights`` is a NumPy ``.npz`` archive (readable without
torch and without pickle).  Version 2 names one of three architectures
(``ARCHITECTURES``), whose layer counts, widths and kernel sizes are read from
the arrays, never from constants:

``mccnn-paper``
    the CVPR 2015 network: conv layers with ReLU after each (tied between the
    two patches), the two feature vectors concatenated, fc layers with ReLU
    between them, 2 outputs and a softmax; cost = P(bad match) = softmax[0].
``mccnn-fst``
    JMLR 2016 MC-CNN-fst: conv layers with ReLU *between* them (none after
    the last), L2-normalised features, no fc layers; cost
    C(p, d) = -f_L(p) . f_R(p - d), in [-1, 1].
``mccnn-acrt``
    JMLR 2016 MC-CNN-acrt: conv layers with ReLU after each, concatenation,
    fc layers with ReLU between them, 1 output through a sigmoid, as in the
    released code; ``fc0`` splits like the paper's L4.  The cost is the
    sigmoid output itself: the released code trains it towards 0 on matching
    pairs and 1 on mismatches (``main.lua``: positive target 0), so it is a
    probability of a bad match in [0, 1], like the paper network's.

Version 1 files (no ``architecture`` other than ``mccnn-paper``) keep loading
as ``mccnn-paper``.  The archive holds:

``__meta__``
    a 0-d unicode array with a JSON object::

        {"format": "mccnn_cl.weights", "version": 2,
         "architecture": "mccnn-paper",          # or "mccnn-fst", "mccnn-acrt"
         "input_channels": 1,                     # gray patches
         "conv_layers": [[32, 5], [200, 5], [200, 1]],   # [maps, kernel] L1-L3
         "fc_layers": [300, 300, 300, 300, 2],    # L4..L8 (L4 sees 2*maps_L3)
         "patch_size": 9,                         # sum(k - 1) + 1
         "normalisation": "per_image_mean_std",   # (I - mean(I)) / std(I)
         "bad_match_class": 0,                    # paper: cost = softmax()[0]
         "stereo": {"sgm_pi2": 55.72, ...},       # optional: Hyperparameters
                                                  # the net was tuned with
         "source": "...", "licence": "...",       # optional: converted files
         "training": {...}}                       # free-form provenance

``stereo`` holds :class:`mccnn_cl.pipeline.Hyperparameters` field names and
values: the stereo-method settings the network was tuned with, which
``StereoMatcher(weights=...)`` uses unless the caller overrides them by name.

``conv{i}.weight`` / ``conv{i}.bias``
    float32, shapes ``(out, in, k, k)`` / ``(out,)``: the siamese layers L1..L3
    (ReLU after each; tied between the left and right patch).
``fc{i}.weight`` / ``fc{i}.bias``
    float32, shapes ``(out, in)`` / ``(out,)``: L4..L8 (ReLU after each but the
    last; the last has 2 outputs fed to a softmax, 1 output and a sigmoid for
    acrt, none at all for fst).  ``fc0.weight`` has ``in = 2 * maps``:
    columns ``[:maps]`` act on the left features, columns ``[maps:]`` on the
    right ones (the L4 split used at inference).
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from importlib import resources

import numpy as np

from .errors import WeightsError

FORMAT = "mccnn_cl.weights"
VERSION = 2
PAPER, FST, ACRT = "mccnn-paper", "mccnn-fst", "mccnn-acrt"
ARCHITECTURES = (PAPER, FST, ACRT)
#: outputs of the last fc layer per architecture (fst has no fc layers)
FC_OUTPUTS = {PAPER: 2, ACRT: 1}
PAPER_CONV = [[32, 5], [200, 5], [200, 1]]
PAPER_FC = [300, 300, 300, 300, 2]
#: The default network: general-fst (trained on KITTI, Middlebury, MiddEval3 and ETH3D), ahead of
#: kitti-fst on the held-out pairs of 3 of the 4 families and level on KITTI (model card,
#: docs/training.md); it matches a KITTI pair in seconds on 2 CPU cores.
DEFAULT_WEIGHTS_NAME = "general-fst.npz"
#: The paper's network (CVPR 2015 architecture), one flag away: ``--weights kitti-paper``.
PAPER_WEIGHTS_NAME = "kitti-paper.npz"
#: Earlier names of shipped files, still accepted by :func:`resolve`.
ALIASES = {"mccnn_kitti_mb_v1": "kitti-paper"}


@dataclass
class Weights:
    """Network weights plus metadata (see module docstring for the format)."""

    conv: list  # [(W (out,in,k,k), b (out,)), ...]
    fc: list  # [(W (out,in), b (out,)), ...]; [] for mccnn-fst
    meta: dict = field(default_factory=dict)
    architecture: str = PAPER

    # -- architecture facts ----------------------------------------------
    @property
    def relu_after_last_conv(self) -> bool:
        """ReLU after the last conv layer: paper and acrt yes, fst no."""
        return self.architecture != FST

    @property
    def stereo(self) -> dict:
        """Hyperparameters the network was tuned with (``meta["stereo"]``; may be empty)."""
        return dict(self.meta.get("stereo") or {})

    # -- shape facts ---------------------------------------------------
    @property
    def input_channels(self) -> int:
        return int(self.conv[0][0].shape[1])

    @property
    def patch_size(self) -> int:
        return 1 + sum(w.shape[2] - 1 for w, _ in self.conv)

    @property
    def margin(self) -> int:
        """Pixels lost on each side by the valid convolutions: (patch_size - 1) // 2."""
        return (self.patch_size - 1) // 2

    @property
    def feature_maps(self) -> int:
        return int(self.conv[-1][0].shape[0])

    def conv_layers(self) -> list:
        return [[int(w.shape[0]), int(w.shape[2])] for w, _ in self.conv]

    def fc_layers(self) -> list:
        return [int(w.shape[0]) for w, _ in self.fc]

    def num_parameters(self) -> int:
        return int(sum(w.size + b.size for w, b in self.conv + self.fc))

    # -- validation ----------------------------------------------------
    def validate(self, source: str = "weights") -> "Weights":
        """Check that the layer shapes chain into a valid network of ``architecture``."""
        arch = self.architecture
        if arch not in ARCHITECTURES:
            raise WeightsError(f"{source}: architecture {arch!r} is not supported "
                               f"(expected one of {', '.join(ARCHITECTURES)})")
        if not self.conv:
            raise WeightsError(f"{source}: needs at least one conv layer")
        if arch == FST and self.fc:
            raise WeightsError(f"{source}: an {FST} network has no fc layers, found {len(self.fc)}")
        if arch != FST and not self.fc:
            raise WeightsError(f"{source}: an {arch} network needs at least one fc layer")
        cin = None
        for i, (w, b) in enumerate(self.conv):
            if w.ndim != 4 or w.shape[2] != w.shape[3] or b.shape != (w.shape[0],):
                raise WeightsError(f"{source}: conv{i} has shapes {w.shape}/{b.shape}")
            if w.shape[2] % 2 == 0 or min(w.shape) < 1:  # an even kernel has no centre pixel
                raise WeightsError(f"{source}: conv{i} has shape {w.shape}: kernels must be odd-sized "
                                   "(1, 3, 5, ...) and every size at least 1")
            if cin is not None and w.shape[1] != cin:
                raise WeightsError(f"{source}: conv{i} expects {w.shape[1]} inputs, previous layer gives {cin}")
            cin = w.shape[0]
        fin = 2 * cin
        for i, (w, b) in enumerate(self.fc):
            if w.ndim != 2 or b.shape != (w.shape[0],) or w.shape[1] != fin or w.shape[0] < 1:
                raise WeightsError(f"{source}: fc{i} has shapes {w.shape}/{b.shape}, expected (*, {fin})")
            fin = w.shape[0]
        if arch != FST and fin != FC_OUTPUTS[arch]:
            what = "softmax over good/bad" if arch == PAPER else "sigmoid"
            raise WeightsError(f"{source}: last layer has {fin} outputs, expected {FC_OUTPUTS[arch]} "
                               f"({what}) for {arch}")
        if not isinstance(self.meta.get("stereo", {}), dict):
            raise WeightsError(f"{source}: metadata 'stereo' must be an object of hyperparameters")
        for w, b in self.conv + self.fc:
            if w.dtype != np.float32 or b.dtype != np.float32:
                raise WeightsError(f"{source}: arrays must be float32")
            if not (np.isfinite(w).all() and np.isfinite(b).all()):
                raise WeightsError(f"{source}: non-finite weights")
        return self

    # -- I/O -------------------------------------------------------------
    def full_meta(self) -> dict:
        meta = {
            "format": FORMAT,
            "version": VERSION,
            "architecture": self.architecture,
            "input_channels": self.input_channels,
            "conv_layers": self.conv_layers(),
            "fc_layers": self.fc_layers(),
            "patch_size": self.patch_size,
            "normalisation": "per_image_mean_std",
        }
        if self.architecture == PAPER:
            meta["bad_match_class"] = 0
        meta.update({k: v for k, v in self.meta.items() if k not in meta})
        return meta

    def save(self, path) -> None:
        """Write the ``.npz`` atomically (temporary file, then rename)."""
        self.validate()
        arrays = {"__meta__": np.array(json.dumps(self.full_meta(), sort_keys=True))}
        for i, (w, b) in enumerate(self.conv):
            arrays[f"conv{i}.weight"], arrays[f"conv{i}.bias"] = w, b
        for i, (w, b) in enumerate(self.fc):
            arrays[f"fc{i}.weight"], arrays[f"fc{i}.bias"] = w, b
        from .atomic import atomic_write

        def write(tmp):
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
        atomic_write(path, write)

    @classmethod
    def load(cls, path=None) -> "Weights":
        """Read and validate a weights file; ``None`` loads the shipped model."""
        if path is None:
            path = default_weights_path()
        path = os.fspath(path)
        if not os.path.exists(path):
            raise WeightsError(f"weights file not found: {path}")
        if not zipfile.is_zipfile(path):
            raise WeightsError(f"{path}: not a readable mccnn_cl weights file "
                               "(not an .npz archive: truncated, or another kind of file)")
        try:
            with np.load(path, allow_pickle=False) as z:
                files = dict((k, z[k]) for k in z.files)
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise WeightsError(f"{path}: not a readable mccnn_cl weights file ({exc})") from exc
        if "__meta__" not in files:
            raise WeightsError(f"{path}: no __meta__ entry; not a mccnn_cl weights file")
        try:
            meta = json.loads(str(files["__meta__"]))
        except ValueError as exc:
            raise WeightsError(f"{path}: corrupt metadata ({exc})") from exc
        _check_meta(meta, path)
        if int(meta.get("version", -1)) > VERSION:
            raise WeightsError(f"{path}: format version {meta.get('version')} is newer than this "
                               f"mccnn_cl understands ({VERSION}); upgrade mccnn_cl")
        arch = meta.get("architecture", PAPER)
        if arch not in ARCHITECTURES:
            raise WeightsError(f"{path}: architecture {arch!r} is not supported "
                               f"(expected one of {', '.join(ARCHITECTURES)})")
        conv, fc = [], []
        try:
            for i in range(len(meta["conv_layers"])):
                conv.append((files[f"conv{i}.weight"], files[f"conv{i}.bias"]))
            for i in range(len(meta.get("fc_layers", []))):
                fc.append((files[f"fc{i}.weight"], files[f"fc{i}.bias"]))
        except KeyError as exc:
            raise WeightsError(f"{path}: missing array {exc}") from exc
        w = cls(conv=conv, fc=fc, meta=meta, architecture=arch).validate(path)
        if w.conv_layers() != meta["conv_layers"] or w.fc_layers() != meta.get("fc_layers", []):
            raise WeightsError(f"{path}: arrays disagree with the metadata's layer sizes")
        for key, have in (("patch_size", w.patch_size), ("input_channels", w.input_channels)):
            if key in meta and meta[key] != have:
                raise WeightsError(f"{path}: metadata {key} {meta[key]} disagrees with the arrays' {have}")
        if meta.get("bad_match_class", 0) != 0:  # the kernels read softmax()[0] as the cost
            raise WeightsError(f"{path}: bad_match_class {meta['bad_match_class']!r}: only 0 (the paper's "
                               "f_neg as the first output) is supported; reorder the last layer's rows")
        if meta.get("normalisation", "per_image_mean_std") != "per_image_mean_std":
            raise WeightsError(f"{path}: normalisation {meta['normalisation']!r}: only per_image_mean_std "
                               "(each image's mean and std) is supported")
        from .hyperparameters import check_settings
        check_settings(w, source=path)  # the stereo settings: known names, in range
        return w

    @classmethod
    def random(cls, conv_layers=None, fc_layers=None, input_channels=1, seed=0,
               architecture: str = PAPER) -> "Weights":
        """Random weights (He-style scale, small random biases) for tests and benchmarks.

        Defaults per architecture: the paper's layers; fst 4 conv 3x3 of 64
        maps (KITTI); acrt 4 conv 3x3 of 112 maps and fc [384] * 4 + [1]."""
        if architecture == FST:
            conv_layers = conv_layers or [[64, 3]] * 4
            fc_layers = []
        elif architecture == ACRT:
            conv_layers = conv_layers or [[112, 3]] * 4
            fc_layers = fc_layers or [384, 384, 384, 384, 1]
        else:
            conv_layers = conv_layers or PAPER_CONV
            fc_layers = fc_layers or PAPER_FC
        rng = np.random.default_rng(seed)
        conv, fc = [], []
        cin = input_channels
        for maps, k in conv_layers:
            fan = cin * k * k
            conv.append((rng.normal(0, np.sqrt(2.0 / fan), (maps, cin, k, k)).astype(np.float32),
                         rng.normal(0, 0.1, maps).astype(np.float32)))
            cin = maps
        fin = 2 * cin
        for out in fc_layers:
            fc.append((rng.normal(0, np.sqrt(2.0 / fin), (out, fin)).astype(np.float32),
                       rng.normal(0, 0.1, out).astype(np.float32)))
            fin = out
        return cls(conv=conv, fc=fc, meta={"training": {"note": f"random, seed {seed}"}},
                   architecture=architecture).validate()


def _check_meta(meta, path) -> None:
    """The metadata's types, so that a malformed file is one WeightsError (never
    a TypeError from deeper down): an object; ``format``; ``version`` an
    integer; ``architecture`` a string; ``conv_layers`` a list of [maps, kernel]
    integer pairs; ``fc_layers`` a list of integers; ``stereo`` an object;
    ``patch_size`` / ``input_channels`` integers when present."""
    def is_int(v):
        return isinstance(v, int) and not isinstance(v, bool)

    if not isinstance(meta, dict):
        raise WeightsError(f"{path}: corrupt metadata (a JSON {type(meta).__name__}, expected an object)")
    if meta.get("format") != FORMAT:
        raise WeightsError(f"{path}: format {meta.get('format')!r}, expected {FORMAT!r}")
    problems = []
    if "version" in meta and not is_int(meta["version"]):
        problems.append(f"version {meta['version']!r} is not an integer")
    if "architecture" in meta and not isinstance(meta["architecture"], str):
        problems.append(f"architecture {meta['architecture']!r} is not a name")
    conv = meta.get("conv_layers")
    if not (isinstance(conv, list) and all(isinstance(c, list) and len(c) == 2 and all(map(is_int, c))
                                           for c in conv)):
        problems.append(f"conv_layers {conv!r} is not a list of [maps, kernel] integer pairs")
    fc = meta.get("fc_layers", [])
    if not (isinstance(fc, list) and all(map(is_int, fc))):
        problems.append(f"fc_layers {fc!r} is not a list of integers")
    if not isinstance(meta.get("stereo", {}), dict):
        problems.append("stereo is not an object of hyperparameters")
    for key in ("patch_size", "input_channels"):
        if key in meta and not is_int(meta[key]):
            problems.append(f"{key} {meta[key]!r} is not an integer")
    if problems:
        text = "; ".join(problems)
        raise WeightsError(f"{path}: malformed metadata: {text[:300]}")


def default_weights_path() -> str:
    """Path of the weights shipped inside the package."""
    ref = resources.files("mccnn_cl.models") / DEFAULT_WEIGHTS_NAME
    return str(ref)


def shipped_models() -> dict:
    """Shipped networks: name (the file's stem) -> path, from ``mccnn_cl/models``."""
    root = resources.files("mccnn_cl.models")
    return {os.path.splitext(f.name)[0]: str(f) for f in sorted(root.iterdir(), key=lambda f: f.name)
            if f.name.endswith(".npz")}


def __getattr__(name):
    """``mccnn_cl.weights.resolve``, the documented name, kept for callers:
    :func:`mccnn_cl.models.resolve` (which converts .t7/.pt through
    :mod:`mccnn_cl.importers`, themselves built on this module, so it is not
    imported from here at import time)."""
    if name == "resolve":
        import importlib

        return importlib.import_module("mccnn_cl.models").resolve
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
