"""OpenCL runtime: device selection, one context object, cached programs.

:class:`ClContext` owns the context, the queue and a cache of built programs
keyed on ``(file, defines)``; kernels are fetched once per program.  Every
stage of the pipeline takes a ``ClContext``; there is no module-level
singleton.

What the stages need to know about the chosen device (its class, limits
and declared quirks, and the rules that pick kernel variants) is
``ClContext.profile``, a :class:`mccnn_cl.opencl.device.DeviceProfile`.

Device selection (:func:`select_device`):

* an explicit ``device`` argument wins: a ``pyopencl.Device``, ``"cpu"``,
  ``"gpu"``, ``"PLATFORM[:DEVICE]"`` substrings (case-insensitive; PLATFORM of the
  platform's name or version string, so ``"pocl"`` finds PoCL; DEVICE of the
  device's name, or its type: ``"pocl:cpu"``), or
  ``"P:D"`` indices as in ``PYOPENCL_CTX``;
* else ``$PYOPENCL_CTX`` is honoured (same syntax);
* else a GPU is preferred, then an accelerator, then a CPU.  Ties are broken
  by platform name and *version* (newest first) and device name, never by the
  platform's index alone, because two platforms can share a name and the ICD
  loader does not keep their order stable.
"""

from __future__ import annotations

import atexit
import logging
import os
import re
import sys
import tempfile
import threading
import time
import warnings
import weakref
from contextlib import ExitStack
from dataclasses import dataclass
from importlib import resources

import numpy as np

from . import binaries
from .device import DeviceProfile, type_name
from ..errors import NO_PLATFORM_HELP, InputError, NoOpenCLDeviceError, OpenCLError

log = logging.getLogger(__name__)

_TYPE_RANK = {"GPU": 0, "ACCELERATOR": 1, "CPU": 2}


def _cl():
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - dependency missing
        raise NoOpenCLDeviceError(f"pyopencl is not installed ({exc}); pip install pyopencl") from exc
    return cl


_TRACKED = {}


def _tracked_buffer_class(cl):
    """A ``pyopencl.Buffer`` subclass whose release (explicit, or by garbage
    collection) is reported to :class:`MemoryTracker` exactly once."""
    cls = _TRACKED.get(id(cl))
    if cls is None:
        class TrackedBuffer(cl.Buffer):
            _on_free = None

            def release(self):
                if self._on_free is not None:
                    self._on_free()
                super().release()

        cls = _TRACKED[id(cl)] = TrackedBuffer
    return cls


class MemoryTracker:
    """Bytes of device buffers made through a :class:`ClContext` (``to_device``,
    ``empty``): ``live`` now, ``peak`` since the last :meth:`reset_peak`.
    Buffers made directly with pyopencl are not counted."""

    def __init__(self):
        self.live = 0
        self.peak = 0

    def add(self, buf, nbytes: int):
        self.live += nbytes
        self.peak = max(self.peak, self.live)
        buf._on_free = weakref.finalize(buf, self._free, nbytes)

    def _free(self, nbytes: int):
        self.live -= nbytes

    def reset_peak(self) -> None:
        self.peak = self.live


class Arena:
    """Sub-buffers carved front to back from one lent buffer (``parent``),
    each at an offset aligned for sub-buffers (the device's
    ``CL_DEVICE_MEM_BASE_ADDR_ALIGN``, at least a page).

    Why: a stage's scratch that is dead before another stage's buffer is
    first written can live inside that buffer (the network's maps inside the
    SGM output volume, which is written only after the cost volume is
    complete): fewer device bytes at once, and on CPU devices fewer fresh
    pages to map on a first call.  The sub-buffers are not counted in
    ``ctx.memory`` (the parent is)."""

    def __init__(self, ctx: "ClContext", parent):
        self.ctx = ctx
        self.parent = parent
        self.size = int(parent.size)
        self.offset = 0
        self.align = ctx.sub_buffer_align
        self.refused = False

    def carve(self, nbytes: int):
        """A sub-buffer of ``nbytes`` at the next aligned offset, or None when it
        does not fit, or when the runtime refuses sub-buffers (then never again
        from this arena: one warning, and the caller makes a buffer of its own)."""
        start = round_up(self.offset, self.align)
        if self.refused or start + int(nbytes) > self.size:
            return None
        try:
            sub = self.parent.get_sub_region(start, int(nbytes))
        except self.ctx.cl.Error as exc:
            self.refused = True
            log.warning("%s refused a sub-buffer (%s); the network's maps get buffers of their own",
                        self.ctx.describe(), str(exc).splitlines()[0])
            return None
        self.offset = start + int(nbytes)
        return sub


