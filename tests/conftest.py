"""Shared pytest fixtures.

``--cl-device SPEC`` (or ``$MCCNN_CL_DEVICE``) chooses the OpenCL device for
the whole run (see :func:`mccnn_cl.cl.select_device`); default: the package's
own preference.  A missing OpenCL platform is a test *failure*, never a skip.
"""

import os
from pathlib import Path

import numpy as np
import pytest

from mccnn_cl.cl import ClContext

REPO = Path(__file__).resolve().parents[1]

# Value written into output buffers before a launch: no kernel ever writes it
# (it is neither a cost, a disparity nor the NaN marking invalid cells), so an
# element left unwritten makes the comparison fail.
POISON = np.float32(-1.2345e30)


def pytest_addoption(parser):
    parser.addoption("--cl-device", default=os.environ.get("MCCNN_CL_DEVICE"),
                     help="OpenCL device spec for the tests (see mccnn_cl.cl.select_device)")


@pytest.fixture(scope="session")
def ctx(request):
    """One ClContext for the whole session."""
    c = ClContext(request.config.getoption("--cl-device"))
    print(f"\nOpenCL device under test: {c.describe()}")
    yield c
    c.close()


@pytest.fixture(scope="session")
def shared_data():
    """Path of ../shared/data (or $MCCNN_SHARED_DATA); missing data fails loudly."""
    p = Path(os.environ.get("MCCNN_SHARED_DATA", REPO.parent / "shared" / "data"))
    if not p.is_dir():
        pytest.fail(f"real test data not found at {p}; set MCCNN_SHARED_DATA")
    return p
