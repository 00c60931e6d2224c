"""The base class of every matching cost and the registry its subclasses join.

A cost class states its ``kind`` (``"census"``) or ``architecture`` (a
network's ``Weights.architecture``); defining the class registers it under
that key (:func:`registered`), and :func:`mccnn_cl.costs.registry.cost_classes`
imports every module of :mod:`mccnn_cl.costs`, so a new network is one class
(plus its kernel) in a module of this package.  The interface is described
in :mod:`mccnn_cl.costs.registry`.
"""

from __future__ import annotations

import numpy as np

_REGISTRY: dict = {}


def registered() -> dict:
    """key -> cost class, for the classes defined so far."""
    return dict(_REGISTRY)


class MatchingCost:
    """``cost(left, right, max_disparity, out=None, progress=None, stats=None, scratch=None, rows=None)
    -> device buffer``.

    Subclasses set ``margin``, ``local``, ``floor`` and ``kind`` or
    ``architecture``, and implement :meth:`__call__`, :meth:`to_host`,
    :meth:`scratch_bytes` and :meth:`flops`."""

    #: registry key of a cost without weights ("census"); networks use ``architecture``
    kind: str | None = None
    architecture: str | None = None
    margin: int = 0
    local: bool = False
    floor: float = 0.0
    #: upper bound of the cost, None where none is known (SGM's 16-bit sweeps need |C| bounded)
    ceiling: float | None = None
    half: bool = False
    vdtype = np.dtype(np.float32)

    def magnitude_bound(self) -> float | None:
        """max |C| over every valid cell (from ``floor`` and ``ceiling``), None where
        the cost has no known ceiling: SGM's 16-bit sweeps' ``cost_bound``."""
        if self.ceiling is None:
            return None
        return max(abs(float(self.floor)), abs(float(self.ceiling)))

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        key = cls.__dict__.get("kind") or cls.__dict__.get("architecture")
        if key is None:
            return
        other = _REGISTRY.get(key)
        if other is not None and other.__qualname__ != cls.__qualname__:
            raise TypeError(f"two cost classes for {key!r}: {other.__qualname__} and {cls.__qualname__}")
        _REGISTRY[key] = cls

    @classmethod
    def build(cls, ctx, weights, half: bool = False, tiles: dict | None = None):
        """The cost for ``weights`` (a network's :class:`~mccnn_cl.weights.Weights`)."""
        return cls(ctx, weights, tiles=tiles, half=half)

    def __call__(self, left, right, max_disparity, out=None, progress=None, stats=None, scratch=None, rows=None,
                 row0=0):
        """The volume ``[D][H_img - 2m][W_img - 2m]`` on the device (into ``out``
        when given); ``progress(done, D)`` as disparities or bands complete;
        ``stats``: ``((mean, std), (mean, std))`` of the left and right images to
        standardise with instead of the inputs' own (None: their own);
        ``scratch``: a device buffer lent for the call's own buffers (a cost
        may leave it unused; its contents are overwritten); ``rows``: volume
        rows per band of a banded cost (the networks; None: :meth:`band_rows`,
        a cost that does not band ignores it); ``row0``: the images' first row in
        the whole images they were cut from (a row tile: the networks' Winograd
        layers then compute its rows as the whole images'; others ignore it)."""
        raise NotImplementedError

    def band_rows(self, H: int, W: int) -> int:
        """The most volume rows one band of an H x W volume takes (a cost that
        does not band: all H)."""
        return int(H)

    def lent_scratch_bytes(self, H: int, W: int, lent: int, rows=None) -> int:
        """Of :meth:`scratch_bytes`, the bytes a lent ``scratch`` buffer of ``lent``
        bytes surely holds (none: a cost that does not use the loan)."""
        return 0

    def to_host(self, left, right, max_disparity, max_bytes=None, progress=None, stats=None,
                rows=None, row0=0) -> np.ndarray:
        """The volume in host memory, using at most ``max_bytes`` of device memory
        at a time (bands of at most ``rows`` rows where the cost bands; ``row0``
        as :meth:`__call__`)."""
        raise NotImplementedError

    def scratch_bytes(self, H: int, W: int, rows=None) -> int:
        """Upper bound of the device bytes a call allocates besides the H x W volume
        (in bands of ``rows`` volume rows where the cost bands; None: :meth:`band_rows`)."""
        raise NotImplementedError

    def flops(self, height: int, width: int, max_disparity: int) -> dict:
        """Arithmetic of one volume (``total`` and its parts)."""
        raise NotImplementedError

    def release_buffers(self) -> None:
        """Free the scratch kept between calls (nothing by default)."""
