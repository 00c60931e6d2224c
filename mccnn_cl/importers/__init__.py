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
name, sha256, what it is), its licence and the converter.

Who trained a file, on what and under which licence is known only for the
published files, recognised by their sha256 (:data:`PUBLISHED`); any other
file gets :data:`UNKNOWN_LICENCE` / :data:`UNKNOWN_BY` (and an
:class:`~mccnn_cl.errors.InputWarning` says so).  The dataset whose settings
a file gets: the caller's ``dataset``, else the one the file identifies --
a published file's, or for a ``.t7`` the ``net_<dataset>_...`` name that
``main.lua`` writes and the stereo options stored in the file (pi1, pi2,
tau_so, ... equal to one column of :data:`mccnn_cl.settings.AUTHORS`); a
name and options that disagree are an error, and a file that identifies
nothing needs ``dataset`` (``convert-weights --dataset``).
``trained_on`` is written only when the file itself identifies the dataset.

Anything that is not such a network raises one :class:`~mccnn_cl.errors.WeightsError` naming
what was expected and what was found.  ``mccnn-cl convert-weights`` and
``mccnn-cl models`` are in :mod:`mccnn_cl.cli.convert`.
"""

from __future__ import annotations

import hashlib
import math
import numbers
import os
import re
import warnings

from ..errors import InputWarning, WeightsError
from ..weights import ACRT, FST, Weights

DATASETS = ("kitti", "kitti2015", "mb")
BSD2 = ("BSD-2-Clause: Copyright (c) 2015, Jure Zbontar; redistribution with the copyright notice, "
        "conditions and disclaimer of the mc-cnn LICENSE")
APACHE2 = ("Apache-2.0: Centre National d'Etudes Spatiales (CNES), PyPI mccnn 1.4.1; "
           "see the Apache License, Version 2.0")
#: licence and authorship of a file that is not one of :data:`PUBLISHED`
UNKNOWN_LICENCE = "unknown (not one of the published files; state the licence of your network yourself)"
UNKNOWN_BY = "unknown (not one of the published files; the file does not say who trained it)"

ZBONTAR = "Jure Zbontar (jzbontar/mc-cnn)"
CNES = "CNES (PyPI mccnn)"
CNES_DATA = ("Middlebury, standardised gray images (CNES preprocess_middlebury: the 2014 scenes at "
             "half size but their first 7, which CNES tests on, and the 2006, 2005 and 2003 "
             "(Cones, Teddy) scenes, among others)")

#: The published networks (the shared models folder), by the sha256 of their file:
#: what the file is, its dataset, who trained it and its licence.
PUBLISHED = {
    "c6c32c68a767c5bc4f5e2b3ca322456a03fe5eac9b187c5b2bc8a969b6a06958": {
        "file": "net_kitti_fast_-a_train_all.t7", "dataset": "kitti", "by": ZBONTAR, "licence": BSD2},
    "0b6b958a22489f34478b4dd6c8b8e96f35922a8bdaf7e88cf0543dd041939283": {
        "file": "cnes_mccnn_1.4.1/mc_cnn_fast_mb_weights.pt", "dataset": "mb", "by": CNES, "licence": APACHE2},
    "1225d8e81cb90ec76d9b992af295e29ac174f7d5f853a8b8d21f063e8b8dfc97": {
        "file": "cnes_mccnn_1.4.1/mc_cnn_accurate_mb_weights.pt", "dataset": "mb", "by": CNES,
        "licence": APACHE2},
}

#: what the released code's -d options train on; pair keys as mccnn_cl.evaluation.datasets names them
TRAINING_DATA = {"kitti": "KITTI 2012 training pairs", "kitti2015": "KITTI 2015 training pairs",
                 "mb": "Middlebury training pairs"}
TRAINING_PAIRS = {"kitti": ("kitti2012", 194), "kitti2015": ("kitti2015", 200)}

#: main.lua's option names -> this project's settings names (mccnn_cl.settings)
T7_OPTIONS = {"pi1": "sgm_pi1", "pi2": "sgm_pi2", "sgm_q1": "sgm_q1", "sgm_q2": "sgm_q2", "alpha1": "sgm_v",
              "tau_so": "sgm_tau_so", "blur_sigma": "blur_sigma", "blur_t": "blur_tau", "L1": "cbca_eta",
              "tau1": "cbca_tau", "cbca_i1": "cbca_iterations", "cbca_i2": "cbca_iterations_after"}


def sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def convert(path, dataset: str | None = None) -> Weights:
    """Convert a published ``.t7`` or ``.pt`` network (see the module docstring).

    ``dataset`` ("kitti", "kitti2015" or "mb") picks the stereo settings;
    default: the dataset the file identifies (a published file's, or a
    ``.t7``'s name and stored options); a file that identifies none needs it."""
    path = os.fspath(path)
    if dataset is not None and dataset not in DATASETS:
        raise WeightsError(f"dataset {dataset!r} is not one of {', '.join(DATASETS)}")
    if os.path.isdir(path):
        raise WeightsError(f"{path} is a folder, not a network file")
    if not os.path.isfile(path):
        raise WeightsError(f"network file not found: {path}")
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".t7", ".pt", ".pth"):
        raise WeightsError(f"{path}: cannot convert a file named {ext or 'without an extension'} "
                           "(expected a Torch7 .t7 or a PyTorch .pt/.pth network)")
    digest = sha256(path)
    published = PUBLISHED.get(digest)
    weights = _from_t7(path, published) if ext == ".t7" else _from_pt(path, published)
    weights.validate(path)  # the arrays (finite, shapes) before the question of the dataset
    from ..settings import authors_settings

    meta = weights.meta
    found, how = meta.pop("_dataset"), meta.pop("_dataset_from")
    if dataset is None and found is None:
        raise WeightsError(f"{path}: which dataset the network was trained on is not known ({how}); say whose "
                           f"stereo settings it gets: mccnn-cl convert-weights --dataset "
                           f"{'|'.join(DATASETS)} (Python: convert(path, dataset=...))")
    meta["dataset"] = dataset or found
    meta["dataset_source"] = (how if dataset is None or dataset == found else
                              f"given by the user ({how if found else 'the file identifies none: ' + how})")
    meta["stereo"] = authors_settings(weights.architecture, meta["dataset"])
    meta["source"].update(file=os.path.basename(path), sha256=digest,
                          published=published["file"] if published else None)
    if published is None:
        warnings.warn(f"{os.path.basename(path)} is not one of the published networks (sha256 {digest[:12]}...): "
                      "its licence and who trained it are unknown (meta['licence']: unknown); state the licence "
                      "of your network yourself", InputWarning, stacklevel=2)
    from .._version import __version__

    meta["converted_by"] = f"mccnn_cl {__version__} ({meta.pop('_converter')})"
    return weights.validate(path)


