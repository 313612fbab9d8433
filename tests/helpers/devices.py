"""The devices the tests run on: ``cpu`` always; ``cuda`` when torch sees a GPU and lidarops was built with
its CUDA kernels. When torch sees a GPU but lidarops has no CUDA kernels the cuda cases are skipped with a
reason, unless ``LIDAROPS_TEST_REQUIRE_CUDA=1`` (then they run and fail loudly)."""
from __future__ import annotations

import os

import pytest
import torch


def _lidarops_cuda_kernels() -> tuple[bool, str]:
    try:
        from lidarops import extension

        return extension.cuda_available(), extension.build_info().get("cuda_reason", "")
    except Exception as e:  # a broken build fails the op tests loudly; here we only pick devices
        return False, f"lidarops failed to load: {e}"


CUDA_VISIBLE = torch.cuda.is_available()
LIDAROPS_CUDA, _CUDA_REASON = _lidarops_cuda_kernels() if CUDA_VISIBLE else (False, "no GPU visible")
REQUIRE_CUDA = os.environ.get("LIDAROPS_TEST_REQUIRE_CUDA", "0") == "1"


def _device_params() -> list:
    params = [pytest.param("cpu", id="cpu")]
    if CUDA_VISIBLE:
        if LIDAROPS_CUDA or REQUIRE_CUDA:
            params.append(pytest.param("cuda", id="cuda"))
        else:
            params.append(pytest.param("cuda", id="cuda", marks=pytest.mark.skip(
                reason=f"torch sees a GPU but lidarops has no CUDA kernels ({_CUDA_REASON})")))
    return params


#: ``pytest.param`` per device (the root ``device`` fixture runs over them)
DEVICES = _device_params()
#: the cuda cases run (a GPU, and lidarops' CUDA kernels or LIDAROPS_TEST_REQUIRE_CUDA=1)
CUDA_OK = any(p.values[0] == "cuda" and not p.marks for p in DEVICES)
requires_cuda = pytest.mark.skipif(not CUDA_OK, reason="needs a GPU and lidarops built with CUDA kernels")
