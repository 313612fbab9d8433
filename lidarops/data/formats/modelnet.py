"""ModelNet40 in the HDF5 form of the PointNet release: ``ply_data_{train,test}{0..}.h5`` with datasets
``data`` (float32[S, P, 3]) and ``label`` (uint8/int[S, 1]), plus ``shape_names.txt``."""
from __future__ import annotations

from pathlib import Path

import numpy as np

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
        ValueError: not HDF5, missing ``data``/``label`` datasets, or inconsistent shapes.
    """
    h5py = _h5py()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ModelNet40 file not found: {path}")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"{path}: not a readable HDF5 file ({e})") from None
    with f:
        missing = [k for k in ("data", "label") if k not in f]
        if missing:
            raise ValueError(f"{path}: missing HDF5 dataset(s) {missing} (found {sorted(f.keys())})")
        data = np.asarray(f["data"][...], dtype=np.float32)
        label = np.asarray(f["label"][...]).reshape(-1).astype(np.int64)
    if data.ndim != 3 or data.shape[2] < 3:
        raise ValueError(f"{path}: 'data' has shape {data.shape}, expected [shapes, points, 3]")
    if label.shape[0] != data.shape[0]:
        raise ValueError(f"{path}: {data.shape[0]} shapes but {label.shape[0]} labels")
    return data[:, :, :3], label


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
            self.class_names = tuple(n.strip() for n in names_file.read_text().splitlines() if n.strip())
        else:
            self.class_names = MODELNET40_CLASSES

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def __getitem__(self, i: int) -> tuple[np.ndarray, int]:
        """Shape ``i`` as (points float32[P, 3], label)."""
        return self.points[i], int(self.labels[i])

    def __repr__(self) -> str:
        return f"ModelNet40({len(self)} shapes from {len(self.files)} file(s))"
