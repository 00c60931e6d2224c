"""Converters from published MC-CNN networks to :class:`mccnn_cl.weights.Weights`.

``convert(path)`` reads, checks and converts one file:

``.t7``
    the authors' Torch7 ASCII networks (jzbontar/mc-cnn, MC-CNN-fst;
    :mod:`.torch7`, no torch needed, nothing in the file is executed);
``.pt`` / ``.pth``
    CNES's PyTorch checkpoints (PyPI ``mccnn``, fast and accurate;
    :mod:`.pytorch`, needs torch, loaded with ``weights_only=True``).

The result carries the stereo-method settings the network was published
with (``meta["stereo"]``, :func:`mccnn_cl.settings.authors_settings` for its
architecture and dataset), where it came from (``meta["source"]``: file
name, sha256, what it is), its licence and the converter.  Anything that is
not such a network raises one :class:`~mccnn_cl.errors.WeightsError` naming
what was expected and what was found.  ``mccnn-cl convert-weights`` and
``mccnn-cl models`` are in :mod:`.commands`.
"""

from __future__ import annotations

import hashlib
import numbers
import os
import re

from ..errors import WeightsError
from ..weights import ACRT, FST, Weights

DATASETS = ("kitti", "kitti2015", "mb")
BSD2 = ("BSD-2-Clause: Copyright (c) 2015, Jure Zbontar; redistribution with the copyright notice, "
        "conditions and disclaimer of the mc-cnn LICENSE")
APACHE2 = ("Apache-2.0: Centre National d'Etudes Spatiales (CNES), PyPI mccnn 1.4.1; "
           "see the Apache License, Version 2.0")


#: what the released code's -d options train on; pair keys as mccnn_cl.evaluation.datasets names them
TRAINING_DATA = {"kitti": "KITTI 2012 training pairs", "kitti2015": "KITTI 2015 training pairs",
                 "mb": "Middlebury training pairs"}
TRAINING_PAIRS = {"kitti": ("kitti2012", 194), "kitti2015": ("kitti2015", 200)}


def sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def convert(path, dataset: str | None = None) -> Weights:
    """Convert a published ``.t7`` or ``.pt`` network (see the module docstring).

    ``dataset`` ("kitti", "kitti2015" or "mb") picks the stereo settings;
    default: the dataset the file was trained on ("kitti" for the authors'
    KITTI 2012 .t7, "mb" for CNES's Middlebury nets)."""
    path = os.fspath(path)
    if dataset is not None and dataset not in DATASETS:
        raise WeightsError(f"dataset {dataset!r} is not one of {', '.join(DATASETS)}")
    if not os.path.isfile(path):
        raise WeightsError(f"network file not found: {path}")
    ext = os.path.splitext(path)[1].lower()
    if ext == ".t7":
        weights = _from_t7(path)
    elif ext in (".pt", ".pth"):
        weights = _from_pt(path)
    else:
        raise WeightsError(f"{path}: cannot convert a file named {ext or 'without an extension'} "
                           "(expected a Torch7 .t7 or a PyTorch .pt/.pth network)")
    from ..settings import authors_settings

    meta = weights.meta
    meta["dataset"] = dataset or meta["dataset"]
    meta["stereo"] = authors_settings(weights.architecture, meta["dataset"])
    meta["source"].update(file=os.path.basename(path), sha256=sha256(path))
    from .._version import __version__

    meta["converted_by"] = f"mccnn_cl {__version__} ({meta.pop('_converter')})"
    return weights.validate(path)


def _from_t7(path) -> Weights:
    from . import torch7

    root = torch7.read_t7(path)
    conv, facts = torch7.network(root, path)
    opts = facts["options"]
    # main.lua names its nets net_<dataset>_<arch>_<arguments>.t7
    named = re.match(r"net_(kitti2015|kitti|mb)_(fast|slow)_", os.path.basename(path))
    dataset = named.group(1) if named else "kitti"
    meta = {
        "dataset": dataset,
        "source": {"what": "MC-CNN-fst trained by J. Zbontar with the released mc-cnn code "
                           f"(Torch7 ASCII, modules {', '.join(m.split('.')[-1] for m in facts['modules'])})",
                   "format": "torch7-ascii", "padding": [list(p) for p in facts["padding"]]},
        "licence": BSD2,
        "training": {"by": "Jure Zbontar (jzbontar/mc-cnn)",
                     "data": TRAINING_DATA[dataset] + (" (all of them: -a train_all)" if opts.get("a") == "train_all"
                                                       else ""),
                     "options": opts},
        "_converter": "mccnn_cl.importers.torch7",
    }
    if opts.get("a") == "train_all" and dataset in TRAINING_PAIRS:
        kind, n = TRAINING_PAIRS[dataset]
        meta["training"]["trained_on"] = [f"{kind}/{i:06d}" for i in range(n)]
    return Weights(conv=conv, fc=[], meta=meta, architecture=FST)


def _from_pt(path) -> Weights:
    from . import pytorch

    ckpt = pytorch.load_checkpoint(path)
    arch, conv, fc = pytorch.network(pytorch.state_dict(ckpt, path), path)
    training = {"by": "CNES (PyPI mccnn)",
                "data": "Middlebury, standardised gray images (CNES preprocess_middlebury: the 2014 scenes at "
                        "half size but their first 7, which CNES tests on, and the 2006, 2005 and 2003 "
                        "(Cones, Teddy) scenes, among others)"}
    if isinstance(ckpt, dict):
        for k in ("epoch", "train_epoch_loss", "test_epoch_loss"):
            value = ckpt.get(k)
            if isinstance(value, numbers.Real) and not isinstance(value, bool):
                training[k] = int(value) if isinstance(value, numbers.Integral) else float(value)
    net = "AccMcCnn (MC-CNN-acrt)" if arch == ACRT else "FastMcCnn (MC-CNN-fst)"
    meta = {
        "dataset": "mb",
        "source": {"what": f"CNES {net} PyTorch checkpoint", "format": "pytorch-checkpoint",
                   "padding": [[0, 0]] * len(conv)},
        "licence": APACHE2,
        "training": training,
        "_converter": "mccnn_cl.importers.pytorch",
    }
    if arch == ACRT:
        meta["source"]["note"] = ("last fc layer negated: CNES's sigmoid is P(match), "
                                  "mccnn-acrt's is P(bad match)")
    return Weights(conv=conv, fc=fc, meta=meta, architecture=arch)
