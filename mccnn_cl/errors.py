"""Exception types raised by mccnn_cl.

Every error a user can cause by what they pass in is an :class:`InputError`
(a ``ValueError``); problems with the OpenCL installation or a kernel are
:class:`OpenCLError` (a ``RuntimeError``).
"""


class MccnnError(Exception):
    """Base class of every exception raised on purpose by mccnn_cl."""


class InputError(MccnnError, ValueError):
    """Bad input: unreadable file, mismatched sizes, image too small, ..."""


class WeightsError(InputError):
    """A weights file that is missing, truncated or of another architecture."""


class OpenCLError(MccnnError, RuntimeError):
    """An OpenCL failure, wrapped with the stage that hit it."""


class NoOpenCLDeviceError(OpenCLError):
    """No OpenCL platform or no usable device was found."""


NO_PLATFORM_HELP = (
    "no OpenCL platform found. Install an OpenCL implementation, e.g. on "
    "Debian/Ubuntu `sudo apt-get install pocl-opencl-icd` (CPU), your GPU "
    "vendor's OpenCL driver, or Intel's CPU runtime `pip install "
    "intel-opencl-rt intel-cmplr-lib-rt`; then check with `mccnn-cl devices`. "
    "ICD files are read from /etc/OpenCL/vendors (or $OCL_ICD_VENDORS)."
)


class InputWarning(UserWarning):
    """Input that runs but is likely not what the caller meant (a swapped pair,
    12-bit data in a 16-bit image, ...); the message names the likely cause."""
