"""What the stages need to know about an OpenCL device: :class:`DeviceProfile`.

A profile is made once per :class:`~mccnn_cl.opencl.context.ClContext` (``ctx.profile``)
from the device's queries, plus facts no query reports, *declared* here for
the devices known to need them: Mesa's llvmpipe (Rusticl's CPU device) ends
every loop of a work-item once that work-item has taken 65535 loop
iterations in all (``loop_limit``; docs/portability.md), and compiles some
kernels for minutes (``slow_compiler``).  Every device-dependent choice of a
stage is a row of :data:`RULES`, whose columns are the device classes:

* ``cpu``: a device whose type is exactly CPU (PoCL, Intel's CPU runtime):
  few, fast work-items that walk whole lines, host prefetch instructions;
* ``llvmpipe``: a CPU behind Rusticl with the loop limit and the slow
  compiler: the CPU's kernels where they fit the limit;
* ``gpu``: everything else (GPUs, accelerators, and Oclgrind, which reports
  every device type at once: it simulates a generic device).

Stages ask the profile (:meth:`DeviceProfile.sgm_options`,
:meth:`~DeviceProfile.cbca_path`, :meth:`~DeviceProfile.network_tiles`,
:meth:`~DeviceProfile.local_tile`, :meth:`~DeviceProfile.line_group`) and
test no device type themselves; a new kernel variant is a new row, a new
kind of device a new column.
"""

from __future__ import annotations

from dataclasses import dataclass, field

CPU, LLVMPIPE, GPU = "cpu", "llvmpipe", "gpu"
CLASSES = (CPU, LLVMPIPE, GPU)

#: llvmpipe's loop iterations per work-item (gallivm's LP_MAX_TGSI_LOOP_ITERATIONS,
#: Mesa 22.3), after which every loop of the work-item ends silently.
LLVMPIPE_LOOP_LIMIT = 65535

