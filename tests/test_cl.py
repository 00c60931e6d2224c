"""The OpenCL runtime module: device choice, program cache, clear errors."""

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from mccnn_cl.opencl.context import ClContext, list_devices, select_device
from mccnn_cl.errors import InputError, NoOpenCLDeviceError, OpenCLError


def test_device_choice_by_type_name_and_index(ctx):
    devices = list_devices()
    assert devices, "no OpenCL device"
    first = devices[0]
    dev, reason = select_device(first.type.lower())
    assert dev == first.handle and first.type.lower() in reason
    dev, _ = select_device(first.platform[:6] + ":" + first.device[:4])
    assert dev.name.strip() == first.device
    dev, _ = select_device(f"{first.platform_index}:{first.device_index}")
    assert dev == first.handle
    with pytest.raises(NoOpenCLDeviceError, match="no OpenCL device matches"):
        select_device("no-such-platform-xyz")
    with pytest.raises(NoOpenCLDeviceError, match="index"):
        select_device("97:3")


def test_preference_order_is_by_type_then_version():
    ranks = [d.rank() for d in list_devices()]
    assert ranks == sorted(ranks)


def test_pyopencl_ctx_is_honoured(monkeypatch):
    d = list_devices()[-1]
    monkeypatch.setenv("PYOPENCL_CTX", f"{d.platform_index}:{d.device_index}")
    dev, reason = select_device(None)
    assert dev == d.handle and reason.startswith("PYOPENCL_CTX")


def test_program_cache_and_defines(ctx, tmp_path, monkeypatch):
    src = os.path.join(ctx.kernel_dir, "common.h")
    assert os.path.exists(src)
    # build a probe kernel from a private copy of the kernel directory
    shutil.copy(src, tmp_path / "common.h")
    monkeypatch.setattr(ctx, "kernel_dir", str(tmp_path))
    # a program built twice with the same defines is the same object; other defines rebuild
    probe = "_probe_test.cl"
    path = os.path.join(ctx.kernel_dir, probe)
    with open(path, "w") as f:
        f.write('#include "common.h"\n#ifndef N\n#error N required\n#endif\n'
                "__kernel void probe_fill(__global float *out) { size_t i = get_global_id(0);"
                " out[i] = (float)(N) + (float)VIDX(0, 0, i, 1, 1); }\n")
    k1 = ctx.kernel(probe, "probe_fill", N=3)
    assert ctx.kernel(probe, "probe_fill", N=3) is k1
    assert ctx.program(probe, N=3) is ctx.program(probe, N=3)
    assert ctx.program(probe, N=4) is not ctx.program(probe, N=3)
    buf = ctx.empty(16 * 4)
    k1(ctx.queue, (16,), None, buf)
    np.testing.assert_array_equal(ctx.from_device(buf, (16,)), 3 + np.arange(16, dtype=np.float32))
    with pytest.raises(OpenCLError, match=r"_probe_test.cl.*failed"):
        ctx.program(probe)  # N missing -> #error, message names file


def test_check_alloc(ctx):
    with pytest.raises(InputError, match="max allocation"):
        ctx.check_alloc(ctx.max_alloc + 1, "cost volume")
    ctx.check_alloc(1024, "small")


def test_no_platform_gives_install_hint(tmp_path):
    env = dict(os.environ, OCL_ICD_VENDORS=str(tmp_path))
    env.pop("PYOPENCL_CTX", None)
    code = ("from mccnn_cl.opencl.context import ClContext\n"
            "from mccnn_cl.errors import NoOpenCLDeviceError\n"
            "try:\n    ClContext()\nexcept NoOpenCLDeviceError as e:\n    print('ERR', e)\n")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert "ERR no OpenCL platform found" in r.stdout, (r.stdout, r.stderr)
    assert "pocl-opencl-icd" in r.stdout


def test_wait_returns_after_the_work(ctx):
    """ctx.wait (a helper thread's blocking wait, the main thread answering
    Ctrl-C meanwhile) returns once the event completed: the copy's result is
    there, the marker COMPLETE; finish() (a marker after everything queued)
    likewise."""
    n = 4_000_000
    src = ctx.to_device(np.arange(n, dtype=np.float32))
    dst = ctx.empty(4 * n, "copy")
    ctx.fill(dst, np.float32(-1), 4 * n)
    ctx.cl.enqueue_copy(ctx.queue, dst, src)
    marker = ctx.cl.enqueue_marker(ctx.queue)
    ctx.wait(marker)
    assert marker.command_execution_status == ctx.cl.command_execution_status.COMPLETE
    out = np.empty(n, np.float32)
    ctx.cl.enqueue_copy(ctx.queue, out, dst, is_blocking=False)
    ctx.finish()
    np.testing.assert_array_equal(out, np.arange(n, dtype=np.float32))


