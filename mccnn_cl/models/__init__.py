"""The shipped networks (the ``*.npz`` beside this file; MODEL_CARD.md) and
:func:`resolve`, which turns whatever a user may name as weights into
:class:`~mccnn_cl.weights.Weights` (also reachable as
``mccnn_cl.weights.resolve``)."""

from __future__ import annotations

import os

from ..errors import WeightsError
from ..weights import ALIASES, Weights, shipped_models


def resolve(spec=None) -> Weights:
    """Weights from what a user may name: None (the default shipped network),
    a :class:`Weights`, a shipped model's name (:func:`shipped_models`; also
    with ``.npz``, "general-fst.npz", when no such file exists), an
    ``.npz`` in this format, or a published network to convert on the fly
    (``.t7`` Torch7, ``.pt`` PyTorch checkpoint; :mod:`mccnn_cl.importers`).
    A path that does not exist is a :class:`WeightsError` listing the shipped names."""
    if spec is None or isinstance(spec, Weights):
        return Weights.load() if spec is None else spec
    text = os.fspath(spec)
    models = shipped_models()
    name = ALIASES.get(text, text)
    exists = os.path.exists(text)
    if name in models and not exists:
        return Weights.load(models[name])
    stem, ext = os.path.splitext(text)
    # a shipped model's file name (as the demo prints it, "general-fst.npz") with no such file here
    if not exists and ext.lower() == ".npz" and not os.path.dirname(text) and ALIASES.get(stem, stem) in models:
        return Weights.load(models[ALIASES.get(stem, stem)])
    if not exists and not ext:
        raise WeightsError(f"no weights file or shipped model named {text!r} "
                           f"(shipped: {', '.join(models) or 'none'})")
    if not exists:
        raise WeightsError(f"weights file not found: {text} (shipped models, given by name: "
                           f"{', '.join(models) or 'none'})")
    if ext.lower() in (".t7", ".pt", ".pth"):
        from ..importers import convert  # torch only for .pt

        return convert(text)
    return Weights.load(text)
