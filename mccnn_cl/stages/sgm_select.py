"""The SGM stage for a device: :func:`make_sgm` picks :class:`~.sgm.SGM` or
:class:`~.sgm_wg.SGMWorkGroup` by the device profile's ``sgm_stage`` rule."""

from __future__ import annotations

from ..errors import InputError
from .sgm import SGM
from .sgm_wg import SGMWorkGroup


def make_sgm(ctx, half: bool = False):
    """The SGM stage for ``ctx``'s device (the profile's ``sgm_stage`` rule):
    :class:`SGM` ("lines") or :class:`~.sgm_wg.SGMWorkGroup` ("workgroup");
    both take the same call and expose ``cols``, ``paired``, ``scratch_bytes``."""
    impl = ctx.profile.rule("sgm_stage")
    if impl == "workgroup":
        return SGMWorkGroup(ctx, half=half, cols=ctx.profile.rule("sgm_wg_cols"))
    if impl != "lines":
        raise InputError(f"unknown SGM stage {impl!r} in the device rules (\"lines\" or \"workgroup\")")
    return SGM(ctx, half=half)
