"""Batches of pairs (pairing by name, failures, --resume, interrupts) in one
process and on a Dask cluster (a LocalCluster of 2 worker processes on PoCL),
and a tiled pair split over the workers.

Census cost, small disparity ranges and crops of the shared KITTI frames keep
each run to seconds.  Outputs of the Dask path are compared byte for byte with
the one-process batch's, and the tiled pair's maps bit for bit with
:meth:`StereoMatcher.compute`'s tiled run.
"""

import os
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from mccnn_cl.batch import Job, Outputs, pair_globs, write_pair
from mccnn_cl.cli import main
from mccnn_cl.cli.commands import IMAGE_EXTENSIONS, _gray
from mccnn_cl.errors import InputError
from mccnn_cl.io import read_image, write_image

from distributed import Client

from mccnn_cl import distributed as dd

FRAMES = ("000000", "000001", "e00001", "e00002", "e00003", "e00004")
D = 24
COMMON = ["--cost", "census", "--max-disp", str(D)]


def frame_crop(src, side, i, rows, x0, width):
    """Frame FRAMES[i]'s crop; with only the bundled frame 000000 (tests/data), a
    crop of 000000 at another column instead, so that every pair differs."""
    p = src / side / f"{FRAMES[i]}_10.png"
    if p.exists():
        return read_image(p)[rows, x0:x0 + width]
    img = read_image(src / side / "000000_10.png")
    x = [400, 20, 110, 200, 290, 380][i] if width <= 200 else [400, 300, 200, 100][i]
    return img[rows, x:x + width]


@pytest.fixture(scope="module")
def kitti(shared_data, tmp_path_factory):
    """image_2/NAME_10.png and image_3/NAME_10.png: 96 x 200 crops of six KITTI 2015 frames
    (or, with the bundled data only, of six windows of frame 000000)."""
    d = tmp_path_factory.mktemp("kitti")
    src = shared_data / "kitti2015/training"
    for side in ("image_2", "image_3"):
        (d / side).mkdir()
        for i, f in enumerate(FRAMES):
            write_image(d / side / f"{f}_10.png", frame_crop(src, side, i, slice(250, 346), 400, 200))
    return d


@pytest.fixture(scope="module")
def cluster():
    """A LocalCluster of 2 worker processes (1 thread each) and its client."""
    with dd.local_cluster(2) as c, Client(c) as client:
        yield client


def glob_args(kitti):
    return ["-l", str(kitti / "image_2/*.png"), "-r", str(kitti / "image_3/*.png")]


def listing(d):
    """A folder's files, without the hidden settings records of batches (``.<map>.mccnn.json``)."""
    return sorted(p for p in os.listdir(d) if not p.startswith("."))


def files(d):
    return {p: (d / p).read_bytes() for p in listing(d)}


@pytest.fixture(scope="module")
def reference(kitti, tmp_path_factory):
    """The one-process batch's outputs (disparity, colour, confidence, labels) of the six pairs."""
    out = tmp_path_factory.mktemp("reference")
    assert main(["match", *glob_args(kitti), "--output-dir", str(out), "--color", "--confidence",
                 "--labels", *COMMON]) == 0
    return out


def test_batch_on_cluster_equals_one_process(kitti, reference, cluster, tmp_path, capsys):
    ref = files(reference)
    assert len(ref) == 4 * len(FRAMES) and f"{FRAMES[0]}_10.pfm" in ref
    out = tmp_path / "out"
    rc = main(["match", *glob_args(kitti), "--output-dir", str(out), "--color", "--confidence", "--labels",
               "--scheduler", cluster.scheduler.address, *COMMON])
    assert rc == 0
    assert files(out) == ref  # byte for byte
    assert f"done {len(FRAMES)}, skipped 0" in capsys.readouterr().out


@pytest.mark.slow  # ~15-25 s here: a fresh process starts a cluster
def test_cli_workers_two(kitti, reference, tmp_path):
    """The README's line, in a fresh process: a LocalCluster of 2 workers."""
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "mccnn_cl", "match", *glob_args(kitti), "--output-dir", str(out),
                        "--workers", "2", *COMMON], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert "dask: 2 workers (local)" in p.stdout
    for f in FRAMES:
        assert (out / f"{f}_10.pfm").read_bytes() == (reference / f"{f}_10.pfm").read_bytes()


def test_unpartnered_names_refused(kitti, reference, cluster, tmp_path, capsys):
    """L = {a, b, d, e}, R = {a, c, d, f}: listed and refused before any work, in both paths."""
    for side, names in (("l", "abde"), ("r", "acdf")):
        (tmp_path / side).mkdir()
        for n in names:
            os.link(kitti / "image_2" / f"{FRAMES[0]}_10.png", tmp_path / side / f"{n}.png")
    for extra in ([], ["--scheduler", cluster.scheduler.address]):
        out = tmp_path / f"out{len(extra)}"
        rc = main(["match", "-l", str(tmp_path / "l/*.png"), "-r", str(tmp_path / "r"), "--output-dir", str(out),
                   *extra, *COMMON])
        err = capsys.readouterr().err
        assert rc == 2
        assert "2 left image(s) without a right partner" in err and "2 right image(s) without a left partner" in err
        for n in ("b.png", "e.png", "c.png", "f.png"):
            assert n in err
        assert not out.exists() or not os.listdir(out)


