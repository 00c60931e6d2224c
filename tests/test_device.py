"""mccnn_cl.opencl.device: the one device profile and its rule table."""

import re
from pathlib import Path

import pyopencl as cl
import pytest

from helpers import fake_device

from mccnn_cl.opencl.device import CLASSES, CPU, GPU, LLVMPIPE, LLVMPIPE_LOOP_LIMIT, RULES, DeviceProfile, device_class
from mccnn_cl.stages.cbca import CBCA, SHORT_MAX
from mccnn_cl.stages.sgm import SGM
from mccnn_cl.stages.sgm_select import make_sgm
from mccnn_cl.stages.sgm_wg import SGMWorkGroup

PACKAGE = Path(__file__).resolve().parents[1] / "mccnn_cl"


T = cl.device_type
DEVICES = {  # what the platforms here report (name, type), and a GPU
    "pocl": fake_device("pthread-skylake-avx512-AMD EPYC", T.CPU),
    "llvmpipe": fake_device("llvmpipe (LLVM 15.0.6, 256 bits)", T.CPU, units=8, width=1, platform="rusticl"),
    "oclgrind": fake_device("Oclgrind Simulator", T.ALL, units=1, width=1, platform="Oclgrind"),
    "gpu": fake_device("NVIDIA H200", T.GPU, units=132, width=1, platform="NVIDIA CUDA"),
}


def test_classes():
    assert device_class(DEVICES["pocl"], cl) == CPU
    assert device_class(DEVICES["llvmpipe"], cl) == LLVMPIPE
    assert device_class(DEVICES["oclgrind"], cl) == GPU  # every type bit at once: a simulated generic device
    assert device_class(DEVICES["gpu"], cl) == GPU
    assert device_class(fake_device("some accelerator", T.ACCELERATOR), cl) == GPU


def test_every_rule_has_every_column():
    for option, row in RULES.items():
        assert set(row) == set(CLASSES), option


def test_declared_loop_limit_and_the_rules_it_changes():
    pocl, pipe = (DeviceProfile.of(DEVICES[k], cl) for k in ("pocl", "llvmpipe"))
    assert pocl.loop_limit is None and not pocl.slow_compiler
    assert pipe.loop_limit == LLVMPIPE_LOOP_LIMIT == 65535 and pipe.slow_compiler
    assert pipe.sgm_options()["fused_rows"] is False and pocl.sgm_options()["fused_rows"] is True
    # an explicit limit overrides the declared one either way
    assert pocl.sgm_options(loop_limit=3000)["loop_limit"] == 3000
    assert pocl.sgm_options(loop_limit=3000)["fused_rows"] is False
    assert pocl.sgm_options(loop_limit=3000)["disp_floor"] == 64 and pocl.sgm_options()["disp_floor"] == 256
    assert pipe.sgm_options(loop_limit=0)["loop_limit"] is None
    # CBCA's fused kernels walk a whole plane per work-item: not under llvmpipe's limit
    assert pipe.cbca_path(3, SHORT_MAX) == "short" and pocl.cbca_path(3, SHORT_MAX) == "multi"


def test_sgm_mirror_reads_follow_the_vector_width():
    """On CPUs the right reference's SGM reads the volume mirrored where the device's float
    vectors hold 16 (the rules' None), and mirrors it in place where they hold 8 (a Zen 3);
    a tuned value wins either way; llvmpipe and GPUs read mirrored."""
    from dataclasses import replace

    wide = DeviceProfile.of(DEVICES["pocl"], cl)
    narrow = DeviceProfile.of(fake_device("pthread-haswell-AMD EPYC", T.CPU, width=8), cl)
    assert RULES["sgm_mirror_reads"][CPU] is None
    assert wide.sgm_mirror_reads() is True and wide.value("sgm_mirror_reads") is True
    assert narrow.sgm_mirror_reads() is False and narrow.sgm_options()["mirror_reads"] is False
    assert replace(narrow, tuned={"sgm_mirror_reads": True}).sgm_options()["mirror_reads"] is True
    assert replace(wide, tuned={"sgm_mirror_reads": False}).value("sgm_mirror_reads") is False
    for key in ("llvmpipe", "gpu"):
        assert DeviceProfile.of(DEVICES[key], cl).sgm_mirror_reads() is True


@pytest.mark.parametrize("key, sgm, cbca, rn", [
    # the defaults each stage had before the profile (one device of each kind seen here), except
    # Oclgrind's CBCA: "multi" before (its CPU bit), now the generic column's work-group passes
    # (kernels/cbca_wg.cl), bit-identical to the short and fused kernels (tests/test_cbca_gpu.py)
    ("pocl", dict(prefetch=True, cols=128, fused_rows=True, specialize=True, whole_tiles=True, paired=True,
                  group_of_one=True, loop_limit=None, width=8, mirror_reads=True, disp_floor=256, int16=True), "multi",
     16),
    ("llvmpipe", dict(prefetch=True, cols=32, fused_rows=False, specialize=False, whole_tiles=False, paired=False,
                      group_of_one=True, loop_limit=65535, width=16, mirror_reads=True, disp_floor=64, int16=False),
     "short", 4),
    ("oclgrind", dict(prefetch=False, cols=32, fused_rows=False, specialize=True, whole_tiles=True, paired=False,
                      group_of_one=False, loop_limit=None, width=16, mirror_reads=True, disp_floor=64, int16=False),
     "workgroup", 4),
    ("gpu", dict(prefetch=False, cols=32, fused_rows=False, specialize=True, whole_tiles=True, paired=False,
                 group_of_one=False, loop_limit=None, width=16, mirror_reads=True, disp_floor=64, int16=False),
     "workgroup", 4),
])
def test_rules_per_device(key, sgm, cbca, rn):
    p = DeviceProfile.of(DEVICES[key], cl)
    assert p.sgm_options() == sgm
    assert p.cbca_path(3, SHORT_MAX) == cbca
    assert p.cbca_path(9, SHORT_MAX) == "running" and p.cbca_path(3, SHORT_MAX, short=False) == "running"
    assert p.cbca_path(3, SHORT_MAX, fused=True, multi=False) == "fused"
    assert p.cbca_path(3, SHORT_MAX, fused=False, multi=False) == "short"
    assert p.cbca_path(3, SHORT_MAX, workgroup=True) == "workgroup"
    assert p.cbca_path(9, SHORT_MAX, workgroup=True) == "running"  # longer arms: the running sums
    tiles = p.network_tiles()
    assert tiles["RN"] == rn and tiles["ROWS_FASTEST"] == int(p.is_cpu)


