"""Readers and writers of real dataset formats, and :func:`open_frames`, which turns a path (or a
scenario name) into a frame source.

===============  ==========================================  =================  ======
format           what                                         read               write
===============  ==========================================  =================  ======
KITTI object     ``velodyne/*.bin``, ``label_2``, ``calib``   :class:`KittiDataset`  yes
PandaSet         ``lidar/*.pkl.gz`` + poses, cuboids          :class:`PandaSetSequence`  yes
nuScenes         ``LIDAR_TOP/*.pcd.bin``                      :func:`read_nuscenes_bin`  yes (tests)
ModelNet40       ``ply_data_*.h5``                            :class:`ModelNet40`  yes (tests)
===============  ==========================================  =================  ======
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

from lidarops.data.formats.kitti import (
    KittiCalib,
    KittiDataset,
    KittiLabels,
    camera_to_lidar_boxes,
    forward_fov_mask,
    kitti_fov_mask,
    lidar_to_camera_boxes,
    read_calib,
    read_kitti_frame,
    read_label,
    read_velodyne,
    write_calib,
    write_image_sets,
    write_kitti_frame,
    write_label,
    write_velodyne,
)
from lidarops.data.formats.modelnet import MODELNET40_CLASSES, ModelNet40, read_modelnet_h5, write_modelnet_h5
from lidarops.data.formats.nuscenes import read_nuscenes_bin, write_nuscenes_bin
from lidarops.data.formats.pandaset import (
    PandaSetSequence,
    read_pandaset_frame,
    world_to_ego,
    write_pandaset_frame,
    write_pandaset_sequence,
)
from lidarops.data.frame import Frame

__all__ = [
    "KittiCalib", "KittiDataset", "KittiLabels", "camera_to_lidar_boxes", "lidar_to_camera_boxes", "kitti_fov_mask",
    "forward_fov_mask", "read_calib", "read_label", "read_velodyne", "read_kitti_frame", "write_calib", "write_label",
    "write_velodyne", "write_kitti_frame", "write_image_sets",
    "PandaSetSequence", "read_pandaset_frame", "write_pandaset_frame", "write_pandaset_sequence", "world_to_ego",
    "read_nuscenes_bin", "write_nuscenes_bin",
    "ModelNet40", "MODELNET40_CLASSES", "read_modelnet_h5", "write_modelnet_h5",
    "FileFrames", "ConcatFrames", "detect_format", "open_frames", "read_frame",
]


class FileFrames:
    """A frame source over a list of files read one at a time.

    Args:
        paths (sequence of Path): the files.
        reader (callable ``path -> Frame``): how to read one.
    """

    def __init__(self, paths: Sequence[Path], reader: Callable[[Path], Frame]) -> None:
        self.paths = [Path(p) for p in paths]
        self.reader = reader

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int) -> Frame:
        frame = self.reader(self.paths[i])
        frame.frame_index = i % len(self)
        return frame

    def __repr__(self) -> str:
        return f"FileFrames({len(self)} files)"


class ConcatFrames:
    """Several frame sources one after another."""

    def __init__(self, sources: Sequence) -> None:
        self.sources = list(sources)
        self._starts = []
        total = 0
        for s in self.sources:
            self._starts.append(total)
            total += len(s)
        self._len = total

    def __len__(self) -> int:
        return self._len

    def __getitem__(self, i: int) -> Frame:
        if not -self._len <= i < self._len:
            raise IndexError(f"frame {i} out of range ({self._len} frames)")
        i %= self._len
        k = max(j for j, start in enumerate(self._starts) if start <= i and len(self.sources[j]))
        return self.sources[k][i - self._starts[k]]

    def __repr__(self) -> str:
        return f"ConcatFrames({len(self.sources)} sources, {self._len} frames)"


def detect_format(path: str | Path) -> str:
    """Guesses the format of a path.

    Returns:
        One of ``"kitti"`` (a KITTI root or split directory), ``"kitti_bin"`` (one velodyne scan),
        ``"pandaset"`` (a sequence directory), ``"pandaset_root"`` (a directory of sequences),
        ``"pandaset_frame"`` (one ``.pkl.gz``), ``"nuscenes"`` (one ``.pcd.bin``), ``"nuscenes_dir"``
        (a directory of them), ``"modelnet"`` (an ``.h5`` file or a directory of ``ply_data_*.h5``).

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: the format is not recognised.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such file or directory: {path}")
    name = path.name
    if path.is_file():
        if name.endswith(".pcd.bin"):
            return "nuscenes"
        if name.endswith(".bin"):
            return "kitti_bin"
        if name.endswith(".pkl.gz"):
            return "pandaset_frame"
        if name.endswith((".h5", ".hdf5")):
            return "modelnet"
        raise ValueError(f"{path}: unrecognised file type (expected .bin, .pcd.bin, .pkl.gz or .h5)")
    if (path / "velodyne").is_dir() or any((path / s / "velodyne").is_dir() for s in ("training", "testing")) \
            or (path / "object" / "training" / "velodyne").is_dir():
        return "kitti"
    if (path / "lidar").is_dir() and any((path / "lidar").glob("*.pkl.gz")):
        return "pandaset"
    if any((p / "lidar").is_dir() for p in path.iterdir() if p.is_dir()):
        return "pandaset_root"
    if any(path.glob("*.pcd.bin")):
        return "nuscenes_dir"
    if any(path.glob("ply_data_*.h5")):
        return "modelnet"
    raise ValueError(f"{path}: not a KITTI, PandaSet, nuScenes or ModelNet40 directory")


