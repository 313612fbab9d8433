"""What the trainer asks of a model and of an evaluator."""
from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from torch import Tensor

__all__ = ["TrainableModel", "Evaluator"]


@runtime_checkable
class TrainableModel(Protocol):
    """A ``torch.nn.Module`` the trainer can fit and evaluate (PointPillars, CounterNet, CAS-Net ...).

    In ``model.train()`` mode, ``model(batch)`` returns ``{"loss": Tensor[], **terms}``: ``loss`` is the
    scalar to minimise, already a mean over the frames of the batch (so that DDP's gradient averaging over
    ranks equals one process on the whole global batch); other scalar tensors (``loss_cls``, ``loss_box``,
    ``loss_dir`` ...) are logged. Non-scalar values are ignored.

    In ``model.eval()`` mode, ``raw = model(batch)`` and ``model.postprocess(raw, batch)`` returns one dict
    of tensors per frame (``boxes (K, 7)``, ``scores (K,)``, ``labels (K,)`` ...), which the trainer hands
    to the evaluator without reading them.

    ``batch`` is what the collate function returns: a dict whose tensors (also inside lists, tuples and
    dicts) the trainer has moved to the device; other values pass through.

    Optionally, ``model.config`` with ``to_dict()`` (and ``class_names``): the trainer then records the
    model's class, config and classes in every checkpoint, so :func:`lidarops.models.load_model` can rebuild
    it from the file alone.
    """

    training: bool

    def __call__(self, batch: dict[str, Any]) -> Any: ...

    def postprocess(self, raw: Any, batch: dict[str, Any]) -> list[dict[str, Tensor]]: ...


class Evaluator(Protocol):
    """``evaluator(predictions, frames) -> (metrics, text)`` on rank 0, after each evaluation.

    Args:
        predictions: one dict per validation frame, in dataset order, tensors on the CPU.
        frames: per-frame metadata in the same order: the batch's list-valued keys split by frame
            (``frame_id``, ``annos``, ``calib`` ..., whatever the collate function put in lists).

    Returns:
        metrics (dict[str, float]): written to ``eval_epoch_{e}.json`` and TensorBoard.
        text (str): a human-readable report, printed and written to ``train.log``.
    """

    def __call__(self, predictions: list[dict[str, Tensor]],
                 frames: list[dict[str, Any]]) -> tuple[dict[str, float], str]: ...
