"""Semi-global matching laid out for GPUs - drives ``kernels/sgm_wg.cl``
(kernel ``sgm_wg_path``): the same C_SGM as :class:`mccnn_cl.stages.sgm.SGM`
(recurrence, penalties and their variants, validity: see that module), the
same call signature, another mapping onto the device.

:class:`SGM`'s kernels were shaped for CPUs: one work-item walks a whole row
or a strip of columns holding kilobytes of private state, and the paired
sweeps run two work-items.  On a GPU that spills registers and leaves most
of the device idle.  Here, as in the authors' CUDA code, one work-group
walks one path line (a row for the horizontal directions, a column for the
vertical ones) and its work-items share out the disparity levels (strides
of the work-group size, so any D); the previous pixel's C_r lives in local
memory, and its minimum over d is a tree reduction in local memory with
barriers (kernels/sgm_wg.cl).  Four launches, one per direction, H or W
work-groups each, accumulate into the output in SGM's order
(C_lr written, + C_rl, + C_tb, + C_bt and / 4) with the same float
operations per cell, so on a given device the results equal SGM's
one-direction kernels (``paired=False``) to the bit where the compilers
round alike, and to rounding in any case (tests/test_sgm_wg.py).

The work-group size is the kernel's own limit on the device
(``CL_KERNEL_WORK_GROUP_SIZE``) bounded by the levels rounded up to the
kernel's preferred multiple (a warp or wavefront on GPUs) and by the local
memory; ``local_size=`` forces one (tests run 1, 4, 16, 64 and the maximum
on CPU implementations, Oclgrind included, which checks the barriers).
No scratch buffer beyond local memory.
"""

from __future__ import annotations

import numpy as np

from ..opencl.context import launch, round_up
from ..errors import InputError
from .disparity import volume_bytes
from .sgm import check_call, penalty_table

#: The four launches (dx, dy, output mode), in SGM's accumulation order.
PASSES = ((1, 0, 0), (-1, 0, 1), (0, 1, 1), (0, -1, 2))
#: ``cols``: 0 (a work-group per column for the vertical paths, as for the rows) or
#: that many adjacent columns per work-group (kernel ``sgm_wg_cols``: a step's cells of
#: one level are adjacent in memory instead of a plane apart)
COLS_CHOICES = (0, 8, 16, 32)
#: work-items across the levels per ``sgm_wg_cols`` work-group, at most
COLS_MAX_SLICES = 32


def _pow2(n: int) -> int:
    """Smallest power of two >= n (n >= 1)."""
    return 1 << (int(n) - 1).bit_length()


