"""Classification metrics: overall accuracy, mean class accuracy and the confusion matrix (PointNet's and
SampleNet's "eval accuracy" and "eval avg class acc"), and :class:`ClassificationEvaluator`, the
:class:`lidarops.train.Evaluator` of :class:`~lidarops.models.pointnet.PointNet` runs.

::

    evaluator = ClassificationEvaluator(model.config.class_names)
    fit(model, train_set, collate_classification, config, "runs/pn", val_dataset=test_set, evaluator=evaluator)
    metrics, text = evaluator(predictions, frames)     # or by hand: one dict per object, in dataset order

Accuracies are percentages. The mean class accuracy averages the classes that have test objects (a class
absent from the test set has no accuracy; it is left out and the report says so).
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["confusion_matrix", "classification_metrics", "format_report", "ClassificationEvaluator"]


def confusion_matrix(predicted: Sequence[int] | np.ndarray, target: Sequence[int] | np.ndarray,
                     num_classes: int) -> np.ndarray:
    """``int64[K, K]``: row = the true class, column = the predicted class.

    Raises:
        ValueError: lengths differ, or a class id outside ``[0, num_classes)`` (naming the argument).
    """
    p = np.asarray(predicted, dtype=np.int64).reshape(-1)
    t = np.asarray(target, dtype=np.int64).reshape(-1)
    if p.shape != t.shape:
        raise ValueError(f"predicted and target must have one entry per object, got {p.size} and {t.size}")
    for name, v in (("predicted", p), ("target", t)):
        bad = (v < 0) | (v >= num_classes)
        if bad.any():
            raise ValueError(f"{name} holds class id {int(v[bad][0])} outside [0, {num_classes})")
    return np.bincount(t * num_classes + p, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def classification_metrics(confusion: np.ndarray, class_names: Sequence[str]) -> dict[str, float]:
    """``accuracy`` (overall, %), ``mean_class_accuracy`` (%, over the classes with objects),
    ``accuracy_<class>`` (%, classes with objects only) and ``num_objects``, from a confusion matrix."""
    confusion = np.asarray(confusion, dtype=np.int64)
    total = int(confusion.sum())
    metrics: dict[str, float] = {}
    if total:
        per_class = confusion.sum(axis=1)
        present = per_class > 0
        recall = np.diag(confusion)[present] / per_class[present]
        metrics["accuracy"] = 100.0 * float(np.trace(confusion)) / total
        metrics["mean_class_accuracy"] = 100.0 * float(recall.mean())
        for name, r in zip(np.asarray(class_names)[present], recall):
            metrics[f"accuracy_{name}"] = 100.0 * float(r)
    metrics["num_objects"] = float(total)
    return metrics


def format_report(confusion: np.ndarray, class_names: Sequence[str]) -> str:
    """The metrics and the confusion matrix as text (rows: true class, columns: predicted)."""
    confusion = np.asarray(confusion, dtype=np.int64)
    m = classification_metrics(confusion, class_names)
    if not m["num_objects"]:
        return "classification: no objects to score"
    lines = [f"classification of {int(m['num_objects'])} objects: overall accuracy {m['accuracy']:.2f} %, "
             f"mean class accuracy {m['mean_class_accuracy']:.2f} %"]
    absent = [n for n, c in zip(class_names, confusion.sum(axis=1)) if c == 0]
    if absent:
        lines.append(f"  (no test objects of {', '.join(absent)}: left out of the mean)")
    width = max(6, *(len(n) for n in class_names))
    corner = "true \\ predicted"
    lines.append(f"{corner:>{width + 9}} " + " ".join(f"{n[:7]:>7}" for n in class_names))
    for k, name in enumerate(class_names):
        n = int(confusion[k].sum())
        acc = f"{100.0 * confusion[k, k] / n:6.1f} %" if n else "      - "
        lines.append(f"{name:>{width}} {acc} " + " ".join(f"{int(v):7d}" for v in confusion[k]) + f"   ({n})")
    return "\n".join(lines)


class ClassificationEvaluator:
    """``evaluator(predictions, frames) -> (metrics, text)`` for :func:`lidarops.train.fit`.

    Args:
        class_names (sequence of str): the classes, in label order (the model's ``config.class_names``).
        label_key (str): the per-object metadata key holding the true class id (what
            :func:`lidarops.data.object_sets.collate_classification` puts in ``gt_label``).

    ``predictions`` are :meth:`PointNet.postprocess` dicts (``label``: the predicted class id); ``frames`` the
    per-object metadata in the same order. After a call, ``confusion`` holds the last confusion matrix.
    """

    def __init__(self, class_names: Sequence[str], label_key: str = "gt_label") -> None:
        if isinstance(class_names, str) or not class_names or not all(isinstance(n, str) for n in class_names):
            raise ValueError(f"class_names must be a non-empty list of names, got {class_names!r}")
        self.class_names = tuple(class_names)
        self.label_key = label_key
        self.confusion: np.ndarray | None = None

    def __call__(self, predictions: Sequence[Mapping[str, Any]],
                 frames: Sequence[Mapping[str, Any]]) -> tuple[dict[str, float], str]:
        if len(predictions) != len(frames):
            raise ValueError(f"predictions and frames must have one entry per object, got {len(predictions)} and "
                             f"{len(frames)}")
        predicted, target = [], []
        for i, (p, f) in enumerate(zip(predictions, frames)):
            if "label" not in p:
                raise ValueError(f"predictions[{i}] has no 'label' (keys {sorted(p)})")
            if self.label_key not in f:
                raise ValueError(f"frames[{i}] has no {self.label_key!r}: batch the objects with "
                                 "collate_classification, which lists each object's true class")
            predicted.append(int(p["label"]))
            target.append(int(f[self.label_key]))
        self.confusion = confusion_matrix(predicted, target, len(self.class_names))
        return classification_metrics(self.confusion, self.class_names), format_report(self.confusion, self.class_names)