#: option -> {device class: value}.  ``sgm_stage``: SGM's implementation
#: (:func:`~mccnn_cl.stages.sgm_select.make_sgm`): "lines" (:class:`~mccnn_cl.stages.sgm.SGM`,
#: a work-item walks whole path lines) or "workgroup" (:class:`~mccnn_cl.stages.sgm_wg.SGMWorkGroup`,
#: a work-group per line; Oclgrind takes it too).  SGM's one-direction kernels: ``sgm_prefetch``
#: (host prefetch instructions where the kernel is compiled to x86/AArch64),
#: ``sgm_cols`` (columns per sgm_columns work-item), ``sgm_fused_rows`` (both
#: row directions in one pass; never under a loop limit), ``sgm_specialize``
#: and ``sgm_whole_tiles`` (faster code, longer compiles), ``sgm_group_of_one``
#: (work-groups of 1, else the kernel's preferred multiple); the paired sweeps
#: (``sgm_paired_max_units``: taken on devices with at most this many compute
#: units; two work-items per launch); ``sgm_width``: sgm.cl's vectors, 16 or 8 floats (SGM_VW;
#: 8 on CPUs by measurement on both CPU classes at hand, the same bits at either width: the
#: paired sweeps took 189-210 ms against 214-240 ms a KITTI-sized volume at 16 on a Zen 3
#: (AVX2), 133-140 against 143-155 ms on a Zen 4 (AVX-512, whose 16-float vectors PoCL uses
#: elsewhere)); ``sgm_mirror_reads``: the right reference's SGM reads the volume mirrored where
#: the stage can (the paired sweeps), else the volume is mirrored in place, there and back
#: (the same bits; None on CPUs: where the float vector width is 16 or more,
#: :meth:`DeviceProfile.sgm_mirror_reads`; PoCL with 16-wide vectors: reading mirrored saves the
#: two passes, 216 against 183 + 2 x 30 ms a KITTI-sized volume; with 8-wide ones, a Zen 3, the
#: passes were the faster; Intel's CPU runtime compiles the mirrored loads into slower code: 390
#: against 184-212 ms for a plain call, so there its tuner keeps the passes); ``sgm_wg_cols``: the work-group stage's vertical
#: paths with that many adjacent columns per work-group (0: one column per work-group,
#: as its rows; :class:`~mccnn_cl.stages.sgm_wg.SGMWorkGroup`); ``sgm_disp_floor``: the least
#: MAX_DISP sgm.cl is compiled for (D rounded up to a power of two, at least this; it sizes
#: private arrays only, the loops run over D): 256 on CPUs, so that every D up to 256 shares the
#: program ``mccnn-cl tune`` stores (a D 73 pair built a program of 4 s after a D 228 one), the
#: paired sweeps' time level (Zen 3, PoCL, medians of 10-20 alternating rounds: D 73 on 496 x 718
#: 69.5 ms at MAX_DISP 128 against 69.3 at 256, D 100 87.3 / 85.4 ms, D 16 9.0 / 9.1 ms, D 40 37.2
#: at 64 against 39.3 ms, faster in 5 of 20); 64 elsewhere (llvmpipe's loop limits are
#: estimated from MAX_DISP; on GPUs private arrays cost registers or spills); ``sgm_int16``: the
#: paired sweeps in 16-bit lanes (sgm_paired_q16) where a call asks for them (the
#: ``sgm_int16`` hyperparameter; written for Clang-based CPU compilers: Mesa's llvmpipe aborted
#: building it; on GPUs the work-group stage runs anyway).  CBCA: ``cbca_workgroup`` (the GPU-shaped
#: two passes of kernels/cbca_wg.cl, a work-group per row or column tile and
#: disparity; before the fused rules), ``cbca_fused`` (both passes in one
#: launch, one work-item per plane walking it whole), ``cbca_multi`` (several
#: iterations per launch, the same), ``cbca_multi_group_of_one``.  Network:
#: ``network_tiles`` (register tiles; the head's RN grows with the float vector width on CPUs;
#: CONV_RM 4 pixels x CONV_RN 16 channels per conv work-item of the fst stack: 4 accumulator
#: registers of AVX-512, 8 of AVX2, whose 16 registers CONV_RM 8 overflowed: the fst conv stack
#: took 2.63 s against 1.44-1.49 s at 4 with PoCL's AVX2 code, 1.18 against 1.21 s with its
#: AVX-512 code; on a Zen 3, whose PoCL device reports a float vector width of 8, one KITTI
#: image's stack took 0.56 s at CONV_RN 16 against 1.03 s at RN 8, BENCHMARKS.md; the paper
#: and acrt stacks keep RN, which their heads share; ``mccnn-cl tune`` measures CONV_RM 4, 6
#: and 8 and CONV_RN 8);
#: ``network_winograd`` (the conv stack's 3 x 3 layers by Winograd's F(2x2, 3x3),
#: kernels/network_conv_wino.cl: (RT tiles, XA products) per work-item, XA 0 = 4 where the
#: kernels get 16-float vectors (:attr:`DeviceProfile.wide_vectors`), else 1; None: the
#: direct GEMM; CPU devices only (~32 KiB of local memory a work-group): a 64 -> 64 layer of
#: general-fst on a KITTI-sized map took 101 against 158 ms at (4, 4) with AVX-512 code, 113
#: against 168 ms at (4, 1) with AVX2 code, BENCHMARKS.md);
#: ``network_local_tiles`` (the conv stack and the L4 split as a local-memory tiled
#: GEMM, kernels/network_conv_wg.cl) with its starting tile ``network_gemm_tile``
#: (TM pixels x TN channels per work-group, TK terms per slice, RM x RN per
#: work-item); ``network_head_gemm`` (the paper/acrt head layer by layer, each
#: hidden layer that GEMM as a 1 x 1 convolution, kernels/network_head_wg.cl,
#: instead of fused per tile of cells); ``fst_workgroup`` (fst's cosine volume with a work-group per
#: (column tile, disparity chunk, row), kernels/fst_wg.cl) with ``fst_volume_tile``
#: (TX columns x TD disparities, TK maps per slice, RX x RD per work-item);
#: ``fst_volume_width``: the pairs form's vector width (fst_volume_pairs built with
#: FST_VW 16 or 8), 0 = the device's float vector width (16 where it is 16, else 8:
#: PoCL on a Zen 3 reports 8, and its 16 float16 accumulators spilled there).  The
#: tiles are the same in every column (they are what a forced run starts from) and
#: shrink to the kernel's CL_KERNEL_WORK_GROUP_SIZE and the local memory.
#: ``census_cost_launch``: (levels per census_cost work-item, 0 = all D; its
#: work-group size, None = the runtime's), kernels/census.cl.  ``wta_chunks``: 16-pixel
#: chunks per work-item of the left WTA (disparity_wta_left's WTA_CHUNKS; more chunks read
#: adjacent lines of a plane per step, one is the most work-items, for GPUs).  ``mirror_lines``:
#: the right-reference volume's in-place mirroring with a work-item per (d, y) line
#: (disparity_right_volume's MIRROR_LINES), else per 16-pair block (the most work-items, for GPUs).
RULES = {
    "sgm_stage":               {CPU: "lines", LLVMPIPE: "lines", GPU: "workgroup"},
    "sgm_prefetch":            {CPU: True,  LLVMPIPE: True,  GPU: False},
    "sgm_cols":                {CPU: 128,   LLVMPIPE: 32,    GPU: 32},
    "sgm_fused_rows":          {CPU: True,  LLVMPIPE: True,  GPU: False},
    "sgm_specialize":          {CPU: True,  LLVMPIPE: False, GPU: True},
    "sgm_whole_tiles":         {CPU: True,  LLVMPIPE: False, GPU: True},
    "sgm_group_of_one":        {CPU: True,  LLVMPIPE: True,  GPU: False},
    "sgm_paired_max_units":    {CPU: 2,     LLVMPIPE: 0,     GPU: 0},
    "sgm_wg_cols":             {CPU: 0,     LLVMPIPE: 0,     GPU: 0},
    "sgm_disp_floor":          {CPU: 256,   LLVMPIPE: 64,    GPU: 64},
    "sgm_width":               {CPU: 8,     LLVMPIPE: 16,    GPU: 16},
    "sgm_mirror_reads":        {CPU: None,  LLVMPIPE: True,  GPU: True},
    "sgm_int16":               {CPU: True,  LLVMPIPE: False, GPU: False},
    "cbca_workgroup":          {CPU: False, LLVMPIPE: False, GPU: True},
    "cbca_fused":              {CPU: True,  LLVMPIPE: False, GPU: False},
    "cbca_multi":              {CPU: True,  LLVMPIPE: True,  GPU: False},
    "cbca_multi_group_of_one": {CPU: True,  LLVMPIPE: True,  GPU: False},
    "network_tiles":           {CPU: dict(TM=64, RM=8, ROWS_FASTEST=1, CONV_RM=4, CONV_RN=16),
                                LLVMPIPE: dict(TM=64, RM=8, ROWS_FASTEST=1, CONV_RM=4),
                                GPU: dict(TM=32, RM=4, RN=4, ROWS_FASTEST=0, CONV_RM=4)},
    "network_local_tiles":     {CPU: False, LLVMPIPE: False, GPU: True},
    "network_head_gemm":       {CPU: False, LLVMPIPE: False, GPU: True},
    "network_winograd":        {CPU: (4, 0), LLVMPIPE: None, GPU: None},
    "network_gemm_tile":       {c: dict(TM=64, TN=64, TK=16, RM=4, RN=4) for c in (CPU, LLVMPIPE, GPU)},
    "fst_workgroup":           {CPU: False, LLVMPIPE: False, GPU: True},
    "fst_volume_tile":         {c: dict(TX=64, TD=64, TK=16, RX=4, RD=4) for c in (CPU, LLVMPIPE, GPU)},
    "fst_volume_width":        {CPU: 0, LLVMPIPE: 0, GPU: 16},
    "launch_local":            {CPU: (64, 2, 2), LLVMPIPE: (64, 2, 2), GPU: None},
    "wta_chunks":              {CPU: 8, LLVMPIPE: 8, GPU: 1},
    "mirror_lines":            {CPU: True, LLVMPIPE: True, GPU: False},
    "census_cost_launch":      {CPU: (0, (16, 1, 1)), LLVMPIPE: (0, (16, 1, 1)), GPU: (1, None)},
}

