"""Make a folder written by ``lidarops data synth --format kitti`` readable by OpenPCDet's KittiDataset,
then run OpenPCDet's own ``create_kitti_infos`` (its infos and ground-truth database).

    python tools/upstream/openpcdet/prepare_kitti.py .peers/OpenPCDet DATA [--faces] [--workers N]

OpenPCDet reads each frame's image size from ``training/image_2/<id>.png`` and needs ``ImageSets/test.txt``;
the simulator writes neither (lidarops assumes KITTI's 1242 x 375 image without reading one). This adds
black 1242 x 375 PNGs (a few hundred bytes each: only their size is read) and an empty test split.
Road planes are not written: train with ``USE_ROAD_PLANE: False`` (``--set`` in OpenPCDet's train.py).
``--faces``: lidarops.compat.pcdet serves the ops the info and database steps call (points_in_boxes_cpu).
"""
from __future__ import annotations

import argparse
import os
import struct
import sys
import time
import zlib
from pathlib import Path


def black_png(width: int, height: int) -> bytes:
    """A grayscale PNG of zeros (the PNG format by hand: no imaging library needed)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    raw = b"".join(b"\x00" + bytes(width) for _ in range(height))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("openpcdet", type=Path)
    p.add_argument("data", type=Path, help="KITTI root written by lidarops data synth (training/, ImageSets/)")
    p.add_argument("--faces", action="store_true")
    p.add_argument("--workers", type=int, default=8)
    args = p.parse_args()
    src, data = args.openpcdet.resolve(), args.data.resolve()
    ids = sorted(f.stem for f in (data / "training/velodyne").glob("*.bin"))
    (data / "training/image_2").mkdir(exist_ok=True)
    png = black_png(1242, 375)
    for i in ids:
        (data / "training/image_2" / f"{i}.png").write_bytes(png)
    (data / "ImageSets/test.txt").write_text("")
    sys.path.insert(0, str(src))
    if args.faces:
        import lidarops.compat.pcdet

        lidarops.compat.pcdet.install()
    import yaml
    from easydict import EasyDict

    from pcdet.datasets.kitti import kitti_dataset

    # kitti_dataset.py imports Path only under `if __name__ == "__main__"` (its command-line entry point)
    kitti_dataset.Path = Path
    cfg = EasyDict(yaml.safe_load((src / "tools/cfgs/dataset_configs/kitti_dataset.yaml").read_text()))
    t0 = time.time()
    os.chdir(data)
    kitti_dataset.create_kitti_infos(dataset_cfg=cfg, class_names=["Car", "Pedestrian", "Cyclist"], data_path=data,
                                     save_path=data, workers=args.workers)
    print(f"OpenPCDet infos and gt database for {len(ids)} frames in {time.time() - t0:.0f} s "
          f"({'lidarops faces' if args.faces else 'its own ops'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
