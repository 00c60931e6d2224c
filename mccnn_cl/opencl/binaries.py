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
kernel directory.  Files are written through :func:`mccnn_cl.atomic.atomic_write`
(a temporary file of a unique name, with the writer's host and pid, in the
same folder, flushed to disk, then renamed: two processes may write the same
binary; readers never see half a file).  Each file holds a header (magic,
payload length, SHA-256 of the payload) that :func:`load` checks: a file cut
short or changed (a copy or sync of the cache folder, a power loss, a disk
error) is deleted and the program built from source, never handed to the
runtime (PoCL crashed the process on a truncated binary, and again in every
later run).  A binary the runtime refuses is deleted too.
``MCCNN_BINARY_CACHE=off`` disables the cache; ``MCCNN_CACHE_DIR`` moves it.

:func:`store` returns whether the file was written, and tells every
:func:`recording` in progress (``mccnn-cl tune`` counts and reports the
binaries stored with it).  A writer killed between its temporary file and the
rename (``kill -9``, a power loss) leaves that file behind; :func:`store`
deletes the temporary files of writers no longer running
(:func:`mccnn_cl.atomic.remove_stale`: its own folder on every call, every
folder of the cache once per process), and once per process those the
caches' earlier writer left (:func:`remove_legacy`).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os

from .. import atomic

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


def _headers_digest(kernel_dir: str) -> str:
    """Hash of every header (``*.h``) of the kernel directory, read each time (a few KB; a header
    changed while a process runs must not key its programs to the old binaries)."""
    h = hashlib.sha256()
    for name in sorted(os.listdir(kernel_dir)):
        if name.endswith(".h"):
            h.update(name.encode())
            with open(os.path.join(kernel_dir, name), "rb") as f:
                h.update(f.read())
    return h.hexdigest()


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


#: A stored file: MAGIC, the payload's length (8 bytes, little-endian), its SHA-256, the payload.
MAGIC = b"MCCNNBIN1"
_HEAD = len(MAGIC) + 8 + 32


def _pack(binary: bytes) -> bytes:
    return MAGIC + len(binary).to_bytes(8, "little") + hashlib.sha256(binary).digest() + binary


def _unpack(data: bytes):
    """The payload of a stored file, or None when it is not whole (header, length or hash wrong)."""
    if len(data) < _HEAD or not data.startswith(MAGIC):
        return None
    n = int.from_bytes(data[len(MAGIC):len(MAGIC) + 8], "little")
    payload = data[_HEAD:]
    if len(payload) != n or hashlib.sha256(payload).digest() != data[len(MAGIC) + 8:_HEAD]:
        return None
    return payload


def load(k: str):
    """The stored binary of key ``k``, or None (none stored, or a file that is not whole: then it
    is deleted, with a warning)."""
    try:
        with open(path(k), "rb") as f:
            data = f.read()
    except OSError:
        return None
    payload = _unpack(data)
    if payload is None:
        if data.startswith(MAGIC[:5]) or len(data) < _HEAD:
            log.warning("a stored kernel binary is damaged (%s, %d bytes); deleting it and building from source",
                        path(k), len(data))
        else:  # written before the header existed: replaced once, quietly
            log.info("a stored kernel binary without a header (%s); building it anew", path(k))
        discard(k)
    return payload


#: Prefix of the temporary files the caches wrote before :mod:`mccnn_cl.atomic`
#: (``tempfile.mkstemp(prefix=".tmp-")``, ``.tmp-probe-`` for the writable check).
LEGACY_PREFIX = ".tmp-"
#: Such a file unchanged this long is a dead writer's (that writer's own rule: a
#: store takes seconds; a younger one may be an older version's write in progress).
LEGACY_STALE_SECONDS = 600.0


def remove_legacy(folder: str) -> list:
    """Delete the caches' earlier temporary files (:data:`LEGACY_PREFIX`) in ``folder``
    unchanged for over :data:`LEGACY_STALE_SECONDS`: left by writers of earlier
    versions killed before their rename, which nothing else deletes now.  Only for
    the cache folders (elsewhere a ``.tmp-`` file is not the package's).  Returns their
    paths; errors are ignored."""
    return atomic.remove_files(folder, lambda name: LEGACY_STALE_SECONDS if name.startswith(LEGACY_PREFIX) else None)


_SWEPT: set = set()


def _sweep_once(root: str) -> None:
    """:func:`mccnn_cl.atomic.remove_stale` and :func:`remove_legacy` in the binary cache
    ``root`` and every folder of it, once per process (``root`` itself: the writable
    check's probe files)."""
    if root in _SWEPT:
        return
    _SWEPT.add(root)
    try:
        subs = [e.path for e in os.scandir(root) if e.is_dir(follow_symlinks=False)]
    except OSError:
        return
    gone = sum(len(atomic.remove_stale(d)) + len(remove_legacy(d)) for d in [root, *subs])
    if gone:
        log.info("deleted %d stale temporary file(s) under %s (writers killed before their rename)", gone, root)


class Recording:
    """What :func:`store` did while a :func:`recording` was open: ``stored`` (files
    written), ``failed`` (``(path, error)`` pairs)."""

    def __init__(self, on_store=None):
        self.stored = 0
        self.failed: list = []
        self.on_store = on_store

    @property
    def attempted(self) -> int:
        return self.stored + len(self.failed)

    def _note(self, p: str, error) -> None:
        if error is None:
            self.stored += 1
        else:
            self.failed.append((p, error))
        if self.on_store is not None:
            self.on_store(self, p, error)


_RECORDINGS: list = []


@contextlib.contextmanager
def recording(on_store=None):
    """Count the :func:`store` calls of this process while open; ``on_store(rec, path,
    error)`` is called after each (``error`` None when the file was written)."""
    rec = Recording(on_store)
    _RECORDINGS.append(rec)
    try:
        yield rec
    finally:
        _RECORDINGS.remove(rec)


def _write(tmp: str, data: bytes) -> None:
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def store(k: str, binary: bytes) -> bool:
    """Write atomically (:func:`mccnn_cl.atomic.atomic_write`); True when written.
    Errors are logged (a warning), never raised; the temporary files of dead
    writers are deleted first."""
    from ..errors import InputError

    p = path(k)
    data = _pack(bytes(binary))
    error = None
    try:
        folder = os.path.dirname(p)
        os.makedirs(folder, exist_ok=True)
        _sweep_once(os.path.dirname(folder))
        atomic.atomic_write(p, lambda tmp: _write(tmp, data))  # also removes its folder's stale files
    except (OSError, InputError) as exc:
        error = exc
        log.warning("could not store a kernel binary in %s: %s", p, exc)
    for rec in list(_RECORDINGS):
        rec._note(p, error)
    return error is None


def discard(k: str) -> None:
    try:
        os.unlink(path(k))
    except OSError:
        pass
