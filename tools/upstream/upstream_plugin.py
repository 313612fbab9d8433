"""pytest plugin for tools/upstream/run.sh: on a machine without CUDA, skip the upstream tests that need it.

mmcv's and torch_cluster's tests skip themselves (markers, device lists). PyTorch3D's have no markers
(upstream runs them on GPU machines): a test that needs CUDA calls ``get_random_cuda_device()`` in its
body, so without CUDA such a test is skipped here instead of failing on ``cuda:0``.
"""
import inspect

import pytest
import torch


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs CUDA (calls get_random_cuda_device)")
    for item in items:
        try:
            source = inspect.getsource(item.obj)
        except (AttributeError, OSError, TypeError):
            continue
        if "get_random_cuda_device()" in source:
            item.add_marker(skip)