class BufferPool:
    """Device buffers kept for reuse between the stages of a run and between
    runs: :meth:`take` hands out a free buffer of at least ``nbytes`` (the
    smallest such), else carves one from a lent :class:`Arena` (see
    :meth:`lend`), else frees the (too small) free ones and makes a new one;
    :meth:`give` returns buffers.

    Why: a fresh buffer's pages are mapped on first touch, which on CPU
    devices costs several times a full pass over it (PoCL, 394 MiB: first
    write ~200 ms, later writes ~40 ms; release ~35 ms), and GPU allocations
    are costly too.  Buffers stay counted in ``ctx.memory`` while free; the
    owner frees them with :meth:`clear` or :meth:`trim`.
    """

    def __init__(self, ctx: "ClContext"):
        self.ctx = ctx
        self._free: list = []
        self._arena = None
        self._carved: list = []  # sub-buffers of the lent arena, until end_loan

    def take(self, nbytes: int, what: str = "buffer"):
        nbytes = max(int(nbytes), 4)
        fits = [i for i, b in enumerate(self._free) if b.size >= nbytes]
        if fits:
            return self._free.pop(min(fits, key=lambda i: self._free[i].size))
        if self._arena is not None:
            sub = self._arena.carve(nbytes)
            if sub is not None:
                self._carved.append(sub)
                return sub
        self.clear()  # every free buffer is too small for this size: don't hold them beside the new one
        return self.ctx.empty(nbytes, what)

    def give(self, *bufs) -> None:
        for b in bufs:
            if b is not None and not any(b is f for f in self._free):
                self._free.append(b)

    def lend(self, arena: Arena) -> None:
        """Carve buffers from ``arena`` (shared by several pools, front to back)
        when no free buffer fits, until :meth:`end_loan`."""
        if self._arena is not None:
            raise RuntimeError("this pool already holds a lent arena")
        self._arena = arena

    def end_loan(self, check: bool = True) -> None:
        """Release the sub-buffers carved from the lent arena and stop carving;
        the arena's buffer is its owner's again.  ``check``: raise if one was
        not given back (False after an error, when some may still be out).
        Work already queued on the sub-buffers still runs (OpenCL keeps a
        released object until its commands complete)."""
        out = [b for b in self._carved if not any(b is f for f in self._free)] if check else []
        self._free = [f for f in self._free if not any(f is b for b in self._carved)]
        for b in self._carved:
            b.release()
        self._carved, self._arena = [], None
        if out:
            raise RuntimeError(f"{len(out)} buffer(s) carved from a lent arena were not given back before its end")

    @property
    def free_bytes(self) -> int:
        """Bytes of the free buffers this pool owns (carved sub-buffers not counted)."""
        return sum(int(b.size) for b in self._free if not any(b is c for c in self._carved))

    def trim(self, keep=None) -> None:
        """Release the free buffers whose size is not ``keep`` (all if None)."""
        kept = []
        for b in self._free:
            if keep is not None and int(b.size) == max(int(keep), 4):
                kept.append(b)
            else:
                b.release()
                self._carved = [c for c in self._carved if c is not b]
        self._free = kept

    def clear(self) -> None:
        self.trim(None)


def _version_tuple(text: str) -> tuple:
    """Numbers found in a version string, for ordering: 'OpenCL 3.0 PoCL 3.1' -> (3, 0, 3, 1)."""
    return tuple(int(n) for n in re.findall(r"\d+", text)[:6])


def _device_type_name(dev) -> str:
    return type_name(dev, _cl())


@dataclass
class DeviceInfo:
    """One OpenCL device as seen by :func:`list_devices`."""

    platform_index: int
    device_index: int
    platform: str
    platform_version: str
    device: str
    type: str
    handle: object  # pyopencl.Device

    def rank(self) -> tuple:
        """Sort key: GPU first, then newer platform version, then names."""
        vers = tuple(-v for v in _version_tuple(self.platform_version))
        return (_TYPE_RANK.get(self.type, 9), vers, self.platform, self.device)

    def __str__(self) -> str:
        return f"{self.device} [{self.type}] on {self.platform} ({self.platform_version})"


