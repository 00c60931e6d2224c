"""Plain numpy references of every pipeline stage, written for clarity.

They are the executable specification the OpenCL kernels are tested
against: ``network`` (the CNN patch by patch), ``aggregation`` (cross arms,
cross-based cost aggregation, semi-global matching) and ``disparity``
(winner-take-all, left-right check, interpolation, subpixel, refinement,
census cost) and ``confidence`` (the per-pixel confidence measure).
"""
