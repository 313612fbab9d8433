"""A detection CAS-Net of ``device_session.sh detect`` as a shipped file: the sampler with distinct picks, the
detector it was trained for, its training command and data, and its rows of ``detection_table.py`` (the
simulated held-out frames and, optionally, the real frames of ``benchmarks/bm_sim2real.py``'s yardstick).

    python tools/casnet/ship_detection.py RUN.pth lidarops/weights/NAME.pth --table casnet_detection.json \\
        [--real-table real.json] --train-data "lidarops data synth ..." --session "REALISM=kitti ... detect"
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

KEYS = ("mAP_3d_moderate_R40", "mAP_3d_moderate_R11", "mAP_bev_moderate_R40", "3d_moderate_R40", "points_kept_mean",
        "distinct_kept_mean", "sample_ms_median")


def rows_of(table: dict, ratio: int, stem: str) -> dict:
    """The table's rows at ``ratio`` for every points, random, FPS and the CAS-Net whose file is ``stem``."""
    out = {}
    for row in table["rows"]:
        if row["ratio"] == 1:
            out["all_points"] = row
        elif row["ratio"] == ratio and row["method"] in ("random", "fps"):
            out[row["method"]] = row
        elif row["ratio"] == ratio and row.get("checkpoint") and Path(row["checkpoint"]).stem == stem:
            out["casnet_whole_cloud"] = row
    if "casnet_whole_cloud" not in out:
        raise SystemExit(f"no row of a CAS-Net file named {stem} at D = {ratio} in the table")
    return {k: {key: v[key] for key in KEYS if key in v} for k, v in out.items()}


def main(argv=None) -> int:
    from lidarops.models.casnet import load_casnet

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src", help="CASNet.save file or training checkpoint of device_session.sh detect")
    p.add_argument("dst")
    p.add_argument("--table", required=True, help="detection_table.py's JSON on the simulated held-out frames")
    p.add_argument("--real-table", help="detection_table.py's JSON on real frames")
    p.add_argument("--stem", help="the CAS-Net's file name in the tables (default: src's)")
    p.add_argument("--train-data", required=True, help="the data synth command of the training frames")
    p.add_argument("--session", required=True, help="the device_session.sh command that trained it")
    p.add_argument("--commit", required=True, help="the commit the training ran at")
    args = p.parse_args(argv)
    ck = torch.load(args.src, map_location="cpu", weights_only=False)
    model = load_casnet(args.src)
    model.dedup = True  # the shipped samplers keep distinct points, as the tables measured them
    run = ck.get("model_config_of_run") or {}
    ratio = ck.get("ratio") or run.get("ratio")
    if not ratio:
        raise SystemExit(f"{args.src} records no sampling ratio (model_config_of_run['ratio'])")
    stem = args.stem or Path(args.src).stem
    table = json.loads(Path(args.table).read_text())
    evaluation = {"protocol": f"tools/casnet/detection_table.py, {table['frames']} frames of {table['data']}, "
                              f"{table['detector']} behind each sampler keeping n // {ratio} points, moderate KITTI "
                              f"mAP over Car, Pedestrian, Cyclist",
                  "device": table["device"], "command": table["command"], **rows_of(table, ratio, stem)}
    if args.real_table:
        real = json.loads(Path(args.real_table).read_text())
        evaluation["real_frames"] = {"protocol": f"the same on {real['frames']} real KITTI frames ({real['data']})",
                                     "device": real["device"], "command": real["command"],
                                     **rows_of(real, ratio, stem)}
    name = Path(args.dst).stem
    model.save(args.dst, task=ck["task"], ratio=int(ratio), model_config_of_run=run or None,
               train_command=ck.get("train_command"),
               data_recipe={"train_data": args.train_data, "session": args.session, "steps": ck.get("it"),
                            "commit": args.commit},
               evaluation=evaluation, it=ck.get("it"),
               usage=f"CASNetSampler(load_casnet('{name}'), whole=True)(points, n // {ratio})")
    print(f"{args.dst}: {Path(args.dst).stat().st_size:,} bytes, task {ck['task']}, D = {ratio}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
