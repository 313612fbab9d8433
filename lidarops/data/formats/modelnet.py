"""ModelNet40 in the HDF5 form of the PointNet release: ``ply_data_{train,test}{0..}.h5`` with datasets
``data`` (float32[S, P, 3]) and ``label`` (uint8/int[S, 1]), plus ``shape_names.txt``."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lidarops.data._checks import finite_rows, read_text, require_file

__all__ = ["MODELNET40_CLASSES", "read_modelnet_h5", "write_modelnet_h5", "ModelNet40"]

#: The 40 ModelNet40 categories in label order.
MODELNET40_CLASSES = (
    "airplane", "bathtub", "bed", "bench", "bookshelf", "bottle", "bowl", "car", "chair", "cone", "cup", "curtain",
    "desk", "door", "dresser", "flower_pot", "glass_box", "guitar", "keyboard", "lamp", "laptop", "mantel", "monitor",
    "night_stand", "person", "piano", "plant", "radio", "range_hood", "sink", "sofa", "stairs", "stool", "table",
    "tent", "toilet", "tv_stand", "vase", "wardrobe", "xbox",
)


def _h5py():
    try:
        import h5py
    except ImportError as e:  # pragma: no cover
        raise ImportError("ModelNet40 HDF5 files need h5py: pip install 'lidarops[data]' or pip install h5py") from e
    return h5py


def read_modelnet_h5(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Reads one ModelNet40 HDF5 file.

    Args:
        path (str or Path): ``ply_data_*.h5``.

    Returns:
        points (ndarray float32[S, P, 3]), labels (ndarray int64[S]).

    Raises:
        FileNotFoundError: missing file.
        ValueError: not HDF5 (or a damaged one: h5py's errors are reported with the file name),
            missing ``data``/``label`` datasets, non-numeric, NaN or infinite values, labels that are
            not integers >= 0, or inconsistent shapes.
    """
    h5py = _h5py()
    path = require_file(path, "ModelNet40")
    # a damaged HDF5 file fails in h5py with OSError, KeyError or RuntimeError depending on the byte hit
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in ("data", "label") if k not in f]
            if missing:
                raise ValueError(f"{path}: missing HDF5 dataset(s) {missing} (found {sorted(f.keys())})")
            data, label = f["data"], f["label"]
            if not isinstance(data, h5py.Dataset) or not isinstance(label, h5py.Dataset):
                raise ValueError(f"{path}: 'data' and 'label' must be HDF5 datasets")
            if data.dtype.kind not in "fiu" or label.dtype.kind not in "iuf":
                raise ValueError(f"{path}: 'data' ({data.dtype}) and 'label' ({label.dtype}) must be numeric")
            if data.ndim != 3 or data.shape[2] < 3:
                raise ValueError(f"{path}: 'data' has shape {data.shape}, expected [shapes, points, 3]")
            if label.size != data.shape[0]:
                raise ValueError(f"{path}: {data.shape[0]} shapes but {label.size} labels")
            data = np.asarray(data[...], dtype=np.float64)[:, :, :3]
            label = np.asarray(label[...], dtype=np.float64).reshape(-1)
    except ValueError as e:
        if str(path) in str(e):
            raise
        raise ValueError(f"{path}: not a readable ModelNet40 HDF5 file ({e})") from None
    except (OSError, KeyError, RuntimeError, TypeError, IndexError, MemoryError) as e:
        raise ValueError(f"{path}: not a readable HDF5 file ({type(e).__name__}: {e})") from None
    finite_rows(data.reshape(data.shape[0], -1), path, "shape")
    if data.size and not np.abs(data).max() <= np.finfo(np.float32).max:
        raise ValueError(f"{path}: 'data' holds values beyond the float32 range")
    bad = np.flatnonzero(~((label >= 0) & (label == np.round(label)) & (label < 2**31)))
    if bad.size:
        raise ValueError(f"{path}: label {int(bad[0])} is {label[bad[0]]!r}; expected an integer class index >= 0")
    return data.astype(np.float32), label.astype(np.int64)


def write_modelnet_h5(path: str | Path, points: np.ndarray, labels: np.ndarray) -> Path:
    """Writes a ModelNet40-style HDF5 file (``data`` float32[S, P, 3], ``label`` uint8[S, 1])."""
    h5py = _h5py()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f.create_dataset("data", data=np.asarray(points, dtype=np.float32))
        f.create_dataset("label", data=np.asarray(labels).reshape(-1, 1).astype(np.uint8))
    return path


class ModelNet40:
    """ModelNet40 shapes from a directory of ``ply_data_<split>*.h5`` files or one file.

    Args:
        path (str or Path): directory or ``.h5`` file.
        split (str): ``"train"`` or ``"test"`` (when ``path`` is a directory).

    Attributes:
        points (ndarray float32[S, P, 3]), labels (ndarray int64[S]), class_names (tuple[str, ...]).

    Raises:
        FileNotFoundError: no matching files.
        ValueError: a file :func:`read_modelnet_h5` refuses, a ``shape_names.txt`` that is not UTF-8
            text, or a label without a class name (the file is named).
    """

    def __init__(self, path: str | Path, split: str = "train") -> None:
        path = Path(path)
        if path.is_dir():
            files = sorted(path.glob(f"ply_data_{split}*.h5"))
            if not files:
                raise FileNotFoundError(f"no ply_data_{split}*.h5 files in {path}")
            names_file = path / "shape_names.txt"
        elif path.is_file():
            files, names_file = [path], path.parent / "shape_names.txt"
        else:
            raise FileNotFoundError(f"ModelNet40 path not found: {path}")
        parts = [read_modelnet_h5(f) for f in files]
        self.points = np.concatenate([p for p, _ in parts])
        self.labels = np.concatenate([lab for _, lab in parts])
        self.files = files
        if names_file.is_file():
            self.class_names = tuple(n.strip() for n in read_text(names_file, "class name").splitlines() if n.strip())
            where = names_file
        else:
            self.class_names, where = MODELNET40_CLASSES, "ModelNet40's 40 classes"
        for f, (_, lab) in zip(files, parts):
            if lab.size and lab.max() >= len(self.class_names):
                raise ValueError(f"{f}: label {int(lab.max())} has no class name ({len(self.class_names)} in {where})")

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def __getitem__(self, i: int) -> tuple[np.ndarray, int]:
        """Shape ``i`` as (points float32[P, 3], label)."""
        return self.points[i], int(self.labels[i])

    def __repr__(self) -> str:
        return f"ModelNet40({len(self)} shapes from {len(self.files)} file(s))"
