"""Atomic file writes: a temporary file in the destination's folder, then ``os.replace``.

An interrupted write never leaves a half-written file under the final name.
The temporary files carry a recognisable name,
``.mccnn-tmp-<host>.<pid>-<random><ext>`` (hidden, in the destination's folder
so the rename stays on one file system; ``<host>`` is this machine's name
reduced to letters, digits and dashes, :func:`host_tag`).  A process killed
while writing (SIGKILL, power loss) cannot remove its own: the next write into
that folder removes them (:func:`remove_stale`), so a crash leaves at most one
stray file until the folder is written to again.  Whether a writer is dead is
known only for this machine's: its file goes at once when its pid no longer
runs, a running one's (another mccnn-cl writing there now) is left alone.  A
folder may be shared between machines (an NFS home directory holds
``~/.cache/mccnn_cl``), and a pid says nothing of another machine's
processes: another host's file, or a name this version cannot read (an older
version's ``.mccnn-tmp-<pid>-…``), is removed only once unchanged for
:data:`STALE_SECONDS`.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import socket
import stat
import tempfile
import time

from .errors import InputError

#: Prefix of every temporary file (followed by :func:`temp_prefix`'s host and pid).
PREFIX = ".mccnn-tmp-"
#: A temporary file of another host (or one whose name cannot be read) unchanged
#: this long is a dead writer's: a write takes seconds to minutes, and the margin
#: covers clocks of the machines sharing a folder that disagree.
STALE_SECONDS = 3600.0
#: The longest :func:`host_tag`.
HOST_TAG_MAX = 40
_NAME = re.compile(re.escape(PREFIX) + r"([A-Za-z0-9-]{1,%d})\.(\d+)-" % HOST_TAG_MAX)


def host_tag(name=None) -> str:
    """``name`` (default: this machine's, ``socket.gethostname()``) as it stands in a
    temporary file's name: every character but ASCII letters, digits and dashes
    made a dash, at most :data:`HOST_TAG_MAX` characters (a longer one keeps its
    start and a hash of the whole, so that two long names stay apart)."""
    if name is None:
        try:
            name = socket.gethostname()
        except OSError:
            name = ""
    tag = re.sub(r"[^A-Za-z0-9-]", "-", name) or "unknown"
    if len(tag) > HOST_TAG_MAX:
        digest = hashlib.sha256(name.encode("utf-8", "surrogateescape")).hexdigest()[:8]
        tag = f"{tag[:HOST_TAG_MAX - 9]}-{digest}"
    return tag


def temp_prefix(pid=None, host=None) -> str:
    """The start of the temporary files' names of process ``pid`` (default: this one)
    on host ``host`` (default: this one; given as :func:`host_tag` makes it):
    ``.mccnn-tmp-<host>.<pid>-``, a random part and the extension follow."""
    return f"{PREFIX}{host_tag() if host is None else host}.{os.getpid() if pid is None else pid}-"


def parse_temp_name(name: str):
    """``(host, pid)`` of a temporary file's name (:func:`temp_prefix`), None when
    ``name`` is not one or cannot be read (an older version's ``.mccnn-tmp-<pid>-…``)."""
    m = _NAME.match(name)
    return None if m is None else (m.group(1), int(m.group(2)))


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


def remove_files(directory, max_age) -> list:
    """Remove the regular files of ``directory`` (links and folders are kept) for
    which ``max_age(name)`` says so: None keeps the file, 0 removes it, a number of
    seconds removes it once unchanged (its mtime) for longer than that.  Returns
    their paths.  Errors (a file already gone, no permission) are ignored: a stray
    file never stops a write."""
    removed = []
    try:
        names = os.listdir(directory)
    except OSError:
        return removed
    now = time.time()
    for name in names:
        limit = max_age(name)
        if limit is None:
            continue
        path = os.path.join(directory, name)
        try:
            st = os.lstat(path)
            if not stat.S_ISREG(st.st_mode) or (limit > 0 and now - st.st_mtime <= limit):
                continue
            os.unlink(path)
            removed.append(path)
        except OSError:
            pass
    return removed


def _stale_after(name: str, here: str):
    """:func:`remove_files`'s verdict on ``name`` for :func:`remove_stale` (``here``: this host's tag)."""
    if not name.startswith(PREFIX):
        return None
    parsed = parse_temp_name(name)
    if parsed is None or parsed[0] != here:
        return STALE_SECONDS  # another host's writer, or another version's name: its pid means nothing here
    return None if _alive(parsed[1]) else 0


def remove_stale(directory) -> list:
    """Remove the temporary files in ``directory`` left by writers that are no
    longer running; returns their paths.  This host's are removed when their pid
    no longer runs; another host's, and names that cannot be read
    (:func:`parse_temp_name`), only when unchanged for :data:`STALE_SECONDS` (a
    pid is no news of another machine: the file may be a write in progress
    there).  Errors (a file already gone, no permission) are ignored: a stray
    file never stops a write."""
    here = host_tag()
    return remove_files(directory, lambda name: _stale_after(name, here))


def _mkstemp(directory, suffix=""):
    try:
        return tempfile.mkstemp(prefix=temp_prefix(), suffix=suffix, dir=directory)
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
