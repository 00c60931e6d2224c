"""OpenCL pipeline stages: a small class per stage (compile in ``__init__``,
enqueue work in ``__call__``, device buffers in and out)."""