def list_devices() -> list[DeviceInfo]:
    """All OpenCL devices of all platforms, in preference order.

    Raises :class:`NoOpenCLDeviceError` (with install instructions) when no
    platform is found.
    """
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise NoOpenCLDeviceError(NO_PLATFORM_HELP + f" (pyopencl said: {exc})") from exc
    out = []
    for pi, plat in enumerate(platforms):
        try:
            devices = plat.get_devices()
        except cl.Error:
            continue
        for di, dev in enumerate(devices):
            out.append(
                DeviceInfo(pi, di, plat.name.strip(), plat.version.strip(), dev.name.strip(),
                           _device_type_name(dev), dev)
            )
    if not out:
        raise NoOpenCLDeviceError(NO_PLATFORM_HELP)
    out.sort(key=DeviceInfo.rank)
    return out


def select_device(spec=None):
    """Choose a device; returns ``(pyopencl.Device, reason)``. See module docstring."""
    cl = _cl()
    if isinstance(spec, cl.Device):
        return spec, "given as a pyopencl.Device"
    reason = "argument"
    if spec is None and os.environ.get("PYOPENCL_CTX"):
        spec, reason = os.environ["PYOPENCL_CTX"], "PYOPENCL_CTX"
    devices = list_devices()
    if spec is None:
        return devices[0].handle, "default preference: GPU > accelerator > CPU, newest platform version"
    spec = str(spec).strip()
    low = spec.lower()
    if low in ("gpu", "cpu", "accelerator"):
        hits = [d for d in devices if d.type.lower() == low]
        if not hits:
            raise NoOpenCLDeviceError(f"no OpenCL {low.upper()} device; found: " + "; ".join(map(str, devices)))
        return hits[0].handle, f"{reason} {spec!r}"
    m = re.fullmatch(r"(\d*)(?::(\d*))?", spec)
    if m:  # PYOPENCL_CTX syntax: platform index[:device index]
        pi = int(m.group(1)) if m.group(1) else 0
        di = int(m.group(2)) if m.group(2) else 0
        for d in devices:
            if d.platform_index == pi and d.device_index == di:
                return d.handle, f"{reason} {spec!r} (indices)"
        raise NoOpenCLDeviceError(f"no OpenCL device at index {spec!r}; found: " + "; ".join(
            f"{d.platform_index}:{d.device_index} {d}" for d in devices))
    pname, _, dname = spec.partition(":")
    # the platform part matches its name or version string (PoCL's name is
    # "Portable Computing Language", its version "OpenCL 3.0 PoCL 3.1 ..."),
    # the device part its name or type ("pocl:cpu")
    hits = [d for d in devices
            if pname.lower() in f"{d.platform} {d.platform_version}".lower()
            and (dname.lower() in d.device.lower() or dname.lower() == d.type.lower())]
    if not hits:
        raise NoOpenCLDeviceError(f"no OpenCL device matches {spec!r}; found: " + "; ".join(map(str, devices)))
    return hits[0].handle, f"{reason} {spec!r} (name match)"


def kernel_source_dir():
    """Context manager yielding the real directory holding the ``.cl`` files."""
    return resources.as_file(resources.files("mccnn_cl.kernels"))


#: Show the OpenCL compiler's own summary lines ("N warnings generated."),
#: which PoCL's clang writes straight to the process's stderr during a build;
#: set by ``mccnn-cl --verbose`` (or MCCNN_COMPILER_OUTPUT=1).  The build log
#: itself goes through PyOpenCL's CompilerWarning.
COMPILER_OUTPUT = os.environ.get("MCCNN_COMPILER_OUTPUT", "") not in ("", "0")
_SUMMARY = re.compile(r"^\d+ (warning|error)s? generated\.\s*$")
_BUILD_LOCK = threading.Lock()


def _filter_compiler_output(text: str) -> str:
    """``text`` less the compiler's summary lines (unless :data:`COMPILER_OUTPUT`)."""
    if COMPILER_OUTPUT:
        return text
    return "".join(line for line in text.splitlines(keepends=True) if not _SUMMARY.match(line))