#: The head's RM (cells per work-item, x RN 16 channels of accumulators) on CPUs without 32 wide
#: vector registers: the paper network's head on a 400 x 200 pair at D 64 took 22.3 s at RM 8 and
#: 16.8 s at 4 with PoCL's AVX2 code, 12.2 and 13.4 s with its AVX-512 code (BENCHMARKS.md).
#: Where the device reports a float vector width of 8 (RN 8: PoCL on a Zen 3) RM 8 keeps to 8
#: registers and stays: the tuner's head run took 1.46 s there against 2.20 s at RM 4.
NARROW_HEAD_RM = 4
#: LLVM CPU names (as PoCL puts them in its device names) whose code has AVX-512
AVX512_LLVM_CPUS = ("avx512", "cascadelake", "cooperlake", "cannonlake", "icelake", "tigerlake", "rocketlake",
                    "sapphirerapids", "emeraldrapids", "graniterapids", "znver4", "znver5", "x86-64-v4", "knl",
                    "knm")

#: Declared facts per class: (loop_limit or None, slow_compiler).
DECLARED = {CPU: (None, False), LLVMPIPE: (LLVMPIPE_LOOP_LIMIT, True), GPU: (None, False)}


def type_name(device, cl) -> str:
    """"GPU", "ACCELERATOR", "CPU" or "OTHER" for a pyopencl device (GPU bit first)."""
    t = int(device.type)
    for name in ("GPU", "ACCELERATOR", "CPU"):
        if t & int(getattr(cl.device_type, name)):
            return name
    return "OTHER"