def dataset_from_options(opts: dict):
    """``(dataset or None, why)``: the authors' MC-CNN-fst column of :data:`mccnn_cl.settings.AUTHORS`
    whose stereo settings all of ``opts`` (main.lua's options, as a .t7 stores them) equal."""
    from ..settings import AUTHORS

    given = {ours: opts[theirs] for theirs, ours in T7_OPTIONS.items()
             if isinstance(opts.get(theirs), numbers.Real) and not isinstance(opts.get(theirs), bool)}
    if not {"sgm_pi1", "sgm_pi2"} <= set(given):
        return None, "its stored options have no pi1 and pi2"
    found = [ds for ds in DATASETS
             if all(math.isclose(float(v), float(AUTHORS[(FST, ds)][k]), rel_tol=1e-6, abs_tol=1e-9)
                    for k, v in given.items())]
    text = f"pi1 = {given['sgm_pi1']:g}, pi2 = {given['sgm_pi2']:g}"
    if len(found) == 1:
        return found[0], f"its stored options ({text}, ...) are the authors' {found[0]} column"
    if not found:
        return None, f"its stored options ({text}, ...) are none of the authors' columns"
    return None, f"its stored options ({text}, ...) fit the columns {', '.join(found)}"


def _t7_dataset(path, opts, published):
    """``(dataset or None, how)`` of a .t7: its published entry, its main.lua name, its options."""
    name = os.path.basename(path)
    named = re.match(r"net_(kitti2015|kitti|mb)_(fast|slow)_", name)
    by_name = named.group(1) if named else None
    by_opts, why = dataset_from_options(opts)
    if by_name and by_opts and by_name != by_opts:
        raise WeightsError(f"{path}: the file name says dataset {by_name} (main.lua's net_<dataset>_...) but "
                           f"{why}: rename the file or check that it is the network you mean")
    if published is not None:
        return published["dataset"], f"the published file {published['file']}"
    if by_name and by_opts:
        return by_name, f"the file name and {why}"
    if by_name:
        return by_name, f"the file name (main.lua's net_{by_name}_...; {why})"
    if by_opts:
        return by_opts, why
    return None, f"the name {name} is not main.lua's net_<dataset>_... and {why}"


