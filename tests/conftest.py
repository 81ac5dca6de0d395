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


# The files that take longest (``python -m pytest --durations=70``, summed per file: about
# 240, 190, 170, 160, 100 and 90 s of one core), started first: with one file per worker
# (``--dist loadfile``) a long file started last leaves the other worker idle until it ends.
# ``--no-loadscope-reorder`` (pyproject) keeps this order instead of xdist's by test count.
SLOWEST_FIRST = ("test_zoomwide.py", "test_digital_zoom.py", "test_diagnose_render.py",
                 "test_calibration_mc.py", "test_diagnose.py", "test_calibrate_cli.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: else as found
