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
    a :class:`Weights`, a shipped model's name (:func:`shipped_models`), an
    ``.npz`` in this format, or a published network to convert on the fly
    (``.t7`` Torch7, ``.pt`` PyTorch checkpoint; :mod:`mccnn_cl.importers`)."""
    if spec is None or isinstance(spec, Weights):
        return Weights.load() if spec is None else spec
    text = os.fspath(spec)
    models = shipped_models()
    name = ALIASES.get(text, text)
    if name in models and not os.path.exists(text):
        return Weights.load(models[name])
    ext = os.path.splitext(text)[1].lower()
    if ext in (".t7", ".pt", ".pth"):
        from ..importers import convert  # torch only for .pt

        return convert(text)
    if not os.path.exists(text) and not ext:
        raise WeightsError(f"no weights file or shipped model named {text!r} "
                           f"(shipped: {', '.join(models) or 'none'})")
    return Weights.load(text)
