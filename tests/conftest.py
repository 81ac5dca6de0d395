import zlib

import numpy as np
import pytest

from zoomcalib.optics.prescription import load_prescription


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
