"""No kernel builds for a new image size or disparity count after a warm-up;
launch sizes that do not follow the image size; the compiler's summary lines
kept off the terminal unless asked for."""

import numpy as np
import pytest

import mccnn_cl.opencl.context as clmod
import mccnn_cl.opencl.device as device
from mccnn_cl import StereoMatcher
from mccnn_cl.atomic import PREFIX, parse_temp_name, temp_prefix
from mccnn_cl.opencl.context import launch_sizes
from mccnn_cl.stages.sgm import MAX_LEVELS, _max_disp

from helpers import random_pair as _random_pair


def random_pair(rng, H, W):
    left, right = _random_pair(rng, H, W)
    return left, np.clip(right, 0, 1)


def test_second_size_and_disparity_count_build_nothing(ctx):
    """After one pair, pairs of other sizes and disparity counts (in the same
    power-of-two bucket of D) build no program."""
    rng = np.random.default_rng(11)
    m = StereoMatcher(cost="census", max_disparity=70, device=ctx)
    m.compute(*random_pair(rng, 61, 143))
    before = ctx.builds
    for (H, W, D) in ((57, 157, 100), (70, 135, 128), (49, 121, 90)):
        m.max_disparity = D
        out = m.compute(*random_pair(rng, H, W))
        assert out.shape == (H, W) and np.isfinite(out).all()
    assert ctx.builds == before, "a new image size or D built a program"


def test_max_disp_buckets():
    """SGM's compiled MAX_DISP: a power of two >= D, at least the floor; six values in all
    at the least floor (64), four at the CPU's (256)."""
    assert [_max_disp(d) for d in (1, 32, 33, 64, 65, 228, 256, 257, MAX_LEVELS)] == \
        [64, 64, 64, 64, 128, 256, 256, 512, MAX_LEVELS]
    assert len({_max_disp(d) for d in range(1, MAX_LEVELS + 1)}) == 6
    assert [_max_disp(d, 256) for d in (1, 73, 228, 256, 257, 600, MAX_LEVELS)] == \
        [256, 256, 256, 256, 512, 1024, MAX_LEVELS]
    assert len({_max_disp(d, 256) for d in range(1, MAX_LEVELS + 1)}) == 4


def test_disparity_floor_by_device(ctx):
    """CPUs build SGM for 256 levels at least (so that the program `mccnn-cl tune` stores
    for D 228 serves every D up to 256); llvmpipe and GPUs for 64; a loop limit (llvmpipe's
    bands are sized from MAX_DISP) takes 64 on any device."""
    from mccnn_cl.stages.sgm import SGM

    assert device.RULES["sgm_disp_floor"] == {device.CPU: 256, device.LLVMPIPE: 64, device.GPU: 64}
    sgm = SGM(ctx)
    assert sgm.disp_floor == device.RULES["sgm_disp_floor"][ctx.profile.kind]
    assert sgm.max_disp(40) == max(64, sgm.disp_floor)
    assert SGM(ctx, loop_limit=65535).max_disp(40) == 64


def test_small_and_large_disparity_counts_share_one_sgm_program_on_cpus(ctx):
    """On a CPU device a pair at D 228 and then pairs at D 40 and 73 (other images'
    sizes) build nothing: one SGM program serves D 1 .. 256 there."""
    if ctx.profile.kind != device.CPU:
        pytest.skip(f"the floor of 256 levels is the CPU rule; this device is {ctx.profile.kind}")
    rng = np.random.default_rng(12)
    m = StereoMatcher(cost="census", max_disparity=228, device=ctx)
    m.compute(*random_pair(rng, 20, 240))
    before = ctx.builds
    for (H, W, D) in ((23, 97, 40), (19, 130, 73)):
        m.max_disparity = D
        out = m.compute(*random_pair(rng, H, W))
        assert out.shape == (H, W) and np.isfinite(out).all()
    assert ctx.builds == before, "a smaller D built a program"