class SGMWorkGroup:
    """C_SGM of a [D][H][W] cost volume by one work-group per path line; see
    the module docstring.  ``half=True``: volumes stored as half (as SGM).
    ``local_size``: the work-group size (default: chosen per D and device,
    :meth:`work_group_size`)."""

    #: For the memory planner (pipeline.py reads these from its SGM stage):
    #: no column strips, no paired sweeps, no scratch buffer.
    cols = None
    paired = False

    def __init__(self, ctx, half: bool = False, local_size=None, cols: int = 0):
        self.ctx = ctx
        self.half = bool(half)
        if local_size is not None and int(local_size) < 1:
            raise InputError(f"SGM work-group size must be >= 1, got {local_size}")
        self.local_size = None if local_size is None else int(local_size)
        if int(cols) not in COLS_CHOICES:
            raise InputError(f"SGM work-group columns must be one of {COLS_CHOICES}, got {cols}")
        self.wg_cols = int(cols)
        self._kernel = None
        self._cols_kernel = None

    def release_buffers(self):
        """Nothing to free: the work-group stage keeps no scratch between calls."""

    @staticmethod
    def scratch_bytes(D, W, *args, **kwargs) -> int:
        """Device memory besides the cost and output volumes: none (whatever
        configuration the planner passes, as to SGM.scratch_bytes)."""
        return 0

    def kernel(self):
        if self._kernel is None:
            self._kernel = self.ctx.kernel("sgm_wg.cl", "sgm_wg_path", VOL_HALF=int(self.half))
        return self._kernel

    def cols_kernel(self):
        if self._cols_kernel is None:
            self._cols_kernel = self.ctx.kernel("sgm_wg.cl", "sgm_wg_cols", VOL_HALF=int(self.half),
                                                SGM_WG_CW=self.wg_cols)
        return self._cols_kernel

    def cols_shape(self, D):
        """(columns, level slices) of a ``sgm_wg_cols`` work-group for D levels, or None
        where it does not fit (the kernel's work-group limit, the local memory)."""
        if not self.wg_cols:
            return None
        cw = self.wg_cols
        kmax = self.ctx.work_group_size(self.cols_kernel()) // cw
        K = max(1, min(kmax, COLS_MAX_SLICES, int(D)))
        while K > 1 and 4 * cw * (2 * (int(D) + 2) + 2 * K) > self.ctx.local_mem:
            K //= 2
        if kmax < 1 or 4 * cw * (2 * (int(D) + 2) + 2 * K) > self.ctx.local_mem:
            return None
        return cw, K

    def _local_bytes(self, D, L) -> int:
        return 4 * (2 * (int(D) + 2) + 2 * _pow2(L))

    def work_group_size(self, D) -> int:
        """The work-group size used for D levels (see the module docstring)."""
        cl, kern = self.ctx.cl, self.kernel()
        kmax = self.ctx.work_group_size(kern)
        if self.local_size is not None:
            if self.local_size > kmax:
                raise InputError(f"SGM work-group size {self.local_size} exceeds this kernel's maximum {kmax} "
                                 f"on {self.ctx.describe()}")
            L = self.local_size
        else:
            pref = int(kern.get_work_group_info(cl.kernel_work_group_info.PREFERRED_WORK_GROUP_SIZE_MULTIPLE,
                                                self.ctx.device))
            L = max(1, min(kmax, round_up(int(D), max(1, pref))))
            while L > 1 and self._local_bytes(D, L) > self.ctx.local_mem:
                L //= 2
        if self._local_bytes(D, L) > self.ctx.local_mem:
            raise InputError(f"SGM at D = {D} with work-groups of {L} needs {self._local_bytes(D, L)} bytes of "
                             f"local memory, more than the {self.ctx.local_mem} of {self.ctx.describe()}")
        return L

    #: calls refuse ``mirror=True`` (SGM.reads_mirrored): the pipeline mirrors the volume itself
    reads_mirrored = False

    def __call__(self, d_cost, d_img_left, d_img_right, D, H, W, pi1=1.0, pi2=32.0, tau_so=0.0625,
                 q1=4.0, q2=10.0, v=2.0, variant="paper", p2_times_pi1=False, outside_large=True,
                 out=None, mirror=False, cost_bound=None):
        """Enqueue the four directions; returns ``out`` (allocated when None,
        must not be ``d_cost``) holding C_SGM, NaN where invalid.  ``mirror``:
        as SGM's, refused here.  ``cost_bound`` (SGM's 16-bit sweeps): ignored,
        the work-group paths run in float."""
        D, H, W = check_call(d_cost, D, H, W, out, mirror, self.reads_mirrored)
        pen = {False: penalty_table(pi1, pi2, q1, q2, v, False, variant, p2_times_pi1),
               True: penalty_table(pi1, pi2, q1, q2, v, True, variant, p2_times_pi1)}
        if out is None:
            out = self.ctx.empty(volume_bytes(self.half) * D * H * W, "SGM output volume")
        L = self.work_group_size(D)
        pw = _pow2(L)
        cl, kern = self.ctx.cl, self.kernel()
        local_path, local_red = cl.LocalMemory(4 * 2 * (D + 2)), cl.LocalMemory(4 * 2 * pw)
        shape = self.cols_shape(D)
        for dx, dy, mode in PASSES:
            lines = H if dx else W
            (p1s, p2s) = pen[dy != 0]
            if dy and shape is not None:  # the vertical paths, adjacent columns per work-group
                cw, K = shape
                launch(self.ctx, "SGM (columns per work-group)", self.cols_kernel(), (round_up(W, cw), K),
                       d_cost, d_img_left, d_img_right, out, cl.LocalMemory(4 * 2 * (D + 2) * cw),
                       cl.LocalMemory(4 * 2 * K * cw), np.int32(D), np.int32(H), np.int32(W), np.int32(dy),
                       *p1s, *p2s, np.float32(tau_so), np.int32(bool(outside_large)), np.int32(mode),
                       local_size=(cw, K))
                continue
            launch(self.ctx, "SGM (work-group per line)", kern, (lines * L,), d_cost, d_img_left, d_img_right,
                   out, local_path, local_red, np.int32(pw), np.int32(D), np.int32(H), np.int32(W),
                   np.int32(dx), np.int32(dy), *p1s, *p2s, np.float32(tau_so), np.int32(bool(outside_large)),
                   np.int32(mode), local_size=(L,))
        return out