def open_frames(spec: str | Path, **kwargs):
    """A frame source (``len`` + indexing to :class:`~lidarops.data.frame.Frame`) for a path or a
    synthetic scenario.

    Args:
        spec (str or Path): a dataset path (see :func:`detect_format`), or ``"synthetic:<scenario>"`` /
            a bare scenario name (``"driving_city"``...) for simulated frames.
        **kwargs: options of the underlying source (e.g. ``image_set="val"`` for KITTI,
            ``num_frames=10`` for synthetic).

    Returns:
        KittiDataset, PandaSetSequence, ConcatFrames, FileFrames or SyntheticFrames.

    Raises:
        FileNotFoundError, ValueError: unknown path or format.
    """
    from lidarops.data.scenarios import SCENARIOS

    text = str(spec)
    name = text[len("synthetic:"):] if text.startswith("synthetic:") else text
    if text.startswith("synthetic:") or (name in SCENARIOS and not Path(text).exists()):
        from lidarops.data.synthetic import SyntheticFrames

        return SyntheticFrames(name, **kwargs)
    path = Path(spec)
    kind = detect_format(path)
    if kind == "kitti":
        return KittiDataset(path, **kwargs)
    if kind == "kitti_bin":
        return FileFrames([path], lambda p: read_kitti_frame(p, **kwargs))
    if kind == "pandaset":
        return PandaSetSequence(path, **kwargs)
    if kind == "pandaset_root":
        return ConcatFrames([PandaSetSequence(p, **kwargs) for p in sorted(path.iterdir()) if (p / "lidar").is_dir()])
    if kind == "pandaset_frame":
        return FileFrames([path], lambda p: read_pandaset_frame(p, **kwargs))
    if kind == "nuscenes":
        return FileFrames([path], lambda p: read_nuscenes_bin(p, **kwargs))
    if kind == "nuscenes_dir":
        return FileFrames(sorted(path.glob("*.pcd.bin")), lambda p: read_nuscenes_bin(p, **kwargs))
    raise ValueError(f"{path}: {kind} data holds object shapes, not LiDAR frames (use ModelNet40 / ObjectDataset)")


def read_frame(spec: str | Path, index: int = 0, **kwargs) -> Frame:
    """Frame ``index`` of :func:`open_frames` ``(spec)``.

    Raises:
        IndexError: ``index`` out of range.
    """
    source = open_frames(spec, **kwargs)
    if not -len(source) <= index < len(source):
        raise IndexError(f"frame {index} out of range: {spec} has {len(source)} frame(s)")
    return source[index]
