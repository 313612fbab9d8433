"""Root fixtures of the suite: ``device``, ``dtype`` and ``one_thread``. The shared helpers (devices, dtype
tables and tolerances, clouds, comparisons, test data) are the package ``helpers`` (tests/helpers/).

``tests/`` is not a package and its folders are (``ops``, ``sparse``, ...: test files of one name may live in
two folders); pytest puts ``tests/`` on ``sys.path``, so test files import ``from helpers.<module> import ...``.

Devices: ``cpu`` always; ``cuda`` when torch sees a GPU and lidarops was built with its CUDA kernels
(:mod:`helpers.devices`; ``LIDAROPS_TEST_REQUIRE_CUDA=1`` runs the cuda cases even without them).
"""
from __future__ import annotations

import os
import threading
import time

import pytest
import torch

from helpers.devices import DEVICES
from helpers.dtypes import DTYPE_IDS, FLOAT_DTYPES



def _share_the_cores() -> None:
    """Under pytest-xdist (``make test`` runs ``-n 2``) each worker takes its share of the cores, and so do
    the processes it starts: two workers of two threads each on two cores would wait on each other."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        threads = max(1, (os.cpu_count() or 1) // workers)
        torch.set_num_threads(threads)
        os.environ.setdefault("OMP_NUM_THREADS", str(threads))


_share_the_cores()


def _xdist_controller(config) -> bool:
    return not hasattr(config, "workerinput") and (getattr(config.option, "numprocesses", None) or 0) > 0


def pytest_collection_modifyitems(config, items):
    """Under xdist, the tests marked slow first: the workers start on them while the short ones fill the
    gaps, instead of one worker finishing a minutes-long test alone at the end (a stable sort: every
    worker collects the same order)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        items.sort(key=lambda item: 0 if item.get_closest_marker("slow") else 1)


class _Heartbeat:
    """Under xdist the workers' own output is not shown, so a test running for minutes would leave the
    terminal silent: after ``SILENCE`` seconds without a finished test the controller names what runs."""

    SILENCE = 45.0

    def __init__(self, config):
        self.config = config
        self.running: dict[str, float] = {}
        self.last = time.monotonic()
        self.lock = threading.Lock()
        self.done = threading.Event()
        threading.Thread(target=self._watch, daemon=True).start()

    def pytest_runtest_logstart(self, nodeid, location):
        with self.lock:
            self.running[nodeid] = time.monotonic()

    def pytest_runtest_logfinish(self, nodeid, location):
        with self.lock:
            self.running.pop(nodeid, None)
            self.last = time.monotonic()

    def pytest_sessionfinish(self):
        self.done.set()

    def _watch(self):
        while not self.done.wait(5.0):
            now = time.monotonic()
            with self.lock:
                if now - self.last < self.SILENCE or not self.running:
                    continue
                self.last = now
                lines = [f"{nodeid} ({now - start:.0f} s)" for nodeid, start in sorted(self.running.items())]
            reporter = self.config.pluginmanager.get_plugin("terminalreporter")  # registered after conftests
            if reporter is not None:
                reporter.write("\n    still running: " + "; ".join(lines) + "\n", flush=True)


def pytest_configure(config):
    if _xdist_controller(config) and config.getoption("verbose") > -2:  # -qq silences it
        config.pluginmanager.register(_Heartbeat(config), "lidarops-heartbeat")


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