def test_auto_range_per_pair(kitti, cluster, tmp_path, capsys):
    """--disp-range auto in a batch: each pair gets its own range, said on a line per pair; each
    map is StereoMatcher(max_disparity="auto")'s of the pair alone; the Dask path writes the same
    bytes; --resume skips complete pairs; a PNG batch refuses only the pair with negative disparities."""
    from mccnn_cl import StereoMatcher
    from mccnn_cl.io import read_pfm
    s = 40  # "shifted": the left image's first s columns and the right's last s dropped (d - s)
    L, R = (read_image(kitti / f"image_{i}/{FRAMES[0]}_10.png") for i in (2, 3))
    pairs = {"plain": (L, R), "shifted": (L[:, s:], R[:, :-s])}
    for side in ("l", "r"):
        (tmp_path / side).mkdir()
    for name, (left, right) in pairs.items():
        write_image(tmp_path / "l" / f"{name}.png", left)
        write_image(tmp_path / "r" / f"{name}.png", right)
    args = ["match", "-l", str(tmp_path / "l"), "-r", str(tmp_path / "r"), "--cost", "census", "--disp-range", "auto"]
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(args + ["--output-dir", str(a)]) == 0
    so = capsys.readouterr().out
    ranges = {}
    for name, (left, right) in pairs.items():
        res = StereoMatcher(cost="census", max_disparity="auto").compute(_gray(left), _gray(right), timings=True)
        lo, hi = ranges[name] = res.disparity_range
        assert f"{name}.pfm: {left.shape[1]}x{left.shape[0]}, disparities {lo}..{hi} (auto: coarse pass" in so
        np.testing.assert_array_equal(read_pfm(a / f"{name}.pfm"), np.where(np.isfinite(res.disparity),
                                                                             res.disparity, np.inf))
    assert ranges["shifted"][0] < 0 and ranges["plain"] != ranges["shifted"]
    assert main(args + ["--output-dir", str(b), "--scheduler", cluster.scheduler.address]) == 0
    so = capsys.readouterr().out
    assert files(a) == files(b)  # byte for byte
    assert all(f"{n}.pfm: " in so and f"disparities {lo}..{hi} (auto: " in so for n, (lo, hi) in ranges.items())
    before = (a / "plain.pfm").stat().st_mtime_ns
    os.unlink(a / "shifted.pfm")
    assert main(args + ["--output-dir", str(a), "--resume"]) == 0
    assert "done 1, skipped 1" in capsys.readouterr().out
    assert files(a) == files(b) and (a / "plain.pfm").stat().st_mtime_ns == before
    # a KITTI 16-bit PNG: the plain pair's range starts at 0 at the lowest; the shifted pair is refused
    c = tmp_path / "c"
    assert main(args + ["--output-dir", str(c), "--format", "png"]) == 2
    so = capsys.readouterr().out
    assert "failed shifted:" in so and "negative disparities" in so and listing(c) == ["plain.png"]
    assert f"disparities {max(ranges['plain'][0], 0)}..{ranges['plain'][1]} (auto: " in so
    assert main(args + ["--output-dir", str(tmp_path / "d"), "--scheduler", cluster.scheduler.address,
                        "--split-tiles"]) == 2
    assert "--disp-range auto" in capsys.readouterr().err


def test_pairing_by_wildcard_text(tmp_path):
    (tmp_path / "cam").mkdir()
    for n in ("L0001.png", "R0001.png", "L0002.png", "R0002.png"):
        (tmp_path / "cam" / n).write_bytes(b"")
    pairs = pair_globs(str(tmp_path / "cam/L*.png"), str(tmp_path / "cam/R*.png"), IMAGE_EXTENSIONS)
    assert [(n, os.path.basename(lp), os.path.basename(rp)) for n, lp, rp in pairs] == [
        ("L0001", "L0001.png", "R0001.png"), ("L0002", "L0002.png", "R0002.png")]


def test_folder_layout(kitti, reference, cluster, tmp_path, capsys):
    """im0/im1 in one folder per scene: --pairs-dir and the */im0.png glob give the same outputs."""
    root = tmp_path / "scenes"
    for f in FRAMES[:3]:
        (root / f"S{f}").mkdir(parents=True)
        os.link(kitti / "image_2" / f"{f}_10.png", root / f"S{f}" / "im0.png")
        os.link(kitti / "image_3" / f"{f}_10.png", root / f"S{f}" / "im1.png")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["match", "--pairs-dir", str(root), "--output-dir", str(a), *COMMON]) == 0
    assert main(["match", "-l", str(root / "*/im0.png"), "-r", str(root / "*/im1.png"), "--output-dir", str(b),
                 "--scheduler", cluster.scheduler.address, *COMMON]) == 0
    assert sorted(listing(a)) == [f"S{f}.pfm" for f in FRAMES[:3]]
    assert files(a) == files(b)
    for f in FRAMES[:3]:
        assert (a / f"S{f}.pfm").read_bytes() == (reference / f"{f}_10.pfm").read_bytes()
    (root / "lonely").mkdir()
    os.link(kitti / "image_2" / f"{FRAMES[0]}_10.png", root / "lonely" / "im0.png")
    capsys.readouterr()
    assert main(["match", "--pairs-dir", str(root), "--output-dir", str(tmp_path / "c"), *COMMON]) == 2
    assert "lonely/im0.png" in capsys.readouterr().err


@pytest.mark.parametrize("where", ["one process", "cluster"])
def test_failing_pairs_reported_others_written(kitti, reference, cluster, tmp_path, capsys, where):
    for side in ("l", "r"):
        (tmp_path / side).mkdir()
        for f in FRAMES[:2]:
            os.link(kitti / ("image_2" if side == "l" else "image_3") / f"{f}_10.png", tmp_path / side / f"{f}.png")
    (tmp_path / "l/corrupt.png").write_bytes(b"not a png")
    os.link(kitti / f"image_3/{FRAMES[2]}_10.png", tmp_path / "r/corrupt.png")
    write_image(tmp_path / "l/sizes.png", read_image(kitti / f"image_2/{FRAMES[3]}_10.png"))
    write_image(tmp_path / "r/sizes.png", read_image(kitti / f"image_3/{FRAMES[3]}_10.png")[:, :150])
    out = tmp_path / "out"
    extra = ["--scheduler", cluster.scheduler.address] if where == "cluster" else []
    rc = main(["match", "-l", str(tmp_path / "l"), "-r", str(tmp_path / "r"), "--output-dir", str(out),
               *extra, *COMMON])
    so = capsys.readouterr().out
    assert rc == 2  # every failure is bad input
    assert "done 2, skipped 0 (outputs complete), failed 2" in so
    assert "failed corrupt:" in so and "corrupt.png" in so
    assert "failed sizes:" in so and "differ" in so
    assert sorted(listing(out)) == [f"{f}.pfm" for f in FRAMES[:2]]
    for f in FRAMES[:2]:
        assert (out / f"{f}.pfm").read_bytes() == (reference / f"{f}_10.pfm").read_bytes()