def _build_quietly(build):
    """Run ``build()`` with file descriptor 2 captured; what it wrote goes back
    to stderr less the compiler's summary lines, and the build log of a build
    that succeeded (PyOpenCL's CompilerWarning) goes to this module's debug log
    instead of the caller's terminal, unless :data:`COMPILER_OUTPUT`.  A failed
    build raises with its log either way.  Builds are serialised (the
    descriptor is the process's)."""
    with _BUILD_LOCK:
        return _logs_to_debug(lambda: _stderr_filtered(build))


def _logs_to_debug(build):
    """``build()`` with PyOpenCL's CompilerWarnings logged at debug level (the
    other warnings it raises are re-issued as they came)."""
    if COMPILER_OUTPUT:
        return build()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            return build()
    finally:  # the caller's filters are back: what is not a build log goes through them
        for w in caught:
            if _is_compiler_warning(w.category):
                log.debug("build log (MCCNN_COMPILER_OUTPUT=1 or --verbose shows it): %s", w.message)
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)


def _is_compiler_warning(category) -> bool:
    """PyOpenCL's CompilerWarning (named, so that pyopencl need not be imported here)."""
    return category.__name__ == "CompilerWarning" and category.__module__.split(".")[0] == "pyopencl"


def _stderr_filtered(build):
    """``build()`` with file descriptor 2 captured, written back less the
    compiler's summary lines."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        return build()
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                return build()
            finally:
                os.dup2(saved, 2)
                tmp.seek(0)
                rest = _filter_compiler_output(tmp.read().decode("utf-8", "replace"))
                if rest:
                    sys.stderr.write(rest)
                    sys.stderr.flush()
    finally:
        os.close(saved)


def _format_define(value) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value)) + "f"
    return str(value)


#: Longest time (seconds) :meth:`ClContext.wait` goes without running Python's signal handlers
#: (Ctrl-C): the process's signals can be delivered to any of its threads, the runtime's included,
#: and then do not wake a waiting main thread.
WAIT_SIGNALS = 0.02

#: Longest time (seconds) the interpreter's exit waits for :meth:`ClContext.wait`'s helper
#: threads still blocked in the runtime (after an interrupted wait: the work already queued).
WAIT_AT_EXIT = 60.0

#: :meth:`ClContext.wait`'s helper threads still blocked in the runtime.
_WAITERS: set = set()
_WAITERS_LOCK = threading.Lock()


def _join_waiters(timeout=None) -> None:
    """Let the helper threads of interrupted waits return before the interpreter finalizes
    (registered with :mod:`atexit`, which runs while threads may still take the GIL).  A daemon
    thread whose blocking wait returned during finalization was ended by the interpreter inside
    PyOpenCL's C++ (its GIL reacquisition), and the process aborted with "terminate called without
    an active exception" (status -6) instead of exiting 130 after Ctrl-C: a race, seen once in a
    fresh-clone test run (``tests/test_robustness.py::test_ctrl_c_is_answered_within_seconds``).
    The wait is the work already queued, which :meth:`ClContext.pace` bounds to about two steps."""
    deadline = time.monotonic() + (WAIT_AT_EXIT if timeout is None else float(timeout))
    with _WAITERS_LOCK:
        waiters = list(_WAITERS)
    for t in waiters:
        t.join(max(0.0, deadline - time.monotonic()))


atexit.register(_join_waiters)


class ClContext:
    """Context, queue and program cache for one OpenCL device.

    Parameters
    ----------
    device : None, str or pyopencl.Device
        See :func:`select_device`.
    profiling : bool
        Create the queue with profiling enabled (for ``bench/``).
    """

    def __init__(self, device=None, profiling: bool = False):
        cl = _cl()
        self.cl = cl
        dev, self.reason = select_device(device)
        self.device = dev
        #: what the stages need to know about the device (mccnn_cl.opencl.device)
        self.profile = DeviceProfile.of(dev, cl)
        from .tune_cache import load as load_tuned  # the choices measured on this device (MCCNN_TUNE=off: none)

        self.profile.tuned.update(load_tuned(dev))
        self.context = cl.Context([dev])
        props = cl.command_queue_properties.PROFILING_ENABLE if profiling else 0
        self.queue = cl.CommandQueue(self.context, properties=props)
        self._programs: dict = {}
        #: programs built from source (the runtime may have served them from its
        #: own cache) and made from a binary stored by :mod:`mccnn_cl.opencl.binaries`
        self.builds = 0
        self.binary_loads = 0
        #: seconds spent making programs (builds and binary loads)
        self.build_seconds = 0.0
        #: store the binary of every program built from source (mccnn_cl.opencl.binaries)
        self.save_binaries = False
        self._kernels: dict = {}
        self.memory = MemoryTracker()
        self._buffer = _tracked_buffer_class(cl)
        self._sub_buffers = None  # probed on first use (sub_buffers)
        self._exit = ExitStack()
        self.kernel_dir = str(self._exit.enter_context(kernel_source_dir()))
        log.info("mccnn_cl OpenCL device: %s (%s)", self.describe(), self.reason)

    # -- device facts -------------------------------------------------
    @property
    def max_alloc(self) -> int:
        """CL_DEVICE_MAX_MEM_ALLOC_SIZE in bytes."""
        return int(self.device.max_mem_alloc_size)

    @property
    def sub_buffer_align(self) -> int:
        """Byte alignment of a sub-buffer's offset: CL_DEVICE_MEM_BASE_ADDR_ALIGN
        (given in bits), at least 4096 (both powers of two)."""
        return max(4096, int(self.device.mem_base_addr_align) // 8)

    @property
    def sub_buffers(self) -> bool:
        """Whether the runtime makes a sub-buffer at an aligned offset
        (:attr:`sub_buffer_align`), probed once with a small buffer; where it
        does not, nothing is lent (:class:`Arena`) and the memory plan counts
        no lent bytes."""
        if self._sub_buffers is None:
            align = self.sub_buffer_align
            probe = self.cl.Buffer(self.context, self.cl.mem_flags.READ_WRITE, size=2 * align)
            try:
                probe.get_sub_region(align, align).release()
                self._sub_buffers = True
            except self.cl.Error as exc:
                self._sub_buffers = False
                log.warning("%s makes no sub-buffers (%s); the network's maps get buffers of their own",
                            self.describe(), str(exc).splitlines()[0])
            finally:
                probe.release()
        return self._sub_buffers

    @property
    def global_mem(self) -> int:
        return int(self.device.global_mem_size)

    @property
    def local_mem(self) -> int:
        return int(self.device.local_mem_size)

    @property
    def max_work_group(self) -> int:
        return int(self.device.max_work_group_size)

    @property
    def has_fp64(self) -> bool:
        return "cl_khr_fp64" in self.device.extensions

    def describe(self) -> str:
        d = self.device
        return f"{d.name.strip()} on {d.platform.name.strip()} ({d.platform.version.strip()})"

    def check_alloc(self, nbytes: int, what: str) -> None:
        """Raise :class:`InputError` if one buffer of ``nbytes`` cannot exist on the device."""
        if nbytes > self.max_alloc:
            raise InputError(
                f"{what} needs {nbytes / 2**20:.0f} MiB in one buffer, more than the device's "
                f"max allocation ({self.max_alloc / 2**20:.0f} MiB on {self.describe()}); "
                "reduce the disparity range or the image size")

    # -- programs and kernels ----------------------------------------
    def program(self, filename: str, **defines):
        """Build ``kernels/<filename>`` with ``-D`` defines; cached per (file, defines)."""
        key = (filename, tuple(sorted((k, _format_define(v)) for k, v in defines.items())))
        prg = self._programs.get(key)
        if prg is not None:
            return prg
        path = os.path.join(self.kernel_dir, filename)
        try:
            with open(path, encoding="utf-8") as f:
                src = f.read()
        except OSError as exc:
            raise OpenCLError(f"kernel source {filename} not found in {self.kernel_dir}") from exc
        options = ["-I", self.kernel_dir] + [f"-D{k}={v}" for k, v in key[1]]
        t0 = time.perf_counter()
        try:
            prg = self._make_program(filename, src, options)
        finally:
            self.build_seconds += time.perf_counter() - t0
        self._programs[key] = prg
        return prg

    def _make_program(self, filename, src, options):
        prg = self._from_binary(src, options)
        if prg is None:
            try:
                prg = _build_quietly(lambda: self.cl.Program(self.context, src).build(options=options))
            except self.cl.RuntimeError as exc:
                raise OpenCLError(
                    f"building {filename} with {' '.join(options[2:])} failed on {self.describe()}:\n{exc}"
                ) from exc
            if self.save_binaries and binaries.enabled():
                binaries.store(binaries.key(self.device, self.kernel_dir, src, options), prg.binaries[0])
            self.builds += 1
        else:
            self.binary_loads += 1
        return prg

    def _from_binary(self, src, options):
        """The program made from its stored binary (:mod:`mccnn_cl.opencl.binaries`), or None."""
        if not binaries.enabled():
            return None
        k = binaries.key(self.device, self.kernel_dir, src, options)
        blob = binaries.load(k)
        if blob is None:
            return None
        try:
            return _build_quietly(lambda: self.cl.Program(self.context, [self.device], [blob]).build(options=options))
        except self.cl.Error as exc:
            log.warning("a stored kernel binary was refused (%s); building from source", str(exc).splitlines()[0])
            binaries.discard(k)
            return None

    def kernel(self, filename: str, name: str, **defines):
        """One kernel object from a cached program (fetched once, reused)."""
        prg = self.program(filename, **defines)
        k = (id(prg), name)
        kern = self._kernels.get(k)
        if kern is None:
            kern = self.cl.Kernel(prg, name)
            self._kernels[k] = kern
        return kern

    def work_group_size(self, kernel) -> int:
        """Largest work-group size this kernel may be launched with on this device."""
        return int(kernel.get_work_group_info(self.cl.kernel_work_group_info.WORK_GROUP_SIZE, self.device))

    # -- buffers -------------------------------------------------------
    def to_device(self, array: np.ndarray, writable: bool = False):
        """Copy a host array to a new read-only buffer (C-contiguous); read-write
        with ``writable`` (for kernels that work in place)."""
        a = np.ascontiguousarray(array)
        self.check_alloc(a.nbytes, "input buffer")
        mf = self.cl.mem_flags
        buf = self._buffer(self.context, (mf.READ_WRITE if writable else mf.READ_ONLY) | mf.COPY_HOST_PTR, hostbuf=a)
        self.memory.add(buf, max(a.nbytes, 1))
        return buf

    def empty(self, nbytes: int, what: str = "buffer"):
        """A new read-write buffer of ``nbytes`` (checked against the max allocation)."""
        self.check_alloc(nbytes, what)
        size = max(int(nbytes), 4)
        buf = self._buffer(self.context, self.cl.mem_flags.READ_WRITE, size=size)
        self.memory.add(buf, size)
        return buf

    def from_device(self, buf, shape, dtype=np.float32) -> np.ndarray:
        """Blocking copy of a device buffer into a new host array (the queue's
        earlier work is waited for interruptibly first, :meth:`wait`)."""
        out = np.empty(shape, dtype=dtype)
        self.wait()
        self.cl.enqueue_copy(self.queue, out, buf)
        return out

    def fill(self, buf, value, nbytes: int, dtype=np.float32) -> None:
        """Fill a buffer with a scalar (used to poison outputs in tests); a
        finite ``value`` that ``dtype`` cannot hold raises ValueError (it would
        become an infinity)."""
        with np.errstate(over="ignore"):
            pattern = np.array([value], dtype=dtype)
        if np.issubdtype(pattern.dtype, np.floating) and np.isinf(pattern[0]) and np.isfinite(value):
            raise ValueError(f"fill value {value!r} does not fit {np.dtype(dtype).name}")
        self.cl.enqueue_fill_buffer(self.queue, buf, pattern, 0, int(nbytes))

    def finish(self) -> None:
        """Wait for everything queued; Python handles signals meanwhile (Ctrl-C
        raises KeyboardInterrupt within milliseconds, see :meth:`wait`)."""
        self.wait()

    def wait(self, event=None) -> None:
        """Wait for ``event`` (default: a marker after everything queued): a
        helper thread makes the runtime's blocking wait while the main thread
        waits for that thread on a ``threading.Event``, returning to Python
        every :data:`WAIT_SIGNALS` seconds so that Ctrl-C raises
        KeyboardInterrupt within that time (the work already queued drains in
        the background, :meth:`pace`); the work's end wakes it at once.  An error
        status raises as ``event.wait()`` does.

        Why a blocking wait: Intel's CPU runtime also runs kernels on the
        threads blocked in its waits.  Polled instead (this method's former
        form: sleeps of up to 1 ms between status checks), it ran every
        kernel of a 2-core device on one core: the paired SGM sweeps took 300
        against 156 ms, a KITTI pair 3.6 s against 2 s.  PoCL runs kernels on
        its own threads either way.  Why not on the main thread: a blocking
        call there holds off signals until the work is done.  (Completion
        callbacks crashed Rusticl at exit: "terminate called without an
        active exception".)  After an interrupted wait the interpreter's exit
        waits for the helper thread (:func:`_join_waiters`, at most
        :data:`WAIT_AT_EXIT` seconds)."""
        cl = self.cl
        if event is None:
            event = cl.enqueue_marker(self.queue)
        self.queue.flush()
        if event.command_execution_status > cl.command_execution_status.COMPLETE:
            done = threading.Event()

            def block():
                try:
                    event.wait()
                except Exception:  # noqa: BLE001 - raised again by the event.wait() below
                    pass
                finally:
                    done.set()
                    with _WAITERS_LOCK:
                        _WAITERS.discard(threading.current_thread())

            helper = threading.Thread(target=block, name="mccnn_cl wait", daemon=True)
            with _WAITERS_LOCK:
                _WAITERS.add(helper)
            helper.start()
            while not done.wait(WAIT_SIGNALS):  # a signal may land on any thread: look every WAIT_SIGNALS
                pass
        event.wait()

    def pace(self) -> None:
        """Bound the work queued ahead of the host to about two steps: mark the
        queue and wait (interruptibly, :meth:`wait`) for the previous mark.
        Long computations call this between launches (network chunks, stages),
        so an interrupted run leaves at most two steps to drain before the
        process can exit, and the device still always has the next step queued."""
        marker = self.cl.enqueue_marker(self.queue)
        self.queue.flush()
        previous, self._paced = getattr(self, "_paced", None), marker
        if previous is not None:
            self.wait(previous)

    def close(self) -> None:
        self._exit.close()


def launch_sizes(ctx, global_size, local_size=None, guarded=None):
    """``(global, local)`` of a launch whose work-group size was not chosen by
    the stage (``local_size`` None): the profile's ``launch_local`` sizes
    (:data:`mccnn_cl.opencl.device.RULES`), the global size rounded up to them, on
    devices that compile a kernel anew for every work-group size (PoCL: left
    to the runtime, the work-group size follows the image size, and each new
    image size cost a compile of every such kernel at its first launch); the
    runtime's choice (None) elsewhere.  ``guarded``: per dimension, whether
    the kernel returns for work-items beyond the sizes it is given (default:
    every dimension); an unguarded dimension gets work-groups of 1."""
    glob = tuple(int(g) for g in global_size)
    if local_size is not None:
        return glob, tuple(int(n) for n in local_size)
    fixed = ctx.profile.launch_local
    if not fixed:
        return glob, None
    guarded = (True,) * len(glob) if guarded is None else tuple(guarded)
    local = tuple(int(fixed[i]) if guarded[i] else 1 for i in range(len(glob)))
    return tuple(round_up(g, n) for g, n in zip(glob, local)), local


def launch(ctx, stage: str, kernel, global_size, *args, local_size=None, guarded=None) -> None:
    """Set ``kernel``'s arguments and enqueue it on ``ctx``'s queue over
    ``global_size`` (work-group ``local_size``, or :func:`launch_sizes`'
    choice when None); an OpenCL error is raised as :class:`OpenCLError`
    naming ``stage``."""
    from ..errors import OpenCLError

    glob, local = launch_sizes(ctx, global_size, local_size, guarded)
    try:
        kernel.set_args(*args)
        ctx.cl.enqueue_nd_range_kernel(ctx.queue, kernel, glob, local)
    except ctx.cl.Error as exc:
        raise OpenCLError(f"{stage}: OpenCL error {exc}") from exc


def round_up(n: int, m: int) -> int:
    """Smallest multiple of ``m`` that is >= ``n``."""
    return ((int(n) + m - 1) // m) * m