def test_launch_local_sizes_do_not_follow_the_image(ctx):
    """Where the profile fixes work-group sizes (PoCL compiles a kernel per
    work-group size), launches of any size share them; the global size is
    rounded up to them; unguarded dimensions get 1; a stage's own choice wins."""
    fixed = ctx.profile.launch_local
    if not fixed:
        assert launch_sizes(ctx, (100, 7)) == ((100, 7), None)
        return
    locals_ = {launch_sizes(ctx, (w, h))[1] for w, h in ((225, 188), (1242, 375), (17, 3))}
    assert locals_ == {tuple(fixed[:2])}
    g, l = launch_sizes(ctx, (1242, 375, 228))
    assert all(gi % li == 0 and gi >= n for gi, li, n in zip(g, l, (1242, 375, 228)))
    assert launch_sizes(ctx, (99, 5), guarded=(1, 0))[1] == (fixed[0], 1)
    assert launch_sizes(ctx, (99, 5), guarded=(1, 0))[0][1] == 5
    assert launch_sizes(ctx, (99, 5), local_size=(3, 1)) == ((99, 5), (3, 1))


def test_fixed_launch_sizes_bit_identical(ctx, monkeypatch):
    """The whole census method with the fixed work-group sizes and with the
    runtime's own choice: the same bits."""
    rng = np.random.default_rng(5)
    left, right = random_pair(rng, 53, 91)
    outs = []
    for local in ((64, 2, 2), None):
        monkeypatch.setitem(device.RULES, "launch_local", {c: local for c in device.CLASSES})
        m = StereoMatcher(cost="census", max_disparity=24, device=ctx)
        res = m.compute(left, right, return_intermediates=True)
        outs.append(res)
    for name in ("C_CNN", "C_SGM", "D_L", "D_R", "D_INT", "D_SE", "D_BF"):
        a, b = outs[0].intermediates[name], outs[1].intermediates[name]
        np.testing.assert_array_equal(a, b, err_msg=name)


@pytest.mark.parametrize("verbose", [False, True])
def test_compiler_summary_lines(monkeypatch, verbose):
    monkeypatch.setattr(clmod, "COMPILER_OUTPUT", verbose)
    text = "2 warnings generated.\nsomething else\n1 error generated.\n"
    got = clmod._filter_compiler_output(text)
    assert got == (text if verbose else "something else\n")


def test_build_output_is_filtered(capfd, monkeypatch):
    """What a build writes to file descriptor 2 comes back less the summary lines."""
    import os

    monkeypatch.setattr(clmod, "COMPILER_OUTPUT", False)

    def build():
        os.write(2, b"3 warnings generated.\nkept line\n")
        return 7

    assert clmod._build_quietly(build) == 7
    err = capfd.readouterr().err
    assert "kept line" in err and "generated" not in err


def _arms(ctx, img):
    from mccnn_cl.stages.cross import CrossArms, arms_from_device

    H, W = img.shape
    return arms_from_device(ctx, CrossArms(ctx)(ctx.to_device(img), H, W), H, W)


