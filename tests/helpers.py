"""Helpers shared by several test modules (test modules import from here, never from each other)."""

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: The worker that runs the stage cases (``case_<name>``) on one OpenCL implementation.
WORKER = Path(__file__).resolve().parent / "test_oclgrind.py"


def invalid_mask(D, H, W):
    d = np.arange(D)[:, None, None]
    x = np.arange(W)[None, None, :]
    return np.broadcast_to(x < d, (D, H, W))


def random_volume(rng, D, H, W, scale=1.0):
    c = (scale * rng.random((D, H, W))).astype(np.float32)
    c[invalid_mask(D, H, W)] = np.nan
    return c


def blocky_image(rng, H, W, block=3, noise=0.02):
    """Piecewise-constant image with a little noise: arms of all lengths."""
    img = np.repeat(np.repeat(rng.random((H // block + 1, W // block + 1)), block, 0), block, 1)[:H, :W]
    return (img + noise * rng.random((H, W))).astype(np.float32)


def ad_volume(img_l, img_r, D):
    H, W = img_l.shape
    c = np.full((D, H, W), np.nan, np.float32)
    for d in range(D):
        c[d, :, d:] = np.abs(img_l[:, d:] - img_r[:, :W - d])
    return c



def kitti_crop(shared_data, y0, x0, H, W):
    """The H x W crop at (y0, x0) of KITTI 2015 training 000000, left and right, gray in [0, 1]."""
    import cv2  # not at the top: the Oclgrind worker imports this module

    imgs = []
    for rel in ("kitti2015/training/image_2/000000_10.png", "kitti2015/training/image_3/000000_10.png"):
        img = cv2.imread(str(shared_data / rel), cv2.IMREAD_GRAYSCALE)
        assert img is not None, rel
        imgs.append(img[y0:y0 + H, x0:x0 + W].astype(np.float32) / 255.0)
    return imgs

# -- network costs (test_fst.py, test_acrt.py) -----------------------------------
def random_pair(rng, H, W, shift=3):
    """A random left image and its right, shifted by ``shift`` with a little noise."""
    left = rng.random((H, W)).astype(np.float32)
    right = np.roll(left, -shift, axis=1) + 0.05 * rng.random((H, W)).astype(np.float32)
    return left, right


def run_poisoned(ctx, cost, left, right, D, half=False):
    """A cost's volume written into a poisoned buffer (conftest.POISON; -1e4 in half)."""
    from conftest import POISON  # not at the top: the Oclgrind worker imports this module without pytest

    m = cost.margin
    h, w = left.shape[0] - 2 * m, left.shape[1] - 2 * m
    item = 2 if half else 4
    d_out = ctx.empty(D * h * w * item, "test volume")
    ctx.fill(d_out, np.float16(-1e4) if half else POISON, D * h * w * item,
             dtype=np.float16 if half else np.float32)
    assert cost(left, right, D, out=d_out) is d_out
    return ctx.from_device(d_out, (D, h, w), np.float16 if half else np.float32)


# -- the stage cases of test_oclgrind.py (also run by test_portability.py) --------
# Kernels a device class never builds (its rules choose another form), so a case there need not
# fetch them: sgm_paired_q16 on Mesa's llvmpipe, which aborts building it (rule sgm_int16).
NOT_BUILT_ON = {"llvmpipe": {"sgm_paired_q16"}}
# The kernels each case must have fetched (checked in the worker): together
# they must cover every kernel the package uses (test_every_kernel_is_covered).
CASE_KERNELS = {
    "network": {"network_conv", "network_head", "network_mark_invalid"},
    "network_wg": {"network_conv_wg", "network_head_l4", "network_head_out", "network_mark_invalid"},
    "fst": {"network_conv", "fst_normalise16", "fst_volume_pairs"},
    "fst_wg": {"network_conv_wg", "fst_normalise", "fst_volume_wg"},
    "winograd": {"network_conv", "network_conv_wino"},
    "acrt": {"network_conv", "network_head", "network_mark_invalid"},
    "census": {"census_transform", "census_cost"},
    "range": {"range_mask"},
    "cross": {"cross_build"},
    "cbca": {"cbca_rows", "cbca_columns", "cbca_rows_short", "cbca_columns_short", "cbca_fused_short",
             "cbca_fused_multi_short"},
    "cbca_wg": {"cbca_rows_wg", "cbca_columns_wg"},
    "sgm": {"sgm_rows", "sgm_columns", "sgm_paired", "sgm_paired_q16"},
    "sgm_wg": {"sgm_wg_path", "sgm_wg_cols"},
    "disparity": {"disparity_wta_left", "disparity_wta_right", "disparity_lr_check",
                  "disparity_right_volume", "disparity_mirror", "interpolate_fill", "subpixel_refine"},
    "refine": {"refine_enlarge", "refine_median", "refine_median16", "refine_bilateral"},
    "confidence": {"confidence_curve"},
    "half": {"network_head", "network_mark_invalid", "census_cost", "cbca_fused_multi_short", "cbca_fused_short",
             "cbca_rows_short",
             "cbca_columns_short", "sgm_rows", "sgm_columns", "sgm_wg_path", "disparity_wta_left", "disparity_right_volume",
             "subpixel_refine"},
}

#: Build forms each case must have fetched whatever the device's rules pick (checked in the
#: worker): (kernel, {define: value, ...}), matched by a fetch of that kernel with at least
#: those defines.  The cpu rules column's forms, which Oclgrind (the gpu column) never takes
#: by default, and the tuner's sgm_wg_cols widths: the cases force them explicitly.
CASE_FORMS = {
    "network": [("network_conv", {"RN": 16}), ("network_head", {"RN": 16, "ROWS_FASTEST": 1}),
                ("network_conv", {"RN": 8}), ("network_head", {"RN": 8, "ROWS_FASTEST": 1})],
    "acrt": [("network_head", {"RN": 16, "NOUT": 1})],
    "winograd": [("network_conv_wino", {"RN": 16, "RT": 4, "XA": 4}),
                 ("network_conv_wino", {"RN": 8, "RT": 3, "XA": 2})],
    "cbca": [("cbca_fused_multi_short", {"CBCA_SELECT_ADD": 0}), ("cbca_fused_multi_short", {"CBCA_SELECT_ADD": 1})],
    "sgm": [("sgm_rows", {"SGM_WHOLE_TILES": 0}), ("sgm_paired", {"VOL_HALF": 1, "SGM_VW": 8})],
    "sgm_wg": [("sgm_wg_cols", {"SGM_WG_CW": 16}), ("sgm_wg_cols", {"SGM_WG_CW": 32})],
    "disparity": [("disparity_wta_left", {"WTA_CHUNKS": 8, "VOL_HALF": 0}),
                  ("disparity_wta_left", {"WTA_CHUNKS": 8, "VOL_HALF": 1}),
                  ("disparity_right_volume", {"MIRROR_LINES": 1, "VOL_HALF": 0}),
                  ("disparity_right_volume", {"MIRROR_LINES": 1, "VOL_HALF": 1})],
    "half": [("sgm_rows", {"VOL_HALF": 1}), ("sgm_columns", {"VOL_HALF": 1})],
}


def run_isolated(impl: str, case: str, timeout: float = 600, nice: int = 0, started=None) -> dict:
    """Run one case in a subprocess that sees only ``impl``.

    Returns ``{"ok", "result" (the worker's dict or None), "oclgrind_errors",
    "stdout", "stderr", "seconds"}``.  Raises ``conftest.ImplUnavailable``
    when the implementation is not installed, ``subprocess.TimeoutExpired``
    (the worker killed) past ``timeout`` seconds.  ``nice``: the worker's
    niceness increment (``nice -n``); ``started(proc)``: called with the
    worker's Popen once it runs (:class:`BackgroundCases` keeps it to stop it).
    """
    from conftest import CL_IMPLS, impl_environ, oclgrind_errors  # noqa: E402

    with tempfile.TemporaryDirectory(prefix="mccnn-impl-") as tmp:
        log = Path(tmp) / "oclgrind.log"
        env = {k: v for k, v in os.environ.items()
               if not k.startswith(("OCLGRIND_", "PYOPENCL_CTX", "RUSTICL_", "OCL_ICD_"))}
        env.update(impl_environ(impl, oclgrind_log=log))
        cmd = [sys.executable, str(WORKER), case, "--expect-platform", CL_IMPLS[impl]["platform"]]
        if nice:
            cmd = ["nice", "-n", str(nice)] + cmd
        t0 = time.perf_counter()
        with subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
            if started is not None:
                started(proc)
            try:
                stdout, stderr = proc.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()
                raise
        seconds = time.perf_counter() - t0
        log_text = log.read_text(errors="replace") if log.exists() else ""
    result = None
    for line in stdout.splitlines():
        if line.startswith("RESULT "):
            result = json.loads(line[7:])
    errors = ""
    if impl == "oclgrind":
        # the log holds only kernel diagnostics: any content fails; API errors go to stderr
        errors = "\n\n".join(e for e in (log_text.strip(), oclgrind_errors(
            "\n\n".join(b for b in stderr.split("\n\n") if "Oclgrind" in b))) if e)
    ok = proc.returncode == 0 and result is not None and result["ok"] and not errors
    return {"ok": ok, "result": result, "oclgrind_errors": errors, "stdout": stdout,
            "stderr": stderr, "seconds": seconds, "returncode": proc.returncode}


class BackgroundCases:
    """Stage cases on other implementations (test_portability.py) run by one
    background thread, one after another, from the start of the session.

    Why: on a fresh machine the Rusticl cases spend ~13 minutes compiling
    (llvmpipe builds each kernel at its first launch, on one core, with a cold
    Mesa cache), while the rest of the suite leaves a core idle through its own
    single-threaded builds.  Started by ``conftest.pytest_collection_finish``
    for the selected cases only, at ``nice`` 19 so that they take what the
    suite leaves idle; each test then waits for its case's result
    (:meth:`result`), which runs the case in the foreground when it was not
    queued.  :meth:`stop` (``pytest_unconfigure``) kills a worker still running.
    """

    NICE = 19
    #: the cases slowest to build first (measured on Rusticl with a cold cache: fst ~320 s,
    #: sgm ~135 s, half ~120 s, winograd ~50 s); the rest in name order
    FIRST = ("fst", "sgm", "half", "winograd", "cbca")

    def __init__(self):
        import threading

        self._lock = threading.Lock()
        self._done = {}  # (impl, case) -> threading.Event
        self._results = {}  # (impl, case) -> result dict or the exception raised
        self._proc = None
        self._stopped = False
        self._thread = None

    def start(self, pairs, timeout: float) -> None:
        """Queue ``pairs`` [(impl, case)] and start the thread (once)."""
        import threading

        order = {c: i for i, c in enumerate(self.FIRST)}
        queue = sorted(dict.fromkeys(pairs), key=lambda p: (order.get(p[1], len(order)), p[1], p[0]))
        if not queue or self._thread is not None:
            return
        with self._lock:
            for p in queue:
                self._done[p] = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(queue, timeout), daemon=True,
                                        name="mccnn-background-cases")
        self._thread.start()

    def _started(self, proc):
        with self._lock:
            self._proc = proc
            stopped = self._stopped
        if stopped:
            proc.kill()

    def _run(self, queue, timeout):
        for p in queue:
            if self._stopped:
                break
            try:
                res = run_isolated(*p, timeout=timeout, nice=self.NICE, started=self._started)
            except BaseException as exc:  # handed to the test, which raises it
                res = exc
            with self._lock:
                self._proc = None
                self._results[p] = res
            self._done[p].set()

    def result(self, impl: str, case: str, timeout: float) -> dict:
        """The case's result: from the background run when it was queued, else run now."""
        ev = self._done.get((impl, case))
        if ev is None:
            return run_isolated(impl, case, timeout=timeout)
        while not ev.wait(5.0):
            if self._thread is None or not self._thread.is_alive():
                raise RuntimeError(f"the background run of {case} on {impl} ended without a result")
        res = self._results[(impl, case)]
        if isinstance(res, BaseException):
            raise res
        return res

    def stop(self) -> None:
        with self._lock:
            self._stopped = True
            proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()


#: seconds one stage case may run on another implementation (test_portability.py): a guard
#: against hangs, not a speed test
STAGE_CASE_TIMEOUT = 900

#: the session's background runner (conftest.py starts it; test_portability.py reads it)
BACKGROUND = BackgroundCases()


# -- device profiles (test_device.py, test_cbca_gpu.py, test_network_gpu.py, test_gpu_memory.py) --
def fake_device(name, type_, units=2, width=16, platform="Some platform", global_mem=1 << 32,
                max_alloc=1 << 30, max_work_group=256, local_mem=1 << 16):
    """What DeviceProfile.of reads of a pyopencl device, for a device that is not here."""
    from types import SimpleNamespace

    return SimpleNamespace(name=name, type=type_, max_compute_units=units, preferred_vector_width_float=width,
                           native_vector_width_float=width, global_mem_size=global_mem, local_mem_size=local_mem,
                           max_mem_alloc_size=max_alloc, max_work_group_size=max_work_group,
                           platform=SimpleNamespace(name=platform))
