"""The weights file format shared by the torch side and the OpenCL side.

Format ``mccnn_cl.weights`` version 1 is a NumPy ``.npz`` archive (readable
without torch and without pickle) holding:

``__meta__``
    a 0-d unicode array with a JSON object::

        {"format": "mccnn_cl.weights", "version": 1,
         "architecture": "mccnn-paper",          # the CVPR 2015 8-layer net
         "input_channels": 1,                     # gray patches
         "conv_layers": [[32, 5], [200, 5], [200, 1]],   # [maps, kernel] L1-L3
         "fc_layers": [300, 300, 300, 300, 2],    # L4..L8 (L4 sees 2*maps_L3)
         "patch_size": 9,                         # sum(k - 1) + 1
         "normalisation": "per_image_mean_std",   # (I - mean(I)) / std(I)
         "bad_match_class": 0,                    # cost = softmax()[0]
         "training": {...}}                       # free-form provenance

``conv{i}.weight`` / ``conv{i}.bias``
    float32, shapes ``(out, in, k, k)`` / ``(out,)``: the siamese layers L1..L3
    (ReLU after each; tied between the left and right patch).
``fc{i}.weight`` / ``fc{i}.bias``
    float32, shapes ``(out, in)`` / ``(out,)``: L4..L8 (ReLU after each but the
    last; the last has 2 outputs fed to a softmax).  ``fc0.weight`` has
    ``in = 2 * maps_L3``: columns ``[:maps]`` act on the left features, columns
    ``[maps:]`` on the right ones (the L4 split used at inference).
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
VERSION = 1
PAPER_CONV = [[32, 5], [200, 5], [200, 1]]
PAPER_FC = [300, 300, 300, 300, 2]
DEFAULT_WEIGHTS_NAME = "mccnn_kitti_mb_v1.npz"


@dataclass
class Weights:
    """Network weights plus metadata (see module docstring for the format)."""

    conv: list  # [(W (out,in,k,k), b (out,)), ...]
    fc: list  # [(W (out,in), b (out,)), ...]
    meta: dict = field(default_factory=dict)

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
        """Check that the layer shapes chain into a valid MC-CNN network."""
        if not self.conv or not self.fc:
            raise WeightsError(f"{source}: needs at least one conv and one fc layer")
        cin = None
        for i, (w, b) in enumerate(self.conv):
            if w.ndim != 4 or w.shape[2] != w.shape[3] or b.shape != (w.shape[0],):
                raise WeightsError(f"{source}: conv{i} has shapes {w.shape}/{b.shape}")
            if cin is not None and w.shape[1] != cin:
                raise WeightsError(f"{source}: conv{i} expects {w.shape[1]} inputs, previous layer gives {cin}")
            cin = w.shape[0]
        fin = 2 * cin
        for i, (w, b) in enumerate(self.fc):
            if w.ndim != 2 or b.shape != (w.shape[0],) or w.shape[1] != fin:
                raise WeightsError(f"{source}: fc{i} has shapes {w.shape}/{b.shape}, expected (*, {fin})")
            fin = w.shape[0]
        if fin != 2:
            raise WeightsError(f"{source}: last layer has {fin} outputs, expected 2 (softmax over good/bad)")
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
            "architecture": "mccnn-paper",
            "input_channels": self.input_channels,
            "conv_layers": self.conv_layers(),
            "fc_layers": self.fc_layers(),
            "patch_size": self.patch_size,
            "normalisation": "per_image_mean_std",
            "bad_match_class": 0,
        }
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
        path = os.fspath(path)
        tmp = path + ".tmp"
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)

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
        if meta.get("format") != FORMAT:
            raise WeightsError(f"{path}: format {meta.get('format')!r}, expected {FORMAT!r}")
        if int(meta.get("version", -1)) > VERSION:
            raise WeightsError(f"{path}: format version {meta.get('version')} is newer than this "
                               f"mccnn_cl understands ({VERSION}); upgrade mccnn_cl")
        if meta.get("architecture") != "mccnn-paper":
            raise WeightsError(f"{path}: architecture {meta.get('architecture')!r} is not supported")
        conv, fc = [], []
        try:
            for i in range(len(meta["conv_layers"])):
                conv.append((files[f"conv{i}.weight"], files[f"conv{i}.bias"]))
            for i in range(len(meta["fc_layers"])):
                fc.append((files[f"fc{i}.weight"], files[f"fc{i}.bias"]))
        except KeyError as exc:
            raise WeightsError(f"{path}: missing array {exc}") from exc
        w = cls(conv=conv, fc=fc, meta=meta).validate(path)
        if w.conv_layers() != meta["conv_layers"] or w.fc_layers() != meta["fc_layers"]:
            raise WeightsError(f"{path}: arrays disagree with the metadata's layer sizes")
        return w

    @classmethod
    def random(cls, conv_layers=None, fc_layers=None, input_channels=1, seed=0) -> "Weights":
        """Random weights (He-style scale, small random biases) for tests and benchmarks."""
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
        return cls(conv=conv, fc=fc, meta={"training": {"note": f"random, seed {seed}"}}).validate()


def default_weights_path() -> str:
    """Path of the weights shipped inside the package."""
    ref = resources.files("mccnn_cl.models") / DEFAULT_WEIGHTS_NAME
    return str(ref)
