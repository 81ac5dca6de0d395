import os
import zlib

import cv2
import numpy as np
import pytest

from zoomcalib.optics.prescription import load_prescription


@pytest.fixture(scope="session", autouse=True)
def one_thread_per_worker():
    # With one pytest-xdist worker per core, BLAS and OpenCV threads of their own only
    # oversubscribe the cores.
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        yield
        return
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)
    with threadpool_limits(1):
        yield


@pytest.fixture(scope="session")
def laikin():
    return load_prescription("laikin-10x")


@pytest.fixture(scope="session")
def nikon():
    return load_prescription("nikon-80-200")


@pytest.fixture
def rng(request):
    # A generator seeded from the test's name: reproducible, different per test.
    return np.random.default_rng(zlib.crc32(request.node.name.encode()))
