"""Where the benchmark scripts find the repository and the shared data.

The shared data is ``$MCCNN_DATA`` when set, else ``../shared/data`` beside the
repository (the layout CI and the README use).  Scripts import this module by
name: run as ``python tools/benchmarks/<script>.py``, their folder is first on
``sys.path``.
"""

from __future__ import annotations

import os
from pathlib import Path

#: the repository root (this file: tools/benchmarks/_paths.py)
REPO = Path(__file__).resolve().parents[2]


def data_dir(given=None) -> Path:
    """``given`` (a ``--data`` argument) if not None, else ``$MCCNN_DATA``, else
    ``../shared/data`` beside the repository."""
    if given is not None:
        return Path(given)
    env = os.environ.get("MCCNN_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"