@pytest.mark.parametrize("where", ["one process", "cluster"])
def test_resume_writes_only_missing(kitti, reference, cluster, tmp_path, capsys, where):
    out = tmp_path / "out"
    args = ["match", *glob_args(kitti), "--output-dir", str(out), "--color", "--confidence", "--labels", *COMMON]
    assert main(args) == 0
    # an interrupted run: pair 0 lost its disparity map (its side files remain), pair 1 everything
    os.unlink(out / f"{FRAMES[0]}_10.pfm")
    for p in listing(out):
        if p.startswith(FRAMES[1]):
            os.unlink(out / p)
    os.utime(out / f"{FRAMES[0]}_10_color.png", (1, 1))
    before = {p: os.stat(out / p).st_mtime_ns for p in listing(out)}
    capsys.readouterr()
    assert main(args) == 2  # without --resume: refused, nothing overwritten
    assert "exists" in capsys.readouterr().err
    extra = ["--scheduler", cluster.scheduler.address] if where == "cluster" else []
    assert main(args + ["--resume"] + extra) == 0
    assert f"done 2, skipped {len(FRAMES) - 2}" in capsys.readouterr().out
    assert files(out) == files(reference)
    after = {p: os.stat(out / p).st_mtime_ns for p in listing(out)}
    rewritten = {p for p in after if before.get(p) != after[p]}
    assert rewritten == {p for p in after if p.startswith((FRAMES[0], FRAMES[1]))}


def test_interrupt_leaves_complete_pairs_only(kitti, reference, tmp_path, monkeypatch, capsys):
    """Ctrl-C while a pair is written: its side files go, earlier pairs stay whole;
    --resume then writes only the missing pairs."""
    import mccnn_cl.cli.common as commands  # the writer batches call
    real, calls = commands.write_disparity, []

    def interrupted(path, disp):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        real(path, disp)

    monkeypatch.setattr(commands, "write_disparity", interrupted)
    out = tmp_path / "out"
    assert main(["match", *glob_args(kitti), "--output-dir", str(out), "--color", "--confidence", *COMMON]) == 130
    first = sorted(f"{FRAMES[0]}_10{s}" for s in (".pfm", "_color.png", "_confidence.pfm"))
    assert sorted(listing(out)) == first
    monkeypatch.setattr(commands, "write_disparity", real)
    before = {p: os.stat(out / p).st_mtime_ns for p in first}
    capsys.readouterr()
    assert main(["match", *glob_args(kitti), "--output-dir", str(out), "--color", "--confidence", "--resume",
                 *COMMON]) == 0
    assert f"done {len(FRAMES) - 1}, skipped 1" in capsys.readouterr().out
    assert {p: os.stat(out / p).st_mtime_ns for p in first} == before
    ref = files(reference)
    assert files(out) == {p: b for p, b in ref.items() if not p.endswith("_labels.png")}


def test_killed_worker_work_redone(kitti, reference, cluster, tmp_path):
    """SIGKILL a worker while it holds a pair: every pair still completes, outputs identical."""
    pids = cluster.run(os.getpid)
    jobs = [Job(f, str(kitti / f"image_2/{f}_10.png"), str(kitti / f"image_3/{f}_10.png"),
                str(tmp_path / f"{f}_10.pfm")) for f in FRAMES]
    config = dd.matcher_config(cost="census")
    killed = {}

    def killer():
        deadline = time.time() + 60
        while time.time() < deadline and not killed:
            for addr, keys in cluster.processing().items():
                if any("pair_task" in str(k) for k in keys) and addr in pids:
                    killed[addr] = list(keys)
                    os.kill(pids[addr], signal.SIGKILL)
                    return
            time.sleep(0.005)

    t = threading.Thread(target=killer)
    t.start()
    results = []
    for job, res in dd.match_pairs(cluster, jobs, config, D):
        assert not isinstance(res, BaseException), res
        write_pair(job, res, Outputs(), None)
        results.append(job.name)
    t.join()
    assert killed, "no worker was caught holding a pair"
    assert sorted(results) == sorted(FRAMES)
    for f in FRAMES:
        assert (tmp_path / f"{f}_10.pfm").read_bytes() == (reference / f"{f}_10.pfm").read_bytes()
    cluster.wait_for_workers(2, timeout=60)  # the nanny restarts the killed worker for later tests


def _tall_pair(shared_data, tmp_path, width=200):
    """Four KITTI frames' 375-row crops stacked: a tall pair the planner cuts in row tiles."""
    src = shared_data / "kitti2015/training"
    paths = []
    for side, name in (("image_2", "L.png"), ("image_3", "R.png")):
        img = np.vstack([frame_crop(src, side, i, slice(0, 370), 400, width) for i in range(4)])
        write_image(tmp_path / name, img)
        paths.append(str(tmp_path / name))
    return Job("tall", paths[0], paths[1], str(tmp_path / "tall.pfm"))


def _limit_for_tiles(matcher, shape, tiles):
    """A memory_limit (bytes) whose plan has at least ``tiles`` row tiles."""
    whole = matcher.memory_plan(shape).peak_bytes
    for frac in np.linspace(0.9, 0.1, 33):
        matcher.memory_limit = int(whole * frac)
        try:
            if len(matcher.memory_plan(shape).tiles) >= tiles:
                return matcher.memory_limit
        except InputError:
            break
    raise AssertionError("no memory limit gives the tiles")


def _split_equals_tiled_run(job, cluster, cost, weights, D, tiles):
    from mccnn_cl.pipeline import StereoMatcher
    m = StereoMatcher(cost=cost, weights=weights, max_disparity=D)
    L, R = _gray(read_image(job.left)), _gray(read_image(job.right))
    m.memory_limit = limit = _limit_for_tiles(m, L.shape, tiles)
    ref = m.compute(L, R, confidence=True)
    assert ref.plan.tiled and len(ref.plan.tiles) >= tiles
    config = dd.matcher_config(cost=cost, weights=weights, memory_limit=limit)
    [(got_job, res)] = list(dd.match_pairs(cluster, [job], config, D, want_confidence=True, split_tiles=True))
    assert not isinstance(res, BaseException), res
    for a, b in ((ref.disparity, res.disparity), (ref.confidence, res.confidence), (ref.labels, res.labels)):
        assert a.shape == b.shape
        np.testing.assert_array_equal(a, b)  # bit for bit (NaN where NaN)
    return limit