BUSY = textwrap.dedent('''
    import os, sys, time
    import numpy as np
    from mccnn_cl.opencl.context import ClContext
    ctx = ClContext(sys.argv[1] or None)
    # 20 000 iterations a work-item (under llvmpipe's loop limit); the work-items make the time
    prg = ctx.cl.Program(ctx.context, """
    __kernel void busy(__global float *a) {
        float x = a[get_global_id(0)];
        for (int j = 0; j < 20000; ++j)
            x = x * 0.999f + 0.5f;
        a[get_global_id(0)] = x;
    }""").build()
    k = ctx.cl.Kernel(prg, "busy")
    g = 64
    while True:  # a launch of ~0.2 s on this device
        buf = ctx.empty(4 * g)
        k(ctx.queue, (g,), None, buf)  # untimed: a new size may compile (PoCL: per work-group size; cold: seconds)
        ctx.finish()
        t = time.perf_counter()
        k(ctx.queue, (g,), None, buf)
        ctx.finish()
        dt = time.perf_counter() - t
        if dt > 0.05 or g >= 1 << 24:
            break
        g *= 4
    g = max(1, int(g * min(0.2 / max(dt, 1e-6), 64)))
    buf = ctx.empty(4 * g)
    for _ in range(int(sys.argv[2]) if len(sys.argv) > 2 else 100):  # 100: ~20 s of work queued
        k(ctx.queue, (g,), None, buf)
    print("waiting", flush=True)
    try:
        ctx.finish()
        print("finished", flush=True)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
        if len(sys.argv) > 3:  # exit as the command line does after Ctrl-C: the interpreter finalizes
            sys.exit(130)
    os._exit(0)  # without draining the queue
''')


def test_exit_after_an_interrupted_wait_waits_for_its_helper(ctx, request, tmp_path):
    """After Ctrl-C interrupted a wait, the helper thread is still blocked in the runtime until
    the work already queued is done; the interpreter's exit waits for it
    (context._join_waiters, atexit) instead of finalizing under it, which could abort the
    process inside PyOpenCL ("terminate called without an active exception", status -6): ~5 s
    of kernels queued, SIGINT half a second into the wait, then a normal exit with status 130,
    which must come after the queued work, not at once."""
    script = tmp_path / "busy.py"
    script.write_text(BUSY)
    p = subprocess.Popen([sys.executable, str(script), request.config.getoption("--cl-device") or "", "25", "exit"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = p.stdout.readline()
        assert line.strip() == "waiting", (line, p.stderr.read() if p.poll() is not None else "")
        time.sleep(0.5)
        p.send_signal(signal.SIGINT)
        line = p.stdout.readline()
        t = time.perf_counter()
        assert line.strip() == "interrupted", (line, p.stderr.read())
        assert p.wait(timeout=60) == 130, p.stderr.read()
        took = time.perf_counter() - t
        assert took > 0.8, f"exited {took:.2f} s after the interrupt, with ~4.5 s of work still queued"
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_join_waiters_returns_when_the_helpers_end():
    """context._join_waiters: joins the registered helper threads, at most for its timeout."""
    import threading

    from mccnn_cl.opencl import context

    done = threading.Event()
    t = threading.Thread(target=done.wait, args=(30,), daemon=True)
    with context._WAITERS_LOCK:
        context._WAITERS.add(t)
    try:
        t.start()
        start = time.perf_counter()
        context._join_waiters(timeout=0.3)  # the helper still runs: back after the timeout
        assert t.is_alive() and 0.25 < time.perf_counter() - start < 5
        done.set()
        context._join_waiters(timeout=30)
        assert not t.is_alive()
    finally:
        done.set()
        with context._WAITERS_LOCK:
            context._WAITERS.discard(t)


def test_ctrl_c_interrupts_a_wait(ctx, request, tmp_path):
    """SIGINT while the main thread waits for queued work (ctx.wait) raises
    KeyboardInterrupt there within a fraction of a second, though the
    process's signals may land on the runtime's threads or on the wait's
    helper thread (whose blocking wait does not return early): ~20 s of
    kernels are queued, the signal comes half a second into the wait."""
    script = tmp_path / "busy.py"
    script.write_text(BUSY)
    p = subprocess.Popen([sys.executable, str(script), request.config.getoption("--cl-device") or ""],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = p.stdout.readline()
        assert line.strip() == "waiting", (line, p.stderr.read() if p.poll() is not None else "")
        time.sleep(0.5)
        t = time.perf_counter()
        p.send_signal(signal.SIGINT)
        line = p.stdout.readline()
        took = time.perf_counter() - t
        assert line.strip() == "interrupted", (line, p.stderr.read())
        assert took < 3.0, f"KeyboardInterrupt came {took:.2f} s after SIGINT, with ~20 s of work queued"
        assert p.wait(timeout=60) == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_fill_refuses_a_value_its_type_cannot_hold(ctx):
    """A finite value that float16 cannot hold would poison with an infinity, silently."""
    buf = ctx.empty(64)
    with pytest.raises(ValueError, match="does not fit float16"):
        ctx.fill(buf, -1.2345e30, 64, np.float16)
    ctx.fill(buf, -65504.0, 64, np.float16)
    ctx.fill(buf, np.inf, 64, np.float16)  # an infinity asked for is one
    got = ctx.from_device(buf, (32,), np.float16)
    assert np.isposinf(got).all()
    ctx.fill(buf, -1.2345e30, 64)
    assert (ctx.from_device(buf, (16,)) == np.float32(-1.2345e30)).all()