def device_class(device, cl) -> str:
    """The :data:`RULES` column of a pyopencl device (module docstring)."""
    if int(device.type) != int(cl.device_type.CPU):
        return GPU
    return LLVMPIPE if "llvmpipe" in device.name.lower() else CPU


@dataclass(frozen=True)
class DeviceProfile:
    """One device's facts and the rules that turn them into kernel choices."""

    name: str
    platform: str
    kind: str               # the RULES column: "cpu" | "llvmpipe" | "gpu"
    compute_units: int
    global_mem: int
    local_mem: int
    max_alloc: int
    max_work_group: int
    vector_width: int       # float vector width (max of preferred and native)
    loop_limit: int | None  # declared: loop iterations per work-item, None = no limit
    slow_compiler: bool     # declared: some kernels take minutes to build
    #: RULES rows chosen by measurement on this device (mccnn_cl.tune), which
    #: :meth:`rule` returns instead of the column's value
    tuned: dict = field(default_factory=dict, compare=False)

    @classmethod
    def of(cls, device, cl) -> "DeviceProfile":
        kind = device_class(device, cl)
        loop_limit, slow = DECLARED[kind]
        width = max(int(device.preferred_vector_width_float), int(device.native_vector_width_float), 1)
        return cls(device.name.strip(), device.platform.name.strip(), kind, int(device.max_compute_units),
                   int(device.global_mem_size), int(device.local_mem_size), int(device.max_mem_alloc_size),
                   int(device.max_work_group_size), width, loop_limit, slow)

    @property
    def launch_local(self):
        """Work-group sizes per dimension of the launches whose stage leaves
        them open (:func:`mccnn_cl.opencl.context.launch_sizes`), or None: the runtime's."""
        value = self.rule("launch_local")
        return tuple(value) if value else None

    def rule(self, option: str):
        """This device's value of one :data:`RULES` row: the tuned one
        (:mod:`mccnn_cl.tune`) when there is one, else the column's; a tuned
        tile row (a dict) holds only the sizes tuned, over the column's."""
        base = RULES[option][self.kind]
        if option not in self.tuned:
            return base
        value = self.tuned[option]
        if isinstance(value, dict) and isinstance(base, dict):  # a tile row: the tuned sizes over the rules'
            return {**base, **value}
        return value

    def rule_source(self, option: str) -> str:
        """"tuned" or "rules": where :meth:`rule`'s value of ``option`` comes from."""
        return "tuned" if option in self.tuned else "rules"

    @property
    def is_cpu(self) -> bool:
        """The device runs the CPU-shaped kernels (the ``cpu`` and ``llvmpipe`` columns)."""
        return self.kind in (CPU, LLVMPIPE)

    def sgm_options(self, loop_limit=None) -> dict:
        """Defaults of :class:`~mccnn_cl.stages.sgm.SGM`'s options; ``loop_limit``
        (0: none) overrides the declared one."""
        limit = self.loop_limit if loop_limit is None else (int(loop_limit) or None)
        return dict(loop_limit=limit, prefetch=self.rule("sgm_prefetch"), cols=self.rule("sgm_cols"),
                    fused_rows=self.rule("sgm_fused_rows") and limit is None,
                    specialize=self.rule("sgm_specialize"), whole_tiles=self.rule("sgm_whole_tiles"),
                    paired=self.compute_units <= self.rule("sgm_paired_max_units"),
                    group_of_one=self.rule("sgm_group_of_one"), width=self.sgm_width(),
                    mirror_reads=self.sgm_mirror_reads(), int16=bool(self.rule("sgm_int16")),
                    # under a loop limit the bands are sized from MAX_DISP: the limited column's floor
                    disp_floor=int(self.rule("sgm_disp_floor") if limit is None else RULES["sgm_disp_floor"][LLVMPIPE]))

    def sgm_mirror_reads(self) -> bool:
        """Whether the right reference's SGM reads the volume mirrored (rule ``sgm_mirror_reads``;
        None: where the device's float vector width is 16 or more).  With 8-wide vectors (PoCL on
        a Zen 3) each mirrored tile row is an 8-float load and permute at a cell offset that moves
        a level at a time, and mirroring the volume in place there and back was the faster:
        ``mccnn-cl tune`` 113 against 132 ms (the faster in 4 of 5 rounds), the census pipeline
        on a KITTI pair 2.05 against 2.22 s (medians of 12 alternating rounds, 9 of 12 faster);
        with 16-wide vectors the mirrored reads save the two passes (BENCHMARKS.md)."""
        v = self.rule("sgm_mirror_reads")
        return bool(v) if v is not None else self.vector_width >= 16

    def sgm_width(self) -> int:
        """Lanes of sgm.cl's vectors (rule ``sgm_width``, 16 or 8)."""
        return int(self.rule("sgm_width"))

    def cbca_path(self, max_arm: int, short_max: int, short=True, fused=None, multi=None, workgroup=None) -> str:
        """CBCA's kernel path for arms of at most ``max_arm``: "workgroup"
        (cbca_rows_wg / cbca_columns_wg), "multi" (cbca_fused_multi_short),
        "fused" (cbca_fused_short), "short" (the two short-arm passes) or
        "running" (the running-sum passes, any arm).  ``short``/``fused``/
        ``multi``/``workgroup`` False exclude a path, ``workgroup=True`` takes
        it (None: the rules; the work-group rule only when neither ``fused``
        nor ``multi`` is given)."""
        if not short or max_arm > short_max:
            return "running"
        if workgroup is None:
            workgroup = self.rule("cbca_workgroup") and fused is None and multi is None
        if workgroup:
            return "workgroup"
        if not (self.rule("cbca_fused") if fused is None else fused):
            return "short"
        return "multi" if (self.rule("cbca_multi") if multi is None else multi) else "fused"

    def network_tiles(self) -> dict:
        """Starting register tiles of the network kernels (refined against the kernel limits by the costs).
        On a CPU without 32 wide vector registers (:attr:`wide_vectors`) and RN 16 the head's RM is
        at most :data:`NARROW_HEAD_RM` unless tuned: its RM x 16 accumulators overflow AVX2's 16
        registers.  ``CONV_RN`` (the fst conv stack's channels per work-item) defaults to RN."""
        tiles = dict(self.rule("network_tiles"))
        if "RN" not in tiles:
            tiles["RN"] = 16 if self.vector_width >= 16 else 8 if self.vector_width >= 8 else 4
        tiles.setdefault("CONV_RN", tiles["RN"])
        if (self.is_cpu and not self.wide_vectors and int(tiles["RN"]) >= 16
                and "RM" not in self.tuned.get("network_tiles", {})):
            tiles["RM"] = min(int(tiles["RM"]), NARROW_HEAD_RM)
        return tiles

    def value(self, option: str):
        """A :data:`RULES` row's value as the stages take it: :meth:`rule`, with the rows whose
        value depends on the device resolved (``fst_volume_width``, ``network_winograd``,
        ``network_tiles``, ``sgm_mirror_reads``: their methods)."""
        resolved = {"fst_volume_width": self.fst_volume_width, "network_winograd": self.winograd,
                    "network_tiles": self.network_tiles, "sgm_mirror_reads": self.sgm_mirror_reads}.get(option)
        return resolved() if resolved is not None else self.rule(option)

    def winograd(self):
        """The conv stack's Winograd block (RT, XA) (rule ``network_winograd``; XA 0: 4 on
        :attr:`wide_vectors` devices, else 1), or None for the direct GEMM."""
        v = self.rule("network_winograd")
        if not v:
            return None
        rt, xa = (int(a) for a in v)
        return rt, xa if xa else (4 if self.wide_vectors else 1)

    def fst_volume_width(self) -> int:
        """fst's pairs-form volume kernel's vector width (rule ``fst_volume_width``; 0: 16 where the
        device's float vector width is 16 or more, else 8)."""
        vw = int(self.rule("fst_volume_width"))
        return vw if vw else (16 if self.vector_width >= 16 else 8)

    @property
    def wide_vectors(self) -> bool:
        """A CPU whose kernels get AVX-512 code (32 registers of 16 floats). PoCL names its CPU
        device after the LLVM CPU it builds for (``pthread-skylake-avx512-...``,
        ``pthread-haswell-...`` on a Zen 3 or with ``POCL_KERNELLIB_NAME=avx2``); other CPU
        runtimes build for the host, whose flags say."""
        name = self.name.lower()
        if name.startswith(("pthread-", "cpu-", "basic-")):
            return any(k in name for k in AVX512_LLVM_CPUS)
        if "llvmpipe" in name:  # "llvmpipe (LLVM 15.0.6, 256 bits)": its vector width
            return "512 bits" in name
        try:
            with open("/proc/cpuinfo") as f:
                return any(line.startswith("flags") and " avx512f" in line for line in f)
        except OSError:
            return False

    def local_tile(self, path_rule: str, tile_rule: str, choice=None):
        """A GPU-shaped path's tile, or None when the path is not taken:
        ``choice`` None follows ``path_rule`` (True: the ``tile_rule`` row's
        sizes), False excludes the path, True takes it with those sizes, a
        dict takes it with those sizes updated by the dict.  Returns
        ``(sizes, forced)``: forced (a dict was given) sizes are checked
        against the kernel's limits, the others shrink to fit them."""
        if choice is None:
            choice = bool(self.rule(path_rule))
        if choice is False:
            return None
        sizes = dict(self.rule(tile_rule))
        if choice is True:
            return sizes, False
        unknown = set(choice) - set(sizes)
        if unknown:
            from ..errors import InputError

            raise InputError(f"unknown {tile_rule} keys {sorted(unknown)} (known: {sorted(sizes)})")
        sizes.update({k: int(v) for k, v in choice.items()})
        return sizes, True

    def line_group(self, ctx, kernel, group_of_one: bool = False) -> int:
        """Work-group size of a line-walking kernel (CBCA, SGM): 1 when
        ``group_of_one`` (CPUs: one work-item per thread spreads the lines
        evenly over the cores), else the kernel's preferred work-group size
        multiple capped by its maximum.  These kernels keep kilobytes of
        private arrays per work-item, and CPU runtimes (PoCL) may lay a whole
        work-group's private memory on one thread's stack, so the runtime's
        own choice (up to thousands of work-items) could overflow it."""
        if group_of_one:
            return 1
        cl = ctx.cl
        pref = int(kernel.get_work_group_info(cl.kernel_work_group_info.PREFERRED_WORK_GROUP_SIZE_MULTIPLE,
                                              ctx.device))
        return max(1, min(pref, ctx.work_group_size(kernel)))
