"""CNES's PyTorch checkpoints of MC-CNN (PyPI ``mccnn``, ``*.pt``).

A checkpoint is a ``torch.save`` dict whose ``model`` entry is the
``state_dict`` of CNES's ``FastMcCnn`` or ``AccMcCnn`` (optimizer, scheduler
and losses beside it are ignored).  It is read with
``torch.load(weights_only=True)``; if torch refuses the pickle, once more
through :data:`restricted` -- an unpickler that allows only the globals a
tensor checkpoint needs (:data:`ALLOWED`) and refuses any other by name.
Nothing else is ever imported from a file.

Layouts (CNES ``mc_cnn/model``): ``conv_blocks`` is an ``nn.Sequential`` of
``Conv2d`` (3x3, no padding) at the even indices with ``ReLU`` at the odd
ones -- the fast net ends on its last Conv2d (then ``F.normalize`` over the
maps), the accurate net on a ReLU.  ``fl_blocks`` (accurate only) are
``Linear`` layers at the even indices with ReLU between them and a final
Sigmoid; the first takes ``cat((left, right), dim=1)``, the same split as
this project's ``fc0``.  CNES trains that sigmoid towards 1 on matches
(BCE target 1) and uses cost = -output, whereas ``mccnn-acrt`` files hold
P(bad match) (the released code's convention): the last layer's weight and
bias are negated on import, so the converted output is 1 - CNES's output
and the cost differs from theirs by the constant 1 only.
"""

from __future__ import annotations

import pickle
import re
import types

import numpy as np

from ..errors import WeightsError
from ..weights import ACRT, FST

#: (module, name) globals the fallback unpickler allows: tensor rebuilding,
#: OrderedDict state dicts, numpy scalars (epochs, losses), their dtypes and
#: the str -> bytes helper their pickles use.
ALLOWED = {
    ("collections", "OrderedDict"),
    ("_codecs", "encode"),
    ("torch._utils", "_rebuild_tensor"),
    ("torch._utils", "_rebuild_tensor_v2"),
    ("torch._utils", "_rebuild_parameter"),
    ("torch", "Size"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "dtype"),
} | {("torch", f"{t}Storage") for t in ("Float", "Double", "Half", "BFloat16", "Long", "Int",
                                         "Short", "Char", "Byte", "Bool")}


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if (module, name) not in ALLOWED:
            raise WeightsError(f"the pickle needs the global {module}.{name}, which is not allowed "
                               "(expected a checkpoint of tensors only)")
        return super().find_class(module, name)


#: a ``pickle_module`` for ``torch.load`` that refuses every global outside ALLOWED
restricted = types.SimpleNamespace(Unpickler=_RestrictedUnpickler, __name__="mccnn_cl_restricted_pickle",
                                   load=lambda f, **kw: _RestrictedUnpickler(f, **kw).load(),
                                   UnpicklingError=pickle.UnpicklingError)

_KEY = re.compile(r"^(conv_blocks|fl_blocks)\.(\d+)\.(weight|bias)$")
EXPECTED = ("a CNES mc-cnn checkpoint: a dict whose 'model' is the state_dict of FastMcCnn "
            "(conv_blocks.0/2/4/...) or AccMcCnn (conv_blocks plus fl_blocks)")


def _torch():
    try:
        import torch
    except ImportError as exc:
        raise WeightsError("reading a .pt checkpoint needs PyTorch, which is not installed "
                           "(pip install torch, or mccnn_cl[train]); .t7 and .npz files need no torch") from exc
    return torch


