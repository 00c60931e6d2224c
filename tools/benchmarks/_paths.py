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


def kitti_000000(given=None):
    """KITTI 2015 training frame 000000 (the benchmarks' pair) through the package's loader,
    under :func:`data_dir` (``given``: a ``--data`` argument); exits with a message naming
    the folder when it cannot be read."""
    import sys

    from mccnn_cl.errors import InputError
    from mccnn_cl.evaluation.datasets import load_kitti2015

    k = data_dir(given) / "kitti2015" / "training"
    try:
        return load_kitti2015(k, "000000")
    except (InputError, OSError) as exc:
        sys.exit(f"KITTI 2015 000000 not readable under {k} (set MCCNN_DATA or --data): {exc}")
