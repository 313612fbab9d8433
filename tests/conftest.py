"""Root fixtures of the suite: ``device``, ``dtype`` and ``one_thread``. The shared helpers (devices, dtype
tables and tolerances, clouds, comparisons, test data) are the package ``helpers`` (tests/helpers/).

``tests/`` is not a package and its folders are (``ops``, ``sparse``, ...: test files of one name may live in
two folders); pytest puts ``tests/`` on ``sys.path``, so test files import ``from helpers.<module> import ...``.

Devices: ``cpu`` always; ``cuda`` when torch sees a GPU and lidarops was built with its CUDA kernels
(:mod:`helpers.devices`; ``LIDAROPS_TEST_REQUIRE_CUDA=1`` runs the cuda cases even without them).
"""
from __future__ import annotations

import pytest
import torch

from helpers.devices import DEVICES
from helpers.dtypes import DTYPE_IDS, FLOAT_DTYPES


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


@pytest.fixture(params=FLOAT_DTYPES, ids=lambda d: DTYPE_IDS[d])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture
def one_thread():
    """Run the test with one intra-op thread (restored after): for tests of tiny tensors, where
    OpenMP wake-ups on a shared machine cost more than the work."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
