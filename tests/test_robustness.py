"""Defects of a user trial (issue 28): nothing silently wrong, no crash, no lost file.

One test (or a few) per row of the issue's table; each failed before its fix.
Small crops of the eighth-size Cones pair (tests/cones_eighth) and the shared data keep every OpenCL
run to seconds on PoCL.
"""

import os
import re
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest

from mccnn_cl.errors import InputError, WeightsError
from mccnn_cl.io import read_image
from mccnn_cl.pipeline import Hyperparameters, StereoMatcher
from mccnn_cl.weights import Weights

DEMO = Path(__file__).resolve().parent / "cones_eighth"  # Middlebury Cones, 225x188 (README there)
SMALL_NET = dict(conv_layers=[[8, 3], [12, 3], [12, 1]], fc_layers=[16, 16, 2])


def cli(*args, timeout=180, env=None):
    e = dict(os.environ)
    e.update(env or {})
    p = subprocess.run([sys.executable, "-m", "mccnn_cl", *map(str, args)], capture_output=True, text=True,
                       timeout=timeout, env=e)
    return p.returncode, p.stdout, p.stderr


def one_line(err, *words):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mccnn-cl: error:"), err
    for w in words:
        assert w in lines[0], err


@pytest.fixture(scope="module")
def demo_pair():
    """The eighth-size Cones pair (225x188), gray in [0, 1]."""
    from mccnn_cl.imageops import to_gray
    return to_gray(read_image(DEMO / "im0.png")), to_gray(read_image(DEMO / "im1.png"))


@pytest.fixture(scope="module")
def crop(demo_pair):
    left, right = demo_pair
    return left[40:104, 60:156], right[40:104, 60:156]  # 96 x 64


# -- 1: threads ----------------------------------------------------------------

