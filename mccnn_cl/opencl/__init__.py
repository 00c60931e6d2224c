"""The OpenCL side: the context (device choice, program cache, launches,
buffers: :mod:`.context`) and the device profile (what the stages need to
know about a device, and the rules that pick kernel paths: :mod:`.device`)."""

from .context import BufferPool, ClContext, launch, list_devices, round_up, select_device  # noqa: F401
from .device import DeviceProfile  # noqa: F401
