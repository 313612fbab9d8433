"""The ``--device`` of every command: checked before anything runs, so that a device the machine or the
build cannot serve is a one-line error (a ``ValueError``) rather than a traceback from the first op."""
from __future__ import annotations

__all__ = ["default_device", "resolve_device"]


def default_device() -> str:
    """``"cuda"`` when torch sees a GPU and lidarops was built with its CUDA kernels, else ``"cpu"``."""
    import torch

    from lidarops import extension

    return "cuda" if torch.cuda.is_available() and extension.cuda_available() else "cpu"


def resolve_device(device: "str | None", flag: str = "--device"):
    """The ``torch.device`` named by ``device`` (None or ``"auto"``: :func:`default_device`).

    Raises:
        ValueError: not a cpu or cuda device; CUDA asked for while torch sees none (or fewer than the
            index), or while lidarops lacks its CUDA kernels. The message names ``flag`` and the way out.
        lidarops.extension.LidaropsBuildError: the compiled library cannot be loaded.
    """
    import torch

    from lidarops import extension

    if device is None or device == "auto":
        return torch.device(default_device())
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        dev = None
    if dev is None or dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{flag} must be cpu or cuda, got {device!r}")
    if dev.type == "cpu":
        return dev
    if not torch.cuda.is_available():
        why = (f"this torch ({torch.__version__}) is built without CUDA" if torch.version.cuda is None
               else f"this torch ({torch.__version__}, CUDA {torch.version.cuda}) sees no CUDA device")
        raise ValueError(f"{flag} {device}: {why}; use {flag} cpu")
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"{flag} {device}: there are {torch.cuda.device_count()} CUDA devices")
    if not extension.cuda_available():
        reason = extension.build_info().get("cuda_reason", "a CPU-only build")
        raise ValueError(f"{flag} {device}: lidarops was built without its CUDA kernels ({reason}); rebuild it "
                         "with a CUDA toolkit (make build, or FORCE_CUDA=1 pip install --no-build-isolation -e .) "
                         f"or use {flag} cpu")
    return dev