def test_concurrent_compute_on_one_matcher_gives_the_sequential_results(ctx, demo_pair):
    """Two threads sharing one matcher (network cost): every result equals the
    one-at-a-time result (before the lock, most were wrong)."""
    left, right = demo_pair
    pairs = [(left[:96, :160], right[:96, :160]), (left[80:176, 40:200], right[80:176, 40:200])]
    m = StereoMatcher(Weights.random(**SMALL_NET, seed=3), max_disparity=24, device=ctx)
    want = [m.compute(*p) for p in pairs]
    got, errors = {}, []

    def work(i):
        try:
            for k in range(3):
                got[(i, k)] = m.compute(*pairs[i])
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)
    threads = [threading.Thread(target=work, args=(i,)) for i in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    for (i, k), d in got.items():
        np.testing.assert_array_equal(d, want[i], err_msg=f"thread {i} call {k}")


def test_compute_calls_never_overlap(ctx, crop, monkeypatch):
    """The lock itself: no two _run calls of one matcher are ever inside at once."""
    m = StereoMatcher(cost="census", max_disparity=8, device=ctx)
    inside, most = [0], [0]
    run = m._run

    def slow_run(*a, **k):
        inside[0] += 1
        most[0] = max(most[0], inside[0])
        try:
            import time
            time.sleep(0.2)
            return run(*a, **k)
        finally:
            inside[0] -= 1
    monkeypatch.setattr(m, "_run", slow_run)
    threads = [threading.Thread(target=m.compute, args=crop) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert most[0] == 1


# -- 2: hyperparameter bounds from the kernels ------------------------------------

MEDIAN_CHILD = """
import numpy as np, sys
from mccnn_cl.opencl.context import ClContext
from mccnn_cl.stages.refine import MedianFilter
from mccnn_cl.reference.disparity import median_filter
ctx = ClContext(None)
rng = np.random.default_rng(0)
D = rng.random((256, 256)).astype(np.float32)
size = int(sys.argv[1])
out = ctx.from_device(MedianFilter(ctx, size)(ctx.to_device(D), 256, 256), (256, 256))
np.testing.assert_array_equal(out[::37, ::41], median_filter(D, size)[::37, ::41])
print("ok")
"""


@pytest.mark.parametrize("size", [23, 31])
def test_large_median_does_not_crash_the_process(size):
    """The sorting median on a 256 x 256 map: the runtime's work-group choice
    (4096 work-items x size^2 private floats) overflowed PoCL's stack (SIGSEGV
    from 23 on); a child process, so a crash fails the test instead of pytest."""
    p = subprocess.run([sys.executable, "-c", MEDIAN_CHILD, str(size)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "ok" in p.stdout, (p.returncode, p.stderr[-2000:])


@pytest.mark.parametrize("name, value, words", [
    ("median_size", 33, "<= 31"), ("cbca_eta", 257, "<= 256"), ("sgm_pi2", 1e7, "<= 1e+06"),
    ("sgm_q1", 1e-9, ">= 1e-06"), ("blur_sigma", 1e-300, ">= 1e-06"), ("cbca_iterations", 2 ** 31, "<= 2.14"),
])
def test_kernel_bounds_are_refused_by_the_api(name, value, words):
    with pytest.raises(InputError) as info:
        Hyperparameters(**{name: value})
    assert name in str(info.value) and words in str(info.value), info.value


def test_kernel_bounds_in_weights_settings_and_cli(tmp_path):
    w = Weights.random(**SMALL_NET)
    w.meta["stereo"] = {"median_size": 35}
    w.save(tmp_path / "w.npz")
    with pytest.raises(WeightsError, match="median_size"):
        StereoMatcher(str(tmp_path / "w.npz"), max_disparity=16, device="cpu")
    rc, _, err = cli("match", DEMO / "im0.png", DEMO / "im1.png", "-o", tmp_path / "x.pfm", "--max-disp", 32,
                     "--weights", tmp_path / "w.npz")
    assert rc == 2, err
    one_line(err, "median_size", "<= 31")
    assert not (tmp_path / "x.pfm").exists()
    rc, _, err = cli("match", DEMO / "im0.png", DEMO / "im1.png", "-o", tmp_path / "x.pfm", "--max-disp", 32,
                     "--cost", "census", "--set", "median_size=25", "--set", "cbca_eta=300")
    assert rc == 2, err
    one_line(err, "cbca_eta", "<= 256")


# -- 3, 4: outputs that collide with each other or with an input -----------------

@pytest.mark.parametrize("extra", [["--confidence", "{o}"], ["--color", "{o}"], ["--labels", "{stem}.png", "--color", "{stem}.png"]])
def test_colliding_outputs_are_refused_before_any_work(tmp_path, extra):
    o = tmp_path / ("same.png" if "--color" in extra[:1] else "same.pfm")
    if extra[0] == "--color":
        o = tmp_path / "same.png"
    args = [a.format(o=o, stem=tmp_path / "side") for a in extra]
    out = tmp_path / "same.png" if extra == ["--color", "{o}"] else tmp_path / "same.pfm"
    rc, _, err = cli("match", DEMO / "im0.png", DEMO / "im1.png", "-o", out, "--max-disp", 16, "--cost", "census",
                     *args, "--force")
    assert rc == 2, err
    one_line(err, "same file")
    assert not out.exists()


def test_output_equal_to_an_input_is_refused_even_with_force(tmp_path):
    import shutil
    left = tmp_path / "l.png"
    shutil.copy(DEMO / "im0.png", left)
    before = left.read_bytes()
    rc, _, err = cli("match", left, DEMO / "im1.png", "-o", left, "--max-disp", 16, "--cost", "census", "--force")
    assert rc == 2, err
    one_line(err, "is the input image")
    assert left.read_bytes() == before
    os.symlink(left, tmp_path / "link.png")  # the same file under another name
    rc, _, err = cli("match", left, DEMO / "im1.png", "-o", tmp_path / "x.pfm", "--color", tmp_path / "link.png",
                     "--max-disp", 16, "--cost", "census", "--force")
    assert rc == 2, err
    one_line(err, "is the input image")
    assert left.read_bytes() == before


# -- 5: a format that cannot hold the values --------------------------------------

def test_png_refuses_values_it_cannot_hold(tmp_path):
    from mccnn_cl.io import read_kitti_disparity, write_kitti_disparity
    d = np.full((4, 5), 280.0, np.float32)
    with pytest.raises(InputError, match="255.996"):
        write_kitti_disparity(tmp_path / "d.png", d)
    with pytest.raises(InputError, match="holds disparities"):
        write_kitti_disparity(tmp_path / "d.png", -d / 100)
    assert not (tmp_path / "d.png").exists()
    ok = np.array([[0.0, 255.99, np.nan, np.inf, 1.5]], np.float32)  # the edges and the invalid markers
    write_kitti_disparity(tmp_path / "d.png", ok)
    back, valid = read_kitti_disparity(tmp_path / "d.png")
    assert valid.tolist() == [[False, True, False, False, True]]
    assert abs(back[0, 1] - 255.99) < 1 / 256


def test_cli_refuses_a_png_for_a_range_past_256_before_any_work(tmp_path):
    rc, _, err = cli("match", DEMO / "im0.png", DEMO / "im1.png", "-o", tmp_path / "d.png", "--max-disp", 300,
                     "--cost", "census")
    assert rc == 2, err
    one_line(err, "255.996", ".pfm")


# -- 7: malformed weights metadata ----------------------------------------------------

@pytest.mark.parametrize("change", [
    {"conv_layers": 5}, {"version": "two"}, {"fc_layers": [16, "x", 2]}, {"conv_layers": [[8, 3], [12]]},
    {"stereo": [1, 2]}, {"architecture": 3}, {"patch_size": "9"},
])
def test_malformed_metadata_is_one_weights_error(tmp_path, change):
    import json
    path = tmp_path / "w.npz"
    Weights.random(**SMALL_NET).save(path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["__meta__"]))
    meta.update(change)
    arrays["__meta__"] = np.array(json.dumps(meta))
    np.savez(path, **arrays)
    with pytest.raises(WeightsError) as info:
        Weights.load(path)
    assert "\n" not in str(info.value)
    rc, _, err = cli("match", DEMO / "im0.png", DEMO / "im1.png", "-o", tmp_path / "x.pfm", "--max-disp", 16,
                     "--weights", path)
    assert rc == 2, err
    one_line(err, "w.npz")


# -- 8, 9: unwritable destinations and raw exceptions --------------------------------

def test_unwritable_output_folder_is_refused_before_any_work(tmp_path):
    # /proc takes no new files, even for root (chmod alone does not stop root)
    rc, _, err = cli("match", DEMO / "im0.png", DEMO / "im1.png", "-o", "/proc/mccnn_x.pfm", "--max-disp", 16,
                     "--cost", "census")
    assert rc == 2, err
    one_line(err, "cannot write into /proc")
    assert ".mccnn-tmp" not in err and "PermissionError" not in err


def test_raw_exceptions_of_the_trial_are_input_errors(tmp_path, ctx):
    f = tmp_path / "afile"
    f.write_text("x")
    rc, _, err = cli("match", "-l", DEMO / "im0.png", "-r", DEMO / "im1.png", "--output-dir", f, "--max-disp", 16,
                     "--cost", "census")
    assert rc == 2, err
    one_line(err, "is a file, not a folder")
    rc, _, err = cli("match", DEMO / "im0.png", DEMO / "im1.png", "-o", tmp_path / "x.pfm", "--max-disp", 16,
                     "--cost", "census", "--memory-limit", "inf")
    assert rc == 2, err
    one_line(err, "--memory-limit")
    m = StereoMatcher(cost="census", max_disparity=8, device=ctx)
    for empty in (np.zeros((0, 0), np.uint8), np.zeros((0, 40), np.float32), np.zeros((30, 0, 3), np.uint8)):
        with pytest.raises(InputError, match="empty"):
            m.compute(empty, empty)


# -- 10: integer images with fewer significant bits -------------------------------------

def test_twelve_bit_data_in_uint16_warns_and_bit_depth_scales_it(ctx, crop):
    from mccnn_cl.errors import InputWarning
    left, right = (np.round(c * 4095).astype(np.uint16) for c in crop)
    m = StereoMatcher(cost="census", max_disparity=16, device=ctx)
    with pytest.warns(InputWarning, match="bit_depth=12"):
        m.compute(left, right)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        twelve = m.compute(left, right, bit_depth=12)
    # 12-bit data read as 12 bits = the same picture at 8 bits (both scaled to [0, 1])
    eight = m.compute(*(np.round(c * 255).astype(np.uint8) for c in crop))
    assert np.mean(np.abs(twelve - eight) > 1) < 0.05
    with pytest.raises(InputError, match="more than 8 bits"):
        m.compute(left, right, bit_depth=8)
    with pytest.raises(InputError, match="bit_depth"):
        m.compute(*crop, bit_depth=12)  # float images have no bit depth


# -- 12: --device pocl ------------------------------------------------------------------

def test_device_pocl_selects_pocl():
    from mccnn_cl.opencl.context import list_devices, select_device
    devs = [d for d in list_devices() if "pocl" in d.platform_version.lower()]
    if not devs:
        pytest.fail("the test machine has PoCL (the suite's reference implementation)")
    for spec in ("pocl", "PoCL", "pocl:cpu", "portable"):
        dev, _ = select_device(spec)
        assert dev in [d.handle for d in devs], spec


# -- 13: --calib with a calibration that gives only ndisp --------------------------------

def test_calib_with_only_ndisp_gives_the_range(tmp_path):
    calib = tmp_path / "calib.txt"
    calib.write_text("width=225\nheight=188\nndisp=24\n")
    rc, out, err = cli("match", DEMO / "im0.png", DEMO / "im1.png", "-o", tmp_path / "x.pfm", "--calib", calib,
                       "--cost", "census")
    assert rc == 0, err
    assert "24 disparities" in out and "no depth" in err
    assert (tmp_path / "x.pfm").exists() and not (tmp_path / "x.ply").exists()


# -- 14: temporary files of a killed writer ------------------------------------------------

def test_stale_temporary_files_are_removed_at_the_next_write(tmp_path):
    from mccnn_cl.atomic import PREFIX, temp_prefix
    from mccnn_cl.depth import write_ply
    # a writer killed mid-write (SIGKILL: nothing of it runs afterwards)
    child = ("import numpy as np, os, signal\n"
             "from mccnn_cl.depth import write_ply\n"
             "def boom(tmp):\n    open(tmp, 'wb').write(b'partial'); os.kill(os.getpid(), signal.SIGKILL)\n"
             "import mccnn_cl.atomic as a\na.atomic_write(r'%s', boom)\n" % (tmp_path / "cloud.ply"))
    p = subprocess.run([sys.executable, "-c", child], timeout=60)
    assert p.returncode == -9
    stale = [f for f in os.listdir(tmp_path) if f.startswith(PREFIX)]
    assert len(stale) == 1 and not (tmp_path / "cloud.ply").exists()
    mine = tmp_path / f"{temp_prefix()}inflight.ply"  # a running writer's file stays
    mine.write_bytes(b"x")
    write_ply(tmp_path / "other.ply", np.zeros((3, 3), np.float32))
    left = sorted(os.listdir(tmp_path))
    assert left == sorted(["other.ply", mine.name]), left


# -- 12: the docs' examples run as written ------------------------------------------------

def doc_error_examples():
    """(command, expected stderr line) of docs/cli.md's error examples (the block under "Exit status")."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()
    lines = text.splitlines()
    out = []
    for i, line in enumerate(lines[:-1]):
        if line.startswith("$ mccnn-cl match ") and lines[i + 1].startswith("mccnn-cl: error:"):
            out.append((line[2:].split("  #")[0].strip(), lines[i + 1]))
    return out


@pytest.mark.full_data  # the docs quote the full-size scenes
def test_docs_error_examples_run_as_written(tmp_path, shared_data):
    """Each documented error example, run on the Middlebury scenes it names
    (../shared/data/middlebury) or the shifted KITTI pair, prints the documented line (a trailing "..."
    stands for the machine-dependent rest) and exits 2 -- or, for --device gpu
    on a machine with a GPU, runs."""
    import shlex
    from mccnn_cl.opencl.context import list_devices
    examples = doc_error_examples()
    assert len(examples) >= 5, examples
    for scene in ("Cones", "Tsukuba"):
        os.symlink(shared_data / "middlebury" / scene, tmp_path / scene)
    (tmp_path / "cones.pfm").write_bytes(b"")
    from mccnn_cl.io import read_image, write_image
    kitti = shared_data / "kitti2015" / "training"  # the shifted pair of the disparity-range examples
    write_image(tmp_path / "left_shifted.png", read_image(kitti / "image_2" / "000000_10.png")[:, 64:])
    write_image(tmp_path / "right_shifted.png", read_image(kitti / "image_3" / "000000_10.png")[:, :-64])
    for name in ("im0.png", "im1.png"):  # the eighth-size Cones pair the docs name
        os.symlink(DEMO / name, tmp_path / name)
    has_gpu = any(d.type == "GPU" for d in list_devices())
    for cmd, want in examples:
        if "--device gpu" in cmd and has_gpu:
            continue
        args = shlex.split(cmd)[1:] + ["--cost", "census"] * ("--weights" not in cmd)
        p = subprocess.run([sys.executable, "-m", "mccnn_cl", *args], capture_output=True, text=True,
                           timeout=180, cwd=tmp_path)
        got = p.stderr.strip()
        assert p.returncode == 2 or "--device" in cmd, (cmd, p.returncode, got)
        if "..." in want:  # "..." stands for the machine-dependent rest
            # so do PoCL's CPU device names (pthread-skylake-avx512-..., pthread-haswell-... on a Zen 3)
            got, want = (re.sub(r"pthread-[\w.-]+", "pthread-CPU", t) for t in (got, want))
            assert got.startswith(want.split("...")[0].rstrip()), (cmd, got, want)
        else:
            assert got == want, (cmd, got, want)


def test_docs_device_pocl_spec_runs():
    """docs/cli.md names --device "pocl": it selects PoCL here (``devices --device pocl``)."""
    rc, out, err = cli("devices", "--device", "pocl")
    assert rc == 0, err
    assert "would use:" in out and "Portable Computing Language" in out.split("would use:")[1], out


def test_cli_png_writer_says_which_pixels_it_cannot_hold(tmp_path, capsys):
    """Subpixel steps a little past the range's ends: invalid (0) in the PNG, with one line on stderr."""
    from mccnn_cl.cli.commands import write_disparity
    from mccnn_cl.io import read_kitti_disparity
    d = np.array([[-0.3, 5.25, 256.2, np.nan]], np.float32)
    write_disparity(str(tmp_path / "d.png"), d)
    err = capsys.readouterr().err
    assert "2 pixels outside" in err and "written as invalid" in err and len(err.strip().splitlines()) == 1
    back, valid = read_kitti_disparity(tmp_path / "d.png")
    assert valid.tolist() == [[False, True, False, False]] and back[0, 1] == 5.25


def test_weights_settings_with_a_newline_in_a_name_are_one_line(tmp_path):
    """Found by the long fuzzing run: a stereo key "\\n0" split the error over two lines."""
    w = Weights.random(**SMALL_NET)
    w.meta["stereo"] = {"\n0": 1}
    w.save(tmp_path / "w.npz")
    with pytest.raises(WeightsError) as info:
        Weights.load(tmp_path / "w.npz")
    assert "\n" not in str(info.value) and "'\\n0'" in str(info.value)


# -- 6: a swapped pair ----------------------------------------------------------------------

def test_swapped_pair_warns_and_the_correct_order_does_not(ctx, shared_data):
    """Tsukuba (quarter size, census, D = 32): swapped, the left-right check fails on
    ~22 % of the pixels -> an InputWarning naming the swap; in order none."""
    from mccnn_cl.errors import InputWarning
    ts = shared_data / "middlebury" / "Tsukuba"
    left, right = read_image(ts / "im0.png"), read_image(ts / "im1.png")
    m = StereoMatcher(cost="census", max_disparity=32, device=ctx)
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        m.compute(left, right)
    with pytest.warns(InputWarning, match="swapped"):
        m.compute(right, left)


# -- 11: Ctrl-C --------------------------------------------------------------------------------

@pytest.mark.slow
def test_ctrl_c_is_answered_within_seconds(tmp_path, shared_data):
    """SIGINT during a full-size KITTI match with the paper's network (D = 228:
    minutes on 2 CPU cores): the process exits 130 within seconds, not after the
    queued work (main's code: the rest of the cost volume).

    The child gets SIGINT's default action back before it starts: a suite run as
    a background job of a non-interactive shell (``bash .ci/run &``) inherits
    SIGINT ignored, and Python then keeps it ignored (as it should: a command
    started that way is not to be interrupted), which would test nothing."""
    import signal
    import time
    k = shared_data / "kitti2015" / "training"
    p = subprocess.Popen([sys.executable, "-m", "mccnn_cl", "match", k / "image_2/000000_10.png",
                          k / "image_3/000000_10.png", "-o", tmp_path / "d.pfm", "--weights", "kitti-paper"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(15)  # past start-up and kernel builds, inside the network's volume
    assert p.poll() is None, p.communicate()
    t0 = time.perf_counter()
    p.send_signal(signal.SIGINT)
    try:
        _, err = p.communicate(timeout=60)
    except subprocess.TimeoutExpired:  # not answered: don't let the match run its minutes on
        p.kill()
        _, err = p.communicate()
        pytest.fail(f"no exit within 60 s of SIGINT; stderr: {err!r}")
    seconds = time.perf_counter() - t0
    assert p.returncode == 130, err
    assert seconds < 10, f"{seconds:.1f} s from SIGINT to exit"
    assert not (tmp_path / "d.pfm").exists()