def load_checkpoint(path, fallback=True):
    """The unpickled checkpoint: ``weights_only=True``, else the :data:`restricted` unpickler."""
    torch = _torch()
    name = str(path)
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise WeightsError(f"{name}: cannot read ({exc.strerror or exc})") from exc
    if not head:
        raise WeightsError(f"{name}: empty file; expected {EXPECTED}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except WeightsError:
        raise
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a bad pickle
        first = exc
    if not fallback or not isinstance(first, pickle.UnpicklingError) or "global" not in _line(first).lower():
        raise WeightsError(f"{name}: not a readable PyTorch checkpoint ({_line(first)}); "
                           f"expected {EXPECTED}") from first
    try:  # torch refused a global: try our own allow-list, which refuses by name
        return torch.load(path, map_location="cpu", weights_only=False, pickle_module=restricted)
    except WeightsError as exc:
        raise WeightsError(f"{name}: {exc}") from first
    except Exception as exc:  # noqa: BLE001
        raise WeightsError(f"{name}: not a readable PyTorch checkpoint ({_line(exc)}); "
                           f"expected {EXPECTED}") from exc


def _line(exc) -> str:
    """One line of a torch error: the unpickler's own reason where torch wraps it in advice."""
    text = str(exc).strip()
    reason = re.search(r"WeightsUnpickler error:\s*([^\n]+)", text)
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if reason:
        lines = [reason.group(1)]
    else:
        lines = [line for line in lines if not line.startswith(_ADVICE)] or lines
    return f"{type(exc).__name__}: {lines[0][:200]}" if lines else type(exc).__name__


#: paragraphs of torch's weights_only errors that give advice, not the reason
_ADVICE = ("Weights only load failed", "Check the documentation", "Please file an issue")


def state_dict(obj, name):
    if isinstance(obj, dict) and isinstance(obj.get("model"), dict):
        return obj["model"]
    if isinstance(obj, dict) and obj and all(isinstance(k, str) and _KEY.match(k) for k in obj):
        return obj  # a bare state_dict
    what = (f"a dict with keys {', '.join(map(str, list(obj)[:8]))}" if isinstance(obj, dict)
            else f"a {type(obj).__name__}")
    raise WeightsError(f"{name}: expected {EXPECTED}; found {what}")


def network(sd, name):
    """(architecture, conv [(W, b)], fc [(W, b)]) from a CNES state_dict."""
    torch = _torch()
    blocks = {"conv_blocks": {}, "fl_blocks": {}}
    for key, value in sd.items():
        m = _KEY.match(key) if isinstance(key, str) else None
        if m is None or not isinstance(value, torch.Tensor):
            others = [k for k in sd if not (isinstance(k, str) and _KEY.match(k))]
            raise WeightsError(f"{name}: expected {EXPECTED}; found other entries "
                               f"{', '.join(map(str, others[:6]))}")
        if not value.is_floating_point():
            raise WeightsError(f"{name}: {key} is {value.dtype}, expected floating-point weights")
        blocks[m.group(1)].setdefault(int(m.group(2)), {})[m.group(3)] = (
            value.detach().to("cpu", torch.float32).numpy().copy())
    conv = _layers(blocks["conv_blocks"], "conv_blocks", 4, name)
    if conv[0][0].shape[1] != 1:
        raise WeightsError(f"{name}: conv_blocks.0.weight has shape {tuple(conv[0][0].shape)}: the network takes "
                           f"{conv[0][0].shape[1]} input channels; mccnn_cl runs networks of 1 gray channel "
                           "(CNES's FastMcCnn / AccMcCnn), not multi-channel ones such as CNES's DataFusion "
                           "variants")
    fc = _layers(blocks["fl_blocks"], "fl_blocks", 2, name, optional=True)
    for i, (w, _) in enumerate(conv):
        if w.shape[2] != w.shape[3] or (i and w.shape[1] != conv[i - 1][0].shape[0]):
            raise WeightsError(f"{name}: conv_blocks.{2 * i}.weight has shape {w.shape}; expected square "
                               f"kernels taking the previous layer's {conv[i - 1][0].shape[0] if i else '?'} maps")
    if not fc:
        return FST, conv, []
    fin = 2 * conv[-1][0].shape[0]
    for i, (w, _) in enumerate(fc):
        if w.shape[1] != fin:
            raise WeightsError(f"{name}: fl_blocks.{2 * i}.weight has shape {w.shape}, expected (*, {fin}) "
                               f"({'[left; right] features' if i == 0 else 'the previous layer'})")
        fin = w.shape[0]
    if fin != 1:
        raise WeightsError(f"{name}: the last fl_blocks layer has {fin} outputs, expected 1 (sigmoid)")
    w, b = fc[-1]
    fc[-1] = (-w, -b)  # CNES: sigmoid -> 1 on matches; mccnn-acrt: P(bad match)
    return ACRT, conv, fc


def _layers(found, prefix, ndim, name, optional=False):
    if not found:
        if optional:
            return []
        raise WeightsError(f"{name}: expected {EXPECTED}; no {prefix} weights")
    idx = sorted(found)
    want = list(range(0, 2 * len(idx), 2))
    if idx != want:
        raise WeightsError(f"{name}: {prefix} layers at indices {idx}, expected {want} "
                           "(a layer with weights, then a ReLU, alternately)")
    out = []
    for i in idx:
        p = found[i]
        if set(p) != {"weight", "bias"}:
            raise WeightsError(f"{name}: {prefix}.{i} has {sorted(p)}, expected weight and bias")
        w, b = p["weight"], p["bias"]
        if w.ndim != ndim or b.shape != (w.shape[0],):
            raise WeightsError(f"{name}: {prefix}.{i} has weight {w.shape} / bias {b.shape}, expected a "
                               f"{ndim}-d weight and one bias per output")
        out.append((np.ascontiguousarray(w, np.float32), np.ascontiguousarray(b, np.float32)))
    return out
