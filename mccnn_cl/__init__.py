"""mccnn_cl: MC-CNN stereo matching with OpenCL inference.

Žbontar & LeCun, "Computing the Stereo Matching Cost with a Convolutional
Neural Network" (CVPR 2015).  The network is trained with PyTorch
(:mod:`mccnn_cl.train`); inference runs as OpenCL kernels through PyOpenCL.
"""

from ._version import __version__  # noqa: F401

from .errors import (  # noqa: F401
    MccnnError,
    InputWarning,
    InputError,
    WeightsError,
    OpenCLError,
    NoOpenCLDeviceError,
)
from .pipeline import Hyperparameters, StereoMatcher  # noqa: F401,E402
