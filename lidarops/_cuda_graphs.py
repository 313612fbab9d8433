"""What every CUDA graph lidarops records shares (the predict and index graphs, SSCATeR's backbone and detect
graphs): the rule for autocast during the warm-up and the capture, and the padded capacities graphs are recorded
for."""
from __future__ import annotations

import contextlib

import torch

__all__ = ["graph_capacity", "record_graph", "uncached_autocast"]


def graph_capacity(n: int, least: int) -> int:
    """The power of two at least ``n`` and ``least``: inputs are padded to it, one graph per capacity."""
    return max(least, 1 << max(n - 1, 0).bit_length())


@contextlib.contextmanager
def uncached_autocast(device_type: str = "cuda"):
    """The autocast in force (if any) with its cache of cast weights off, for a CUDA graph's warm-up and capture: a
    cast cached by the warm-up would be read by the graph as it is, and freed when the outermost autocast ends
    (torch's rule for graphs under autocast)."""
    if not torch.is_autocast_enabled(device_type):
        yield
        return
    with torch.autocast(device_type, dtype=torch.get_autocast_dtype(device_type), cache_enabled=False):
        yield


def record_graph(fn, device, *, warmups: int = 1, pool=None, capture_error_mode: str = "global"):
    """Run ``fn`` ``warmups`` times on a side stream (cuDNN picks its algorithms, the allocator settles its blocks,
    lazy state is made: torch's rule before a capture), then capture it on ``device``; returns the graph and the
    outputs of the captured call. The caller's contexts (no_grad, autocast, validation) hold for both."""
    with torch.cuda.device(device):
        side, current = torch.cuda.Stream(), torch.cuda.current_stream()
        side.wait_stream(current)
        with torch.cuda.stream(side):
            for _ in range(warmups):
                fn()
        current.wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=pool, capture_error_mode=capture_error_mode):
            outputs = fn()
    return graph, outputs