def test_stored_binaries(ctx, monkeypatch, tmp_path, caplog):
    """A program whose binary was saved is made from it in a new context (no
    source build) and computes the same bits; a corrupt binary is discarded
    with a warning and the program built from source."""
    import os

    from mccnn_cl.opencl import binaries
    from mccnn_cl.opencl.context import ClContext

    monkeypatch.setenv("MCCNN_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("MCCNN_BINARY_CACHE", raising=False)
    img = np.random.default_rng(3).random((37, 53)).astype(np.float32)
    expected = _arms(ctx, img)
    saver = ClContext(ctx.device)
    saver.save_binaries = True
    saver.program("cross.cl")
    files = [os.path.join(d, f) for d, _, fs in os.walk(tmp_path / "binaries") for f in fs]
    assert len(files) == 1 and not os.path.basename(files[0]).startswith(PREFIX)
    loader = ClContext(ctx.device)
    np.testing.assert_array_equal(_arms(loader, img), expected)
    assert (loader.builds, loader.binary_loads) == (0, 1)
    with open(files[0], "wb") as f:  # whole, with its header, but not a program: the runtime refuses it
        f.write(binaries._pack(b"not a binary"))
    other = ClContext(ctx.device)
    with caplog.at_level("WARNING", logger="mccnn_cl.opencl.context"):
        np.testing.assert_array_equal(_arms(other, img), expected)
    assert (other.builds, other.binary_loads) == (1, 0)
    assert "refused" in caplog.text and not os.path.exists(files[0])
    # a file cut short or changed is never handed to the runtime (PoCL crashed on a truncated
    # binary, in every later run): it is deleted and the program built from source
    saver.save_binaries = True
    saver._programs.clear()
    saver.program("cross.cl")
    whole = open(files[0], "rb").read()
    assert whole.startswith(binaries.MAGIC)
    for damaged in (whole[: len(whole) // 2], whole[:-1] + bytes([whole[-1] ^ 1]), whole[:20]):
        with open(files[0], "wb") as f:
            f.write(damaged)
        fresh = ClContext(ctx.device)
        caplog.clear()
        with caplog.at_level("WARNING", logger="mccnn_cl.opencl.binaries"):
            np.testing.assert_array_equal(_arms(fresh, img), expected)
        assert (fresh.builds, fresh.binary_loads) == (1, 0) and "damaged" in caplog.text
        assert not os.path.exists(files[0])
    with open(files[0], "wb") as f:  # a file of the format before the header: rebuilt, no warning
        f.write(whole[len(binaries.MAGIC) + 40:])
    caplog.clear()
    older = ClContext(ctx.device)
    with caplog.at_level("WARNING", logger="mccnn_cl.opencl.binaries"):
        np.testing.assert_array_equal(_arms(older, img), expected)
    assert (older.builds, older.binary_loads) == (1, 0) and not caplog.text and not os.path.exists(files[0])
    monkeypatch.setenv("MCCNN_BINARY_CACHE", "off")
    assert not binaries.enabled()


def test_saved_programs_are_recorded(ctx, monkeypatch, tmp_path):
    """A context that saves binaries tells binaries.recording what it stored (what
    `mccnn-cl tune` counts and reports)."""
    from mccnn_cl.opencl import binaries
    from mccnn_cl.opencl.context import ClContext

    monkeypatch.setenv("MCCNN_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("MCCNN_BINARY_CACHE", raising=False)
    saver = ClContext(ctx.device)
    saver.save_binaries = True
    with binaries.recording() as rec:
        saver.program("cross.cl")
    assert (rec.stored, rec.failed) == (1, [])
    assert (ClContext(ctx.device).program("cross.cl") is not None)


def test_stale_temporary_binaries_are_deleted(monkeypatch, tmp_path):
    """A process killed (kill -9) inside binaries.store, after its temporary file and
    before the rename, leaves that file (mccnn_cl.atomic's pid-named name); the next
    store deletes those of writers no longer running, young or not (before: only
    those over ten minutes old, so each kill within ten minutes left one more, a
    program binary each), in its own folder and (once per process) in every folder
    of the cache, and keeps one of a running process (a write in progress)."""
    import os
    import signal
    import subprocess
    import sys

    from mccnn_cl.opencl import binaries

    monkeypatch.setenv("MCCNN_CACHE_DIR", str(tmp_path))
    killed = ("import os, signal, sys; from mccnn_cl.opencl import binaries; "
              "os.fsync = lambda fd: os.kill(os.getpid(), signal.SIGKILL); binaries.store(sys.argv[1], b'x' * 4096)")
    root = tmp_path / "binaries"

    def kill_a_writer(k):
        p = subprocess.Popen([sys.executable, "-c", killed, k], env=dict(os.environ, MCCNN_CACHE_DIR=str(tmp_path)))
        assert p.wait() == -signal.SIGKILL
        return p.pid

    def temps(sub):
        return sorted(f for f in os.listdir(root / sub) if f.startswith(PREFIX))

    first = kill_a_writer("ab" + "0" * 62)
    assert [parse_temp_name(f)[1] for f in temps("ab")] == [first]  # the dead writer's file, named by its pid
    second = kill_a_writer("ab" + "1" * 62)
    assert [parse_temp_name(f)[1] for f in temps("ab")] == [second]  # the first one's deleted: none pile up
    kill_a_writer("cd" + "0" * 62)
    assert temps("ab") == [] and len(temps("cd")) == 1  # a new process sweeps every folder of the cache
    assert os.listdir(root / "ab") == []  # nothing under a final name either
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        in_progress = f"{temp_prefix(alive.pid)}in-progress.bin"
        (root / "cd" / in_progress).write_bytes(b"x")
        monkeypatch.setattr(binaries, "_SWEPT", set(), raising=False)  # as in a new process
        assert binaries.store("cd" + "2" * 62, b"payload")
        assert temps("cd") == [in_progress]
    finally:
        alive.kill()
        alive.wait()
    assert binaries.load("cd" + "2" * 62) == b"payload"


def test_binaries_are_written_through_atomic_write(monkeypatch, tmp_path):
    """binaries.store writes through mccnn_cl.atomic.atomic_write (the package's one
    way of writing a file whole or not at all), and a failed write leaves neither
    a file under the final name nor a temporary one."""
    import errno
    import os

    import mccnn_cl.atomic as atomic
    from mccnn_cl.opencl import binaries

    monkeypatch.setenv("MCCNN_CACHE_DIR", str(tmp_path))
    written, real = [], atomic.atomic_write

    def spy(path, write_fn):
        written.append(os.fspath(path))
        return real(path, write_fn)

    monkeypatch.setattr(atomic, "atomic_write", spy)
    k = "ef" + "0" * 62
    assert binaries.store(k, b"payload") and written == [binaries.path(k)]
    assert binaries.load(k) == b"payload"

    def disk_full(tmp, data):
        with open(tmp, "wb") as f:
            f.write(data[:10])  # a part written, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(binaries, "_write", disk_full)
    k2 = "ef" + "1" * 62
    assert not binaries.store(k2, b"payload")
    assert sorted(os.listdir(tmp_path / "binaries" / "ef")) == [os.path.basename(binaries.path(k))]


def test_earlier_versions_temporary_binaries_are_deleted_when_old(monkeypatch, tmp_path):
    """The caches' earlier writer (tempfile.mkstemp(prefix=".tmp-"), before mccnn_cl.atomic)
    left a ``.tmp-*`` file when killed before its rename; nothing deleted those any more
    (before: kept for ever).  The first store of a process deletes those unchanged for
    over ten minutes (that writer's own rule) in every folder of the cache and the
    cache's own folder (the writable check's probe files); a younger one may be an older
    version's write in progress (another process, another host) and stays."""
    import os
    import time

    from mccnn_cl.opencl import binaries

    monkeypatch.setenv("MCCNN_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(binaries, "_SWEPT", set(), raising=False)  # as in a new process
    root = tmp_path / "binaries"
    old, young = time.time() - 15 * 60, time.time() - 2 * 60
    files = {root / "ab" / ".tmp-k2j4h5g1": old, root / "ab" / ".tmp-young": young,
             root / "cd" / ".tmp-x9a8b7c6": old, root / ".tmp-probe-q1w2e3r4": old,
             root / "cd" / "not-a-tmp-file": old}
    for f, t in files.items():
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(b"partial")
        os.utime(f, (t, t))
    assert binaries.store("ab" + "3" * 62, b"payload")
    left = sorted(os.path.relpath(os.path.join(d, f), root) for d, _, fs in os.walk(root) for f in fs)
    assert left == sorted([os.path.relpath(binaries.path("ab" + "3" * 62), root), os.path.join("ab", ".tmp-young"),
                           os.path.join("cd", "not-a-tmp-file")]), left
    assert binaries.load("ab" + "3" * 62) == b"payload"


def _store_many(root, payload_byte, n):
    import os

    os.environ["MCCNN_CACHE_DIR"] = root
    from mccnn_cl.opencl import binaries

    for _ in range(n):
        assert binaries.store("aa" + "0" * 62, bytes([payload_byte]) * (1 << 20))


def test_two_processes_storing_one_binary_at_once(tmp_path):
    """Two processes storing the same binary at once (two first runs on one machine)
    never tear it: the file left is one writer's, whole, and no temporary file stays."""
    import multiprocessing
    import os

    from mccnn_cl.opencl import binaries

    mp = multiprocessing.get_context("spawn")
    procs = [mp.Process(target=_store_many, args=(str(tmp_path), b, 15)) for b in (1, 2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join()
        assert p.exitcode == 0
    data = open(tmp_path / "binaries" / "aa" / ("aa" + "0" * 62 + ".bin"), "rb").read()
    payload = binaries._unpack(data)
    assert payload in (b"\x01" * (1 << 20), b"\x02" * (1 << 20))
    assert os.listdir(tmp_path / "binaries" / "aa") == ["aa" + "0" * 62 + ".bin"]


def test_build_logs_go_to_debug(monkeypatch, caplog, recwarn):
    """A successful build's log (PyOpenCL's CompilerWarning) reaches the debug log,
    not the caller, unless COMPILER_OUTPUT; other warnings pass through."""
    import logging
    import warnings

    from pyopencl import CompilerWarning

    def build():
        warnings.warn("Non-empty compiler output encountered", CompilerWarning)
        warnings.warn("something else", UserWarning)
        return 3

    monkeypatch.setattr(clmod, "COMPILER_OUTPUT", False)
    with caplog.at_level(logging.DEBUG, logger=clmod.__name__):
        assert clmod._build_quietly(build) == 3
    assert [str(w.message) for w in recwarn] == ["something else"]
    assert any("Non-empty compiler output" in r.getMessage() for r in caplog.records)
    recwarn.clear()
    monkeypatch.setattr(clmod, "COMPILER_OUTPUT", True)
    assert clmod._build_quietly(build) == 3
    assert sorted(w.category.__name__ for w in recwarn) == ["CompilerWarning", "UserWarning"]


def test_library_build_log_is_quiet(ctx, monkeypatch, caplog, recwarn):
    """A real build whose log is not empty (a ``#warning``; PoCL on AVX2 CPUs logs
    ABI notes for sgm.cl's 16-float vectors, Intel's runtime logs every program):
    through the Python API the caller gets no CompilerWarning, the debug log has
    it; with COMPILER_OUTPUT (--verbose) the caller gets it."""
    import logging
    import uuid

    monkeypatch.setenv("MCCNN_BINARY_CACHE", "off")
    src = '#warning "a note from the compiler"\n__kernel void k(__global float *a) { a[0] = 1.0f; }\n'
    for verbose in (False, True):
        monkeypatch.setattr(clmod, "COMPILER_OUTPUT", verbose)
        recwarn.clear()
        caplog.clear()
        with caplog.at_level(logging.DEBUG, logger=clmod.__name__):
            # a define never used before: no cache (PyOpenCL's, PoCL's, the package's) has the program
            ctx._make_program("note.cl", src, ["-I", ctx.kernel_dir, f"-DFRESH_{uuid.uuid4().hex}=1"])
        compiler = [w for w in recwarn if w.category.__name__ == "CompilerWarning"]
        logged = [r for r in caplog.records if "build log" in r.getMessage()]
        assert (len(compiler), len(logged)) == ((1, 0) if verbose else (0, 1))
