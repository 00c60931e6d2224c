"""Atomic file writes: a temporary file in the destination's folder, then ``os.replace``.

An interrupted write never leaves a half-written file under the final name.
The temporary files carry a recognisable name, ``.mccnn-tmp-<pid>-<random><ext>``
(hidden, in the destination's folder so the rename stays on one file system).
A process killed while writing (SIGKILL, power loss) cannot remove its own:
the next write into that folder removes every such file whose process is no
longer running on this machine (:func:`remove_stale`), so a crash leaves at
most one stray file until the folder is written to again.  Files of running
processes (another mccnn-cl writing there now) are left alone.
"""

from __future__ import annotations

import errno
import os
import re
import tempfile

from .errors import InputError

#: Prefix of every temporary file (followed by the writer's pid and a dash).
PREFIX = ".mccnn-tmp-"
_NAME = re.compile(re.escape(PREFIX) + r"(\d+)-")


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's running process
        return True
    except OSError:
        return True
    return True


def remove_stale(directory) -> list:
    """Remove the temporary files in ``directory`` left by processes that are no
    longer running; returns their paths.  Errors (a file already gone, no
    permission) are ignored: a stray file never stops a write."""
    removed = []
    try:
        names = os.listdir(directory)
    except OSError:
        return removed
    for name in names:
        m = _NAME.match(name)
        if m is None or _alive(int(m.group(1))):
            continue
        path = os.path.join(directory, name)
        try:
            if os.path.isfile(path) and not os.path.islink(path):
                os.unlink(path)
                removed.append(path)
        except OSError:
            pass
    return removed


def _mkstemp(directory, suffix=""):
    try:
        return tempfile.mkstemp(prefix=f"{PREFIX}{os.getpid()}-", suffix=suffix, dir=directory)
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            reason = "not writable" + ("" if exc.errno != errno.EROFS else " (read-only file system)")
        raise InputError(f"cannot write into {directory}: {reason}") from exc


def check_writable(directory) -> None:
    """InputError (one line) unless a file can be created in ``directory``
    (tried for real: permissions, read-only mounts and ACLs all count)."""
    fd, tmp = _mkstemp(directory)
    os.close(fd)
    os.unlink(tmp)


def atomic_write(path, write_fn) -> None:
    """Call ``write_fn(tmp)`` on a temporary file in ``path``'s folder (same
    extension: cv2 picks the encoder from it), then rename it onto ``path``.
    The temporary file is removed on any error; stale ones of crashed
    processes are removed first (:func:`remove_stale`).  An unwritable folder
    is an InputError naming the folder, not the hidden temporary file."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    remove_stale(directory)
    fd, tmp = _mkstemp(directory, os.path.splitext(path)[1])
    os.close(fd)
    try:
        write_fn(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give new files the usual mode
        try:
            os.replace(tmp, path)
        except IsADirectoryError as exc:
            raise InputError(f"{path} is a folder, not a file") from exc
        except PermissionError as exc:
            raise InputError(f"cannot write {path}: {exc.strerror or 'permission denied'}") from exc
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path, data: bytes) -> None:
    """``data`` at ``path``, whole or not at all (:func:`atomic_write`)."""
    def write(tmp):
        with open(tmp, "wb") as f:
            f.write(data)
    atomic_write(path, write)


#: Locks this process holds (:func:`exclusive_lock`): real path -> [fd, depth].
_HELD: dict = {}


def lock_holder(path) -> str:
    """The line the holder of the lock file ``path`` wrote into it (its pid, host
    and start time), "" when there is none or it cannot be read."""
    try:
        with open(path, "rb") as f:
            return f.read(300).decode("utf-8", "replace").strip()
    except OSError:
        return ""


class exclusive_lock:
    """Context manager: hold an exclusive ``flock`` on the file ``path`` (created
    if missing) while open.  When another process holds it: without ``on_wait``,
    raises :class:`~mccnn_cl.errors.InputError` with ``busy`` formatted with
    ``holder`` (the line that process wrote into the file: ``pid N on HOST,
    since TIME``) and ``path``; with ``on_wait``, calls ``on_wait(holder)`` and
    waits for the lock.  Re-entrant within one process (a nested use of
    the same path is free; the lock goes with the outermost).  The kernel
    releases the lock when its holder exits, killed or not; the file stays
    (deleting it would let a third process lock a new file while a second
    holds the old one)."""

    def __init__(self, path, busy: str = "{path} is locked by another process ({holder})", on_wait=None):
        self.path = os.fspath(path)
        self.busy = busy
        self.on_wait = on_wait
        self._key = None

    def __enter__(self):
        import fcntl
        import socket
        import time

        key = os.path.realpath(self.path)
        if key in _HELD:
            _HELD[key][1] += 1
            self._key = key
            return self.path
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise InputError(f"cannot create the lock file {self.path}: {exc.strerror or exc}") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if self.on_wait is None:
                os.close(fd)
                raise InputError(self.busy.format(holder=lock_holder(self.path) or "holder unknown",
                                                  path=self.path)) from None
            self.on_wait(lock_holder(self.path))
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
            except BaseException:  # Ctrl-C while waiting
                os.close(fd)
                raise
        except OSError as exc:  # a file system without locks: say so rather than run unprotected
            os.close(fd)
            raise InputError(f"cannot lock {self.path}: {exc.strerror or exc}") from exc
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}, since "
                          f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode(), 0)
        except OSError:
            pass
        _HELD[key] = [fd, 1]
        self._key = key
        return self.path

    def __exit__(self, *exc):
        held = _HELD.get(self._key)
        if held is not None:
            held[1] -= 1
            if held[1] == 0:
                del _HELD[self._key]
                os.close(held[0])  # releases the lock
        self._key = None
        return False
