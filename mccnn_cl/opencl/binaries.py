"""Program binaries kept on disk between processes (``~/.cache/mccnn_cl/binaries``).

Why: PoCL caches source builds itself, but a hit still preprocesses the
source and costs ~0.2 s per program (14 programs for the fst method: ~2.5 s
of a KITTI pair's first call on 2 loaded cores); a program made from its
binary costs ~0.02 s.  Fetching a binary from PoCL compiles every kernel of
the program once more (seconds per program), so binaries are saved only when
asked (:attr:`mccnn_cl.opencl.context.ClContext.save_binaries`: ``mccnn-cl tune`` sets
it for a run of the default method after tuning), and loaded whenever present.

A binary's file name is a hash of everything its build depends on: the
package version, the platform (name, version), the device (name, driver
version), the build options, the kernel source and every header of the
kernel directory.  Files are written to a temporary name and renamed (two
processes may write the same binary; readers never see half a file).  A
binary the runtime refuses is deleted and the program built from source.
``MCCNN_BINARY_CACHE=off`` disables the cache; ``MCCNN_CACHE_DIR`` moves it.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile

log = logging.getLogger(__name__)


def cache_root() -> str:
    """The package's cache directory (``$MCCNN_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/mccnn_cl``, else ``~/.cache/mccnn_cl``)."""
    root = os.environ.get("MCCNN_CACHE_DIR")
    if root:
        return root
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "mccnn_cl")


def enabled() -> bool:
    return os.environ.get("MCCNN_BINARY_CACHE", "on").lower() not in ("off", "0", "no", "false")


_HEADERS: dict = {}


def _headers_digest(kernel_dir: str) -> str:
    """Hash of every header (``*.h``) of the kernel directory (once per directory)."""
    digest = _HEADERS.get(kernel_dir)
    if digest is None:
        h = hashlib.sha256()
        for name in sorted(os.listdir(kernel_dir)):
            if name.endswith(".h"):
                h.update(name.encode())
                with open(os.path.join(kernel_dir, name), "rb") as f:
                    h.update(f.read())
        digest = _HEADERS[kernel_dir] = h.hexdigest()
    return digest


def device_identity(device) -> list:
    """What identifies a device's compiler: platform name and version, device name, driver version."""
    return [device.platform.name.strip(), device.platform.version.strip(), device.name.strip(),
            str(device.driver_version).strip()]


def key(device, kernel_dir: str, source: str, options) -> str:
    from .._version import __version__

    h = hashlib.sha256()
    for part in [__version__, *device_identity(device), " ".join(options), source, _headers_digest(kernel_dir)]:
        h.update(part.encode("utf-8", "replace"))
        h.update(b"\0")
    return h.hexdigest()


def path(k: str) -> str:
    return os.path.join(cache_root(), "binaries", k[:2], k + ".bin")


def load(k: str):
    """The stored binary of key ``k``, or None."""
    try:
        with open(path(k), "rb") as f:
            return f.read()
    except OSError:
        return None


def store(k: str, binary: bytes) -> None:
    """Write atomically (temporary file, then rename); errors are logged, never raised."""
    p = path(k)
    try:
        os.makedirs(os.path.dirname(p), exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(p), prefix=".tmp-")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(binary)
            os.replace(tmp, p)
        except BaseException:
            os.unlink(tmp)
            raise
    except OSError as exc:
        log.warning("could not store a kernel binary in %s: %s", p, exc)


def discard(k: str) -> None:
    try:
        os.unlink(path(k))
    except OSError:
        pass