def test_huge_image_split_over_workers_equals_tiled_run(shared_data, cluster, tmp_path):
    job = _tall_pair(shared_data, tmp_path)
    limit = _split_equals_tiled_run(job, cluster, "census", None, 32, tiles=4)
    # a tile that cannot fit is an error before any tile runs
    config = dd.matcher_config(cost="census", memory_limit=limit // 8)
    [(_, res)] = list(dd.match_pairs(cluster, [job], config, 32, split_tiles=True))
    assert isinstance(res, InputError) and "does not fit" in str(res)


@pytest.mark.slow
def test_huge_image_split_network_cost(shared_data, cluster, tmp_path):
    """The network's volume per tile from the whole image's standardisation: bit for bit too."""
    job = _tall_pair(shared_data, tmp_path, width=260)
    _split_equals_tiled_run(job, cluster, "cnn", "kitti-fst", 200, tiles=2)


def test_network_tile_tasks_stay_within_memory_limit(shared_data, tmp_path):
    """A worker's network tile task (run here in-process, twice, as a worker runs
    its tiles) keeps no volume through the network's bands and no feature maps
    through the volume stages, as StereoMatcher's tiled call does: the device
    peak stays within the memory limit on every task (before, the second task
    held the first's kept volumes through its bands)."""
    job = _tall_pair(shared_data, tmp_path, width=200)
    config = dd.matcher_config(cost="cnn", weights="kitti-fst", memory_limit=None)
    D = 64
    m = dd._matcher(config, D)  # the in-process worker's matcher (built once, kept)
    try:
        L = _gray(read_image(job.left))
        m.memory_limit = limit = _limit_for_tiles(m, L.shape, 3)
        plan = dd.plan_task(config, L.shape, D)
        assert plan["tiled"] and len(plan["tiles"]) >= 3
        for tile in plan["tiles"][:3]:
            m.ctx.memory.reset_peak()
            dd.tile_task(config, job, D, tile, plan["tile_budget"], False)
            assert m.ctx.memory.peak <= limit, (tile, m.ctx.memory.peak, limit)
    finally:
        dd._MATCHERS.pop(dd._key(config, D), None)


def test_worker_devices(monkeypatch, capsys):
    """LocalCluster worker i takes device i of the preferred kind; --device pins every worker."""
    import mccnn_cl.opencl.context as cl
    gpus = [cl.DeviceInfo(0, i, "NVIDIA CUDA", "OpenCL 3.0", f"GPU {i}", "GPU", f"gpu{i}") for i in range(3)]
    cpu = cl.DeviceInfo(1, 0, "Portable Computing Language", "OpenCL 3.0", "cpu", "CPU", "cpu")
    monkeypatch.setattr(cl, "list_devices", lambda: [*gpus, cpu])
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    assert [dd.worker_device(None, i)[0].device for i in range(5)] == ["GPU 0", "GPU 1", "GPU 2", "GPU 0", "GPU 1"]
    assert dd.worker_device(None, None)[0].device == "GPU 0"  # not a LocalCluster worker: the default choice
    monkeypatch.setattr(cl, "select_device", lambda spec=None: ("cpu", f"argument {spec!r}"))
    assert [dd.worker_device("cpu", i)[0].device for i in range(2)] == ["cpu", "cpu"]
    monkeypatch.undo()
    assert main(["devices", "--workers", "2"]) == 0
    out = capsys.readouterr().out
    assert "worker 0: " in out and "worker 1: " in out


# -- checks every path makes before any work; a failed --force rewrite --------------------------

def _copy_pairs(kitti, root, n=2):
    """root/l/NAME.png and root/r/NAME.png: copies (not links) of the first n pairs."""
    for side, src in (("l", "image_2"), ("r", "image_3")):
        (root / side).mkdir(parents=True)
        for f in FRAMES[:n]:
            shutil.copyfile(kitti / src / f"{f}_10.png", root / side / f"{f}.png")
    return root


@pytest.mark.parametrize("mode", ["--force", "--resume"])
def test_outputs_never_overwrite_inputs(kitti, cluster, tmp_path, capsys, mode):
    """An output naming an input image is refused before any work, even with --force or --resume:
    in the one-process batch, on a cluster, and for one pair with --workers."""
    root = _copy_pairs(kitti, tmp_path / "in")
    before = files(root / "l"), files(root / "r")
    for side in ("l", "r"):
        for extra in ([], ["--scheduler", cluster.scheduler.address], ["--workers", "1"]):
            rc = main(["match", "-l", str(root / "l/*.png"), "-r", str(root / "r/*.png"), "--output-dir",
                       str(root / side), "--format", "png", mode, *extra, *COMMON])
            err = capsys.readouterr().err
            assert rc == 2, (side, extra, err)
            assert "is the input image" in err
        if mode == "--force":  # one pair on a cluster (refused before the cluster starts)
            one = root / side / f"{FRAMES[0]}.png"
            rc = main(["match", str(root / "l" / one.name), str(root / "r" / one.name), "-o", str(one), "--force",
                       "--workers", "1", *COMMON])
            assert rc == 2 and "is the input image" in capsys.readouterr().err
    assert (files(root / "l"), files(root / "r")) == before


def test_relative_paths_with_workers_in_another_folder(kitti, reference, cluster, tmp_path, monkeypatch, capsys):
    """--scheduler with relative paths: the workers of an existing cluster run in a working folder of
    their own, and the client sends them the paths made absolute in its folder
    (dd.for_workers), so a batch and one pair given relative paths are matched (before, every pair
    failed: the workers looked for l/NAME.png in their folder), byte for byte as in one process."""
    client_dir = _copy_pairs(kitti, tmp_path / "client")
    elsewhere = tmp_path / "worker"
    elsewhere.mkdir()
    before = cluster.run(os.getcwd)
    cluster.run(os.chdir, str(elsewhere))
    try:
        assert set(cluster.run(os.getcwd).values()) == {str(elsewhere)}
        monkeypatch.chdir(client_dir)
        rc = main(["match", "-l", "l/*.png", "-r", "r/*.png", "--output-dir", "out",
                   "--scheduler", cluster.scheduler.address, *COMMON])
        cap = capsys.readouterr()
        assert rc == 0, cap.out + cap.err
        assert "done 2, skipped 0 (outputs complete), failed 0" in cap.out
        for f in FRAMES[:2]:
            assert (client_dir / "out" / f"{f}.pfm").read_bytes() == (reference / f"{f}_10.pfm").read_bytes()
        f = FRAMES[0]
        rc = main(["match", f"l/{f}.png", f"r/{f}.png", "-o", "one.pfm", "--scheduler", cluster.scheduler.address,
                   *COMMON])
        cap = capsys.readouterr()
        assert rc == 0, cap.out + cap.err
        assert (client_dir / "one.pfm").read_bytes() == (reference / f"{f}_10.pfm").read_bytes()
        assert os.listdir(elsewhere) == []  # the workers read by absolute path and write nothing
    finally:
        for address, cwd in before.items():
            cluster.run(os.chdir, cwd, workers=[address])
    job = Job("a", "l/a.png", "r/a.png", "out/a.pfm", ["out/a_color.png"])
    sent = dd.for_workers(job)
    assert (sent.left, sent.right, sent.out, sent.sides) == (
        str(client_dir / "l/a.png"), str(client_dir / "r/a.png"), str(client_dir / "out/a.pfm"),
        [str(client_dir / "out/a_color.png")])


@pytest.mark.parametrize("split", [False, True], ids=["pair task", "split tiles"])
def test_failures_name_paths_as_given(cluster, tmp_path, monkeypatch, split):
    """A pair given by relative paths whose image is not there: its failure names the path as the
    user gave it (``file not found: l/a.png``), not the absolute path the worker was sent
    (dd.for_workers), which the user never typed.  With split tiles the client reads the sent path
    itself (the image's size, for the plan): the same."""
    monkeypatch.chdir(tmp_path)
    job = Job("a", "l/a.png", "r/a.png", "out/a.pfm", ["out/a_color.png"])
    [(got, exc)] = list(dd.match_pairs(cluster, [job], dd.matcher_config(cost="census"), D, split_tiles=split))
    assert got is job and isinstance(exc, InputError), exc
    assert str(exc) == "file not found: l/a.png"
    # an exception whose message is not its one text argument is left as it is
    err = OSError(2, "No such file or directory", str(tmp_path / "l/a.png"))
    assert dd._as_given(err, {str(tmp_path / "l/a.png"): "l/a.png"}).filename == str(tmp_path / "l/a.png")


@pytest.mark.parametrize("rng", [["--disp-range", "auto"], ["--min-disp", "4", "--max-disp", "16"],
                                 ["--disp-range", "4:19"]])
@pytest.mark.parametrize("where", ["--workers", "--scheduler"])
def test_split_tiles_with_a_range_not_from_0_refused_before_a_cluster(kitti, tmp_path, monkeypatch, capsys, rng,
                                                                        where):
    """--split-tiles needs a range from 0: with --disp-range auto or a minimum disparity it is
    refused from the options alone, before any cluster starts, any client connects or the output
    folder is made (before, a LocalCluster started first and the refusal came from its client)."""
    import distributed
    started = []

    def no_cluster(*args, **kwargs):
        started.append((args, kwargs))
        raise AssertionError("a cluster was started")
    monkeypatch.setattr(dd, "local_cluster", no_cluster)
    monkeypatch.setattr(distributed, "Client", no_cluster)
    extra = ["--workers", "2"] if where == "--workers" else ["--scheduler", "tcp://127.0.0.1:1"]
    out = tmp_path / "out"
    for what in (["-l", str(kitti / "image_2/*.png"), "-r", str(kitti / "image_3/*.png"), "--output-dir", str(out)],
                 [str(kitti / f"image_2/{FRAMES[0]}_10.png"), str(kitti / f"image_3/{FRAMES[0]}_10.png"),
                  "-o", str(out / "one.pfm")]):
        rc = main(["match", *what, "--cost", "census", *rng, *extra, "--split-tiles"])
        err = capsys.readouterr().err
        assert rc == 2, err
        assert "--split-tiles cannot be combined with --min-disp or --disp-range auto" in err
        assert started == [] and not out.exists()


def test_split_tiles_without_a_cluster_is_refused(kitti, tmp_path, capsys):
    """--split-tiles only means something on Dask workers: without --workers or --scheduler it is
    refused in one line before any work (it used to be ignored silently)."""
    out = tmp_path / "out"
    for what in (["-l", str(kitti / "image_2/*.png"), "-r", str(kitti / "image_3/*.png"), "--output-dir", str(out)],
                 [str(kitti / f"image_2/{FRAMES[0]}_10.png"), str(kitti / f"image_3/{FRAMES[0]}_10.png"),
                  "-o", str(out / "one.pfm")]):
        rc = main(["match", *what, "--cost", "census", "--max-disp", "32", "--split-tiles"])
        err = capsys.readouterr().err
        assert rc == 2, err
        assert "--split-tiles spreads a pair's tiles over Dask workers" in err
        assert len(err.strip().splitlines()) == 1, err
        assert not out.exists()


def test_png_range_refused_before_any_work(kitti, cluster, tmp_path, capsys):
    """A .png batch (and one .png pair on a cluster) with a stated range a KITTI PNG cannot hold is
    refused before any work, as for one pair in one process; --disp-range auto is not (per pair)."""
    root = _copy_pairs(kitti, tmp_path / "in")
    lr = ["-l", str(root / "l/*.png"), "-r", str(root / "r/*.png")]
    for rng, words in ((["--min-disp", "-24", "--max-disp", "40"], "cannot store negative disparities"),
                       (["--disp-range=-24:15"], "cannot store negative disparities"),
                       (["--max-disp", "300"], "holds disparities 0..255.996")):
        for extra in ([], ["--scheduler", cluster.scheduler.address], ["--workers", "1"]):
            out = tmp_path / "out"
            rc = main(["match", *lr, "--output-dir", str(out), "--format", "png", "--cost", "census", *rng, *extra])
            err = capsys.readouterr().err
            assert rc == 2, (rng, extra, err)
            assert words in err
            assert not out.exists()
        one = tmp_path / "one.png"
        rc = main(["match", str(root / f"l/{FRAMES[0]}.png"), str(root / f"r/{FRAMES[0]}.png"), "-o", str(one),
                   "--cost", "census", *rng, "--workers", "1"])
        assert rc == 2 and words in capsys.readouterr().err and not one.exists()


def test_pairing_question_marks_classes_and_single_files(kitti, reference, tmp_path, capsys):
    """?, [...] and * in one component give one key (the text they matched, concatenated); keys of
    components with wildcards are joined with '/'; one file named on each side is one pair."""
    cam = tmp_path / "cam"
    cam.mkdir()
    for n in ("L0001.png", "R0001.png", "L0002.png", "R0002.png"):
        (cam / n).write_bytes(b"")
    want = [("L0001", "L0001.png", "R0001.png"), ("L0002", "L0002.png", "R0002.png")]
    for left in ("L????.png", "L*.png", "L[0-9]???.png", "L?[0-9]*.png", "L*[!x].png"):
        for right in ("R*.png", "R??[0-9]?.png", "R[0-9][0-9]*"):
            pairs = pair_globs(str(cam / left), str(cam / right), IMAGE_EXTENSIONS)
            assert [(n, os.path.basename(lp), os.path.basename(rp)) for n, lp, rp in pairs] == want, (left, right)
    with pytest.raises(InputError, match="without a right partner"):  # keys 01, 02 beside 0001, 0002
        pair_globs(str(cam / "L[0-9]00?.png"), str(cam / "R*.png"), IMAGE_EXTENSIONS)
    for scene in ("A1", "B2"):
        for c in ("cam0", "cam1"):
            (tmp_path / "scenes" / scene / c).mkdir(parents=True)
            (tmp_path / "scenes" / scene / c / "im.png").write_bytes(b"")
    pairs = pair_globs(str(tmp_path / "scenes/??/cam0/*.png"), str(tmp_path / "scenes/*/cam1/??.png"),
                       IMAGE_EXTENSIONS)
    assert [n for n, _, _ in pairs] == ["A1/im", "B2/im"]
    # one file each side, without wildcards: one pair, named after the left file
    assert pair_globs(str(cam / "L0001.png"), str(cam / "R0002.png"), IMAGE_EXTENSIONS) == [
        ("L0001", str(cam / "L0001.png"), str(cam / "R0002.png"))]
    out = tmp_path / "one"
    f = FRAMES[0]
    assert main(["match", "-l", str(kitti / f"image_2/{f}_10.png"), "-r", str(kitti / f"image_3/{f}_10.png"),
                 "--output-dir", str(out), *COMMON]) == 0
    assert listing(out) == [f"{f}_10.pfm"]
    assert (out / f"{f}_10.pfm").read_bytes() == (reference / f"{f}_10.pfm").read_bytes()


@pytest.mark.parametrize("where", ["one process", "cluster"])
def test_calib_without_focal_length_gives_the_range(kitti, shared_data, cluster, tmp_path, capsys, where):
    """A Middlebury 2001-2006 calib.txt (width, height, ndisp only) in a batch and for one pair on a
    cluster: a note, ndisp as the range, no depth or point cloud -- as for one pair in one process."""
    ts = shared_data / "middlebury/Tsukuba"
    calib = str(ts / "calib.txt")
    root = tmp_path / "in"
    names = ("tsukuba", "upside_down")  # pairs of the calibration's size (384x288)
    for side, im in (("l", "im0.png"), ("r", "im1.png")):
        (root / side).mkdir(parents=True)
        img = read_image(ts / im)
        write_image(root / side / f"{names[0]}.png", img)
        write_image(root / side / f"{names[1]}.png", np.ascontiguousarray(img[::-1]))
    extra = ["--scheduler", cluster.scheduler.address] if where == "cluster" else []
    pairs = [(str(root / f"l/{n}.png"), str(root / f"r/{n}.png")) for n in names]
    single = []
    for i, (lp, rp) in enumerate(pairs):  # the one-process single pair: the reference
        single.append(tmp_path / f"single{i}.pfm")
        assert main(["match", lp, rp, "-o", str(single[i]), "--cost", "census", "--calib", calib]) == 0
    capsys.readouterr()
    out = tmp_path / "out"
    args = ["match", "-l", str(root / "l/*.png"), "-r", str(root / "r/*.png"), "--output-dir", str(out),
            "--cost", "census", "--calib", calib, "--color", "--verbose", *extra]
    assert main(args) == 0
    cap = capsys.readouterr()
    assert "has no focal length/baseline" in cap.err and "ndisp=32" in cap.err
    assert "done 2, skipped 0" in cap.out
    assert sorted(listing(out)) == sorted(f"{n}{s}" for n in names for s in (".pfm", "_color.png"))
    for i, n in enumerate(names):
        assert (out / f"{n}.pfm").read_bytes() == single[i].read_bytes()  # ndisp = 32 levels
    assert cap.out.count("384x288, 32 disparities") == 2  # --verbose: a line per pair
    assert main(args + ["--resume"]) == 0  # complete without depth files
    assert "done 0, skipped 2" in capsys.readouterr().out
    if where == "cluster":
        one = tmp_path / "one.pfm"
        assert main(["match", *pairs[0], "-o", str(one), "--cost", "census", "--calib", calib, *extra]) == 0
        assert "has no focal length/baseline" in capsys.readouterr().err
        assert one.read_bytes() == single[0].read_bytes()
        assert sorted(listing(tmp_path)) == ["in", "one.pfm", "out", "single0.pfm", "single1.pfm"]


def test_batch_says_once_when_calib_is_for_another_size(shared_data, tmp_path, capsys):
    """--calib for 384x288 images on a batch of 120x96 crops: one warning for the size, not one per pair."""
    ts = shared_data / "middlebury/Tsukuba"
    root = tmp_path / "in"
    for side, im in (("l", "im0.png"), ("r", "im1.png")):
        (root / side).mkdir(parents=True)
        img = read_image(ts / im)
        for i in range(2):
            write_image(root / side / f"c{i}.png", np.ascontiguousarray(img[100 + 40 * i:196 + 40 * i, 150:270]))
    assert main(["match", "-l", str(root / "l/*.png"), "-r", str(root / "r/*.png"), "--output-dir",
                 str(tmp_path / "out"), "--cost", "census", "--calib", str(ts / "calib.txt")]) == 0
    err = capsys.readouterr().err
    assert err.count("is for 384x288 images") == 1 and "is 120x96" in err


def test_remove_partial_removes_only_what_the_write_made(tmp_path):
    def put(p, data):
        tmp = tmp_path / ".tmp"
        tmp.write_bytes(data)
        os.replace(tmp, p)  # as the writers do: a temporary file renamed

    job = Job("a", "l.png", "r.png", str(tmp_path / "a.pfm"),
              [str(tmp_path / "a_color.png"), str(tmp_path / "a_confidence.pfm")])
    for p in job.outputs:
        put(p, b"old")
    before = job.state()
    put(job.sides[0], b"new")  # a --force rewrite fails after its first side file
    job.remove_partial(before)
    assert [os.path.exists(p) for p in job.outputs] == [False, True, True]
    assert not job.complete()  # --resume redoes it
    put(job.sides[0], b"old")
    before = job.state()
    for p in job.outputs:  # a write that got as far as the disparity map: complete, kept
        put(p, b"new")
    job.remove_partial(before)
    assert job.complete()
    os.unlink(job.out)
    before = job.state()  # no map yet (first run): every side file the write made goes
    os.unlink(job.sides[1])
    put(job.sides[1], b"new")
    job.remove_partial(before)
    assert [os.path.exists(p) for p in job.outputs] == [True, False, False]


@pytest.mark.parametrize("where", ["one process", "cluster"])
def test_failed_force_rewrite_leaves_pair_incomplete(kitti, reference, cluster, tmp_path, monkeypatch, capsys,
                                                     where):
    """--force over complete pairs, one pair's rewrite failing before its disparity map: the
    rewrite removed the old map (and record) first and the side files it made go, so nothing of
    that pair remains and --resume redoes it."""
    import errno

    import mccnn_cl.cli.common as common  # the writer batches call
    out = tmp_path / "out"
    args = ["match", *glob_args(kitti), "--output-dir", str(out), "--color", "--confidence", *COMMON]
    assert main(args) == 0
    real = common.write_disparity

    def failing(path, disp):
        if os.path.basename(path).startswith(FRAMES[0]):
            raise OSError(errno.EIO, "Input/output error")  # this pair's only (a full disk stops the batch)
        real(path, disp)

    monkeypatch.setattr(common, "write_disparity", failing)
    extra = ["--scheduler", cluster.scheduler.address] if where == "cluster" else []
    capsys.readouterr()
    assert main(args + ["--force", *extra]) == 1
    assert f"done {len(FRAMES) - 1}, skipped 0 (outputs complete), failed 1" in capsys.readouterr().out
    assert [p for p in os.listdir(out) if FRAMES[0] in p] == []
    monkeypatch.setattr(common, "write_disparity", real)
    assert main(args + ["--resume", *extra]) == 0
    assert f"done 1, skipped {len(FRAMES) - 1}" in capsys.readouterr().out
    assert files(out) == {p: b for p, b in files(reference).items() if not p.endswith("_labels.png")}


# -- crash safety: a killed --force, settings records, a full disk, progress in logs ------------

def _two_pairs(kitti, root, frames=(0, 1)):
    """root/l/{a,b}.png and root/r/{a,b}.png: copies of two frames' crops."""
    for side, src in (("l", "image_2"), ("r", "image_3")):
        (root / side).mkdir(parents=True, exist_ok=True)
        for name, i in zip("ab", frames):
            shutil.copyfile(kitti / src / f"{FRAMES[i]}_10.png", root / side / f"{name}.png")
    return ["-l", str(root / "l"), "-r", str(root / "r")]


#: runs `mccnn-cl ARGS` in a process that dies outright (no clean-up) when the disparity map of
#: pair "a" is about to be written: after its side files, as a SIGKILL or a power cut can
_DIE_BEFORE_MAP = """
import os, sys
import mccnn_cl.cli.common as common
real = common.write_disparity
def write(path, disp):
    if os.path.basename(path).startswith("a."):
        os._exit(9)
    real(path, disp)
common.write_disparity = write
from mccnn_cl.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_force_killed_before_the_map_leaves_the_pair_incomplete(kitti, tmp_path, capsys):
    """--force killed after a pair's new side files but before its map: the old map must not make
    the pair look complete (old map + new side files); --resume redoes it, and the folder then equals
    a fresh run's."""
    io = ["--color", "--confidence", *COMMON]
    pairs = _two_pairs(kitti, tmp_path / "in")
    out = tmp_path / "out"
    assert main(["match", *pairs, "--output-dir", str(out), *io]) == 0
    _two_pairs(kitti, tmp_path / "in", frames=(2, 1))  # pair a's images change (new rectification, ...)
    p = subprocess.run([sys.executable, "-c", _DIE_BEFORE_MAP, "match", *pairs, "--output-dir", str(out),
                        "--force", *io], capture_output=True, text=True, timeout=300)
    assert p.returncode == 9, p.stderr
    assert (out / "a_color.png").exists() and not (out / "a.pfm").exists()  # a is incomplete
    capsys.readouterr()
    assert main(["match", *pairs, "--output-dir", str(out), "--resume", *io]) == 0
    assert "done 1, skipped 1" in capsys.readouterr().out
    fresh = tmp_path / "fresh"
    assert main(["match", *pairs, "--output-dir", str(fresh), *io]) == 0
    assert files(out) == files(fresh)
    assert (out / ".a.pfm.mccnn.json").read_bytes() == (fresh / ".a.pfm.mccnn.json").read_bytes()


@pytest.mark.parametrize("where", ["one process", "cluster"])
def test_resume_refuses_pairs_made_with_other_settings(kitti, reference, cluster, tmp_path, capsys, where):
    """Each pair records its settings; --resume with other ones (here --max-disp) refuses before any
    work, naming the pairs and what differs, instead of keeping maps of another range."""
    import json

    out = tmp_path / "out"
    shutil.copytree(reference, out)
    extra = ["--scheduler", cluster.scheduler.address] if where == "cluster" else []
    io = ["--output-dir", str(out), "--color", "--confidence", "--labels", "--resume", *extra]
    before = files(out)
    capsys.readouterr()
    rc = main(["match", *glob_args(kitti), *io, "--cost", "census", "--max-disp", str(D + 8)])
    err = capsys.readouterr().err
    assert rc == 2, err
    rec = json.loads((out / f".{FRAMES[0]}_10.pfm.mccnn.json").read_text())["settings"]
    assert rec["cost"] == "census" and rec["disparities"] == f"0..{D - 1}"
    assert f"{len(FRAMES)} complete pair(s) were made with other settings" in err
    assert f"disparities 0..{D - 1} there, 0..{D + 7} now" in err and "--force" in err and FRAMES[0] in err
    assert files(out) == before
    assert main(["match", *glob_args(kitti), *io, *COMMON]) == 0  # the same settings: every pair kept
    assert f"done 0, skipped {len(FRAMES)}" in capsys.readouterr().out
    os.unlink(out / f".{FRAMES[1]}_10.pfm.mccnn.json")  # a pair of an older mccnn-cl: settings unknown
    assert main(["match", *glob_args(kitti), *io, *COMMON]) == 2
    assert f"1 complete pair(s) have no record of their settings ({FRAMES[1]}_10" in capsys.readouterr().err
    assert files(out) == before


@pytest.mark.parametrize("where, code", [("one process", "ENOSPC"), ("one process", "EROFS"),
                                         ("one process", "EDQUOT"), ("cluster", "ENOSPC")])
def test_full_disk_stops_the_batch_naming_the_file(kitti, cluster, tmp_path, monkeypatch, capsys, where, code):
    """A full disk, a read-only file system or a quota: the batch stops at the first pair, naming
    the file, instead of matching every pair to fail it the same way."""
    import errno

    import mccnn_cl.cli.common as common
    calls = []

    def full(path, disp):
        calls.append(path)
        raise OSError(getattr(errno, code), os.strerror(getattr(errno, code)))

    monkeypatch.setattr(common, "write_disparity", full)
    out = tmp_path / "out"
    extra = ["--scheduler", cluster.scheduler.address] if where == "cluster" else []
    rc = main(["match", *glob_args(kitti), "--output-dir", str(out), "--color", *COMMON, *extra])
    cap = capsys.readouterr()
    assert rc == 1
    assert len(calls) == 1, calls  # no later pair was written
    name = os.path.basename(calls[0])[:-len(".pfm")]  # on a cluster: the pair done first
    assert calls[0] == str(out / f"{name}.pfm")
    assert f"{calls[0]}: {os.strerror(getattr(errno, code))} (writing pair {name}): the batch stops here" in cap.err
    assert "--resume" in cap.err and "done 0, skipped 0 (outputs complete), failed 1" in cap.out
    assert os.listdir(out) == []  # the pair's colour picture (and settings record) went with it


def test_write_failing_without_a_reason_on_a_full_folder_stops_the_batch(kitti, tmp_path, monkeypatch, capsys):
    """cv2 only returns False on a full disk: a small write into the folder (the probe) finds the
    reason; on a folder with room the same failure is this pair's only."""
    import errno
    import types

    import mccnn_cl.batch as batch
    import mccnn_cl.cli.common as common

    def failing(path, disp):
        raise InputError(f"{path}: cv2 could not write the PNG")

    monkeypatch.setattr(common, "write_disparity", failing)
    pairs = _two_pairs(kitti, tmp_path / "in")
    rc = main(["match", *pairs, "--output-dir", str(tmp_path / "roomy"), *COMMON])
    assert rc == 2 and "done 0, skipped 0 (outputs complete), failed 2" in capsys.readouterr().out

    def quota(**kwargs):
        raise OSError(errno.EDQUOT, os.strerror(errno.EDQUOT), os.path.join(kwargs["dir"], ".mccnn-tmp-1-x"))

    monkeypatch.setattr(batch, "tempfile", types.SimpleNamespace(mkstemp=quota), raising=False)
    out = tmp_path / "full"
    rc = main(["match", *pairs, "--output-dir", str(out), *COMMON])
    cap = capsys.readouterr()
    assert rc == 1 and "failed 1" in cap.out
    assert f"{out}: {os.strerror(errno.EDQUOT)} (writing pair a): the batch stops here with 1 pair(s) left" in cap.err
    # the failed write's temporary file is gone when the probe runs: it writes more than any output needed
    asked = []
    monkeypatch.setattr(batch, "_probe_folder", lambda folder, nbytes=0: asked.append(nbytes))
    assert main(["match", *pairs, "--output-dir", str(tmp_path / "full2"), *COMMON]) == 2
    h, w = read_image(tmp_path / "in/l/a.png").shape[:2]
    assert len(asked) == 2 and min(asked) > h * w * 4  # > the float32 map, the largest output


@pytest.mark.parametrize("where", ["one process", "cluster"])
def test_progress_lines_when_not_a_terminal(kitti, cluster, tmp_path, capsys, where):
    """Redirected (a log, a pipe), a batch says 'k/N pairs ... ETA' on stderr as pairs end."""
    extra = ["--scheduler", cluster.scheduler.address] if where == "cluster" else []
    assert main(["match", *glob_args(kitti), "--output-dir", str(tmp_path / "out"), *COMMON, *extra]) == 0
    err = capsys.readouterr().err
    n = len(FRAMES)
    assert f"matching: 1/{n} pairs, " in err and ", ETA " in err
    assert f"matching: {n}/{n} pairs, " in err


def test_progress_lines_every_tenth_and_every_30_s():
    from mccnn_cl.batch import Progress

    now = [0.0]
    import io
    import contextlib
    buf = io.StringIO()
    with contextlib.redirect_stderr(buf):
        p = Progress(100, tty=False, clock=lambda: now[0])
        for i in range(100):
            now[0] += 0.5 if i < 50 else 20.0  # 50 quick pairs, then slow ones
            p.update(1)
    lines = buf.getvalue().splitlines()
    counts = [int(line.split()[1].split("/")[0]) for line in lines]
    assert counts[:5] == [10, 20, 30, 40, 50]  # every tenth while quick
    assert counts[5:7] == [52, 54]  # then at least every 30 s
    assert counts[-1] == 100 and lines[-1].startswith("matching: 100/100 pairs") and "ETA" not in lines[-1]
    assert lines[0] == "matching: 10/100 pairs, 00:05 elapsed, ETA 00:45"
