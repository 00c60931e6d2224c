"""The tuner's per-device cache (``<cache>/tune/<hash>.json``): where it lies,
reading it (a corrupt or foreign file is ignored with one warning) and writing
it atomically (:func:`mccnn_cl.atomic.atomic_write`: stale temporary files of
killed writers deleted, the earlier writer's ``.tmp-*`` too:
:func:`mccnn_cl.opencl.binaries.remove_legacy`), and the lock
``mccnn-cl tune`` holds while it measures (:func:`tuning_lock`).
:class:`~mccnn_cl.opencl.context.ClContext` reads a device's choices from here;
:mod:`mccnn_cl.opencl.tune` measures and stores them."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import warnings

from .. import atomic
from .binaries import cache_root, device_identity, remove_legacy

log = logging.getLogger(__name__)

#: 2: the KITTI-like size and the rules' candidate measured beside the others
#: (files of format 1, tuned on a 96 x 384 volume, are ignored); 3: the fst conv
#: stack's CONV_RN (a tuned CONV_RM of format 2 was measured at RN, not CONV_RN)
FORMAT = 3
#: The representative size (H, W, D) candidates are timed at (recorded with
#: the choices): a quarter of a KITTI 2015 pair's rows at its full width and
#: disparity range (1242 x 375, D 228), so that row strides, plane strides
#: and the volume (109 MB, beyond every cache) behave as on a KITTI pair.
SIZE = (96, 1242, 228)


def enabled() -> bool:
    return os.environ.get("MCCNN_TUNE", "on").lower() not in ("off", "0", "no", "false")


def identity(device) -> dict:
    from .._version import __version__

    plat, plat_version, name, driver = device_identity(device)
    return {"platform": plat, "platform_version": plat_version, "device": name, "driver_version": driver,
            "package_version": __version__, "format": FORMAT}


def folder() -> str:
    """The folder of the tuning files (``<cache>/tune``)."""
    return os.path.join(cache_root(), "tune")


def cache_path(device) -> str:
    ident = identity(device)
    digest = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:24]
    return os.path.join(folder(), digest + ".json")


#: The lock file ``mccnn-cl tune`` holds (``flock``) while it measures and stores.
LOCK_NAME = "tune.lock"


def lock_path() -> str:
    return os.path.join(folder(), LOCK_NAME)


def tuning_lock(on_wait=None):
    """Context manager: an exclusive lock on :func:`lock_path` (one per cache
    folder, :class:`mccnn_cl.atomic.exclusive_lock`) while open, so that two
    tuning runs never measure under each other's load nor overwrite each other's
    results.  When another process holds it, calls ``on_wait(holder)``
    (``holder``: the line that process wrote into the file, its pid and start
    time, or "") and waits for it.  The kernel releases the lock when its holder
    exits, killed or not; the file itself stays."""
    os.makedirs(folder(), exist_ok=True)
    return atomic.exclusive_lock(lock_path(), on_wait=on_wait or (lambda holder: None))


_WARNED: set = set()


def _warn_once(path: str, why: str) -> None:
    if path not in _WARNED:
        _WARNED.add(path)
        warnings.warn(f"mccnn_cl: ignoring the tuning cache {path} ({why}); the rules table is used "
                      "until `mccnn-cl tune` rewrites it", RuntimeWarning, stacklevel=3)


def record(device):
    """The stored record of ``device`` (a dict with its choices and what was
    measured), or None when there is none, when tuning is disabled, or when
    the file is corrupt or of another device/driver/version (one warning)."""
    if not enabled():
        return None
    path = cache_path(device)
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except FileNotFoundError:
        return None
    except (OSError, ValueError, RecursionError) as exc:  # RecursionError: absurdly nested JSON
        _warn_once(path, f"unreadable: {type(exc).__name__}: {str(exc)[:200]}")
        return None
    if not isinstance(data, dict) or data.get("identity") != identity(device) \
            or not isinstance(data.get("choices"), dict):
        _warn_once(path, "written for another device, driver or package version, or malformed")
        return None
    return data


def load(device) -> dict:
    """The stored choices of ``device`` ({} when none: see :func:`record`;
    also when tuning kept the rules' every choice)."""
    data = record(device)
    if data is None:
        return {}
    from .device import RULES

    return {k: v for k, v in data["choices"].items() if k in RULES}


def store(device, choices: dict, measured: dict, size=SIZE) -> str:
    """Write the choices (measured at ``size``) atomically
    (:func:`mccnn_cl.atomic.atomic_write`: a temporary file in the same folder,
    then a rename); the temporary files of dead writers are deleted first, the
    earlier writer's ``.tmp-*`` too (:func:`~mccnn_cl.opencl.binaries.remove_legacy`)."""
    path = cache_path(device)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    if remove_legacy(os.path.dirname(path)):
        log.info("deleted stale temporary file(s) of an earlier version in %s", os.path.dirname(path))
    data = {"identity": identity(device), "choices": choices, "measured": measured,
            "size": list(size), "when": time.strftime("%Y-%m-%d %H:%M:%S")}

    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=1, sort_keys=True)

    atomic.atomic_write(path, write)
    return path
