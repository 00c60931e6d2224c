"""Matching costs: the census transform and the networks (paper, acrt, fst).

Every cost is a :class:`~mccnn_cl.costs.base.MatchingCost` subclass,
registered by its ``kind`` or ``architecture`` (:mod:`.base`);
:func:`make_cost` builds the one a pipeline needs (:mod:`.registry` states
the interface).  Modules: :mod:`.census`, :mod:`.features` (the conv stack
every network shares and :class:`~.features.ConvNetCost`), :mod:`.network`
(paper, acrt), :mod:`.fst`.
"""

from .base import MatchingCost  # noqa: F401
from .registry import cost_classes, make_cost  # noqa: F401