def _from_t7(path, published) -> Weights:
    from . import torch7

    root = torch7.read_t7(path)
    conv, facts = torch7.network(root, path)
    opts = facts["options"]
    dataset, how = _t7_dataset(path, opts, published)
    modules = ", ".join(m.split(".")[-1] for m in facts["modules"])
    what = ("MC-CNN-fst trained by J. Zbontar with the released mc-cnn code" if published else
            "MC-CNN-fst saved by the released mc-cnn code (main.lua), not one of the published files")
    train_all = opts.get("a") == "train_all"
    if dataset is None:
        data = "unknown (the file does not identify its dataset)"
    else:
        data = TRAINING_DATA[dataset] + (" (all of them: -a train_all)" if train_all else "")
    meta = {
        "_dataset": dataset, "_dataset_from": how,
        "source": {"what": f"{what} (Torch7 ASCII, modules {modules})",
                   "format": "torch7-ascii", "padding": [list(p) for p in facts["padding"]]},
        "licence": published["licence"] if published else UNKNOWN_LICENCE,
        "training": {"by": published["by"] if published else UNKNOWN_BY, "data": data, "options": opts},
        "_converter": "mccnn_cl.importers.torch7",
    }
    if train_all and dataset in TRAINING_PAIRS:
        kind, n = TRAINING_PAIRS[dataset]
        desc = {"by": meta["training"]["by"], "how": "main.lua -a train_all"}
        meta["training"]["trained_on"] = {f"{kind}/{i:06d}": dict(desc) for i in range(n)}
    return Weights(conv=conv, fc=[], meta=meta, architecture=FST)


def _from_pt(path, published) -> Weights:
    from . import pytorch

    ckpt = pytorch.load_checkpoint(path)
    arch, conv, fc = pytorch.network(pytorch.state_dict(ckpt, path), path)
    training = {"by": published["by"] if published else UNKNOWN_BY,
                "data": CNES_DATA if published else "unknown (not one of the published files)"}
    if isinstance(ckpt, dict):
        for k in ("epoch", "train_epoch_loss", "test_epoch_loss"):
            value = ckpt.get(k)
            if isinstance(value, numbers.Real) and not isinstance(value, bool):
                training[k] = int(value) if isinstance(value, numbers.Integral) else float(value)
    net = "AccMcCnn (MC-CNN-acrt)" if arch == ACRT else "FastMcCnn (MC-CNN-fst)"
    meta = {
        "_dataset": published["dataset"] if published else None,
        "_dataset_from": (f"the published file {published['file']}" if published else
                          "a PyTorch checkpoint that is not one of the published files stores no dataset"),
        "source": {"what": f"CNES {net} PyTorch checkpoint" if published else
                           f"{net} PyTorch checkpoint in CNES's layout, not one of the published files",
                   "format": "pytorch-checkpoint", "padding": [[0, 0]] * len(conv)},
        "licence": published["licence"] if published else UNKNOWN_LICENCE,
        "training": training,
        "_converter": "mccnn_cl.importers.pytorch",
    }
    if arch == ACRT:
        meta["source"]["note"] = ("last fc layer negated: CNES's sigmoid is P(match), "
                                  "mccnn-acrt's is P(bad match)")
    return Weights(conv=conv, fc=fc, meta=meta, architecture=arch)