def test_paired_sweeps_follow_compute_units():
    assert DeviceProfile.of(fake_device("cpu", T.CPU, units=2), cl).sgm_options()["paired"]
    assert not DeviceProfile.of(fake_device("cpu", T.CPU, units=3), cl).sgm_options()["paired"]


def test_stages_take_their_defaults_from_the_profile(ctx):
    opts = ctx.profile.sgm_options()
    s = SGM(ctx)
    assert (s.prefetch, s.cols, s.fused_rows, s.specialize, s.whole_tiles, s.paired, s._loop_limit, s.width) == \
        (opts["prefetch"], opts["cols"], opts["fused_rows"], opts["specialize"], opts["whole_tiles"],
         opts["paired"], opts["loop_limit"], opts["width"])
    assert SGM(ctx, cols=48, paired=False).cols == 48
    assert CBCA(ctx).path(3) == ctx.profile.cbca_path(3, SHORT_MAX)
    assert CBCA(ctx, fused=False).path(3) == "short"


@pytest.mark.parametrize("key, stage", [("pocl", SGM), ("llvmpipe", SGM), ("oclgrind", SGMWorkGroup),
                                        ("gpu", SGMWorkGroup)])
def test_sgm_stage_per_device(ctx, monkeypatch, key, stage):
    """make_sgm (StereoMatcher's SGM) by the profile: the line-walking SGM on
    CPUs, the work-group-per-line one on GPU-classed devices (Oclgrind too)."""
    monkeypatch.setattr(ctx, "profile", DeviceProfile.of(DEVICES[key], cl))
    for half in (False, True):
        st = make_sgm(ctx, half=half)
        assert type(st) is stage and st.half is half


def test_no_device_type_test_outside_the_profile():
    """The stages, the pipeline and the context make no device-dependent choice
    of their own: they live in mccnn_cl/opencl/device.py (device listing and
    selection by type in opencl/context.py and tools/gpucheck.py choose a device, not a kernel)."""
    pattern = re.compile(r"device_type\.|\.type\s*[&=]|is_rusticl|platform\.name\.lower|\"rusticl\"")
    found = []
    files = (sorted(PACKAGE.glob("stages/*.py")) + sorted(PACKAGE.glob("costs/*.py"))
             + [PACKAGE / "pipeline.py", PACKAGE / "opencl" / "context.py"])
    assert len(files) > 8
    for path in files:
        rel = path.relative_to(PACKAGE).as_posix()
        for no, line in enumerate(path.read_text().splitlines(), 1):
            if pattern.search(line):
                found.append(f"{rel}:{no}: {line.strip()}")
    assert not found, "\n".join(found)


def test_head_tile_follows_the_vector_registers():
    """CPUs without AVX-512 code get the head's RM at most NARROW_HEAD_RM (PoCL names the LLVM CPU
    it builds for); AVX-512 code keeps the rules' RM; a tuned RM wins either way; GPUs are untouched."""
    from mccnn_cl.opencl.device import NARROW_HEAD_RM, RULES
    wide = DeviceProfile.of(fake_device("pthread-skylake-avx512-AMD EPYC", T.CPU), cl)
    narrow = DeviceProfile.of(fake_device("pthread-haswell-AMD EPYC", T.CPU), cl)
    zen4 = DeviceProfile.of(fake_device("pthread-znver4-AMD EPYC 9654", T.CPU), cl)
    gpu = DeviceProfile.of(fake_device("NVIDIA H200", T.GPU), cl)
    assert wide.wide_vectors and zen4.wide_vectors and not narrow.wide_vectors
    assert not DeviceProfile.of(DEVICES["llvmpipe"], cl).wide_vectors  # 256-bit code
    assert wide.network_tiles()["RM"] == RULES["network_tiles"]["cpu"]["RM"] > NARROW_HEAD_RM
    assert narrow.network_tiles()["RM"] == NARROW_HEAD_RM
    assert narrow.network_tiles()["CONV_RM"] == RULES["network_tiles"]["cpu"]["CONV_RM"]
    assert gpu.network_tiles()["RM"] == RULES["network_tiles"]["gpu"]["RM"]
    narrow.tuned["network_tiles"] = {"RM": 8}
    assert narrow.network_tiles()["RM"] == 8
    # a device that reports 8-wide vectors (PoCL on a Zen 3) gets RN 8: RM 8 keeps to 8 registers
    zen3 = DeviceProfile.of(fake_device("pthread-haswell-AMD EPYC", T.CPU, width=8), cl)
    tiles = zen3.network_tiles()
    assert tiles["RN"] == 8 and tiles["RM"] == RULES["network_tiles"]["cpu"]["RM"] == 8
    assert tiles["CONV_RN"] == RULES["network_tiles"]["cpu"]["CONV_RN"] == 16  # the fst stack's own
    assert gpu.network_tiles()["CONV_RN"] == gpu.network_tiles()["RN"]  # no rule of its own: RN
