"""A classification CAS-Net of ``device_session.sh classify`` as a shipped file: a ``CASNetPointNet`` holding the
sampler and the PointNet it was trained for, the training commands of both, the training set's recipe (from the
config's object set, checked against the cache key the device built) and its rows of ``classification_table.py``.

    python tools/casnet/ship_classification.py RUNS/cas_d8_fast.pth RUNS/pointnet_objects.pth \\
        lidarops/weights/casnet_pointnet_d8.pth --table casnet_classification.json --key 9ad8417de3e1 --commit abc1234
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    from lidarops.checkpoint import read_checkpoint
    from lidarops.config import load_config
    from lidarops.data.object_sets import datasets_from_config
    from lidarops.models.casnet import load_casnet
    from lidarops.models.casnet_pointnet import CASNetPointNet
    from lidarops.models.pointnet import PointNet

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("casnet", help="the CAS-Net (CASNet.save file of device_session.sh)")
    p.add_argument("pointnet", help="the PointNet it was trained for (lidarops.models.weights export)")
    p.add_argument("out")
    p.add_argument("--table", required=True, help="classification_table.py's JSON of the same runs")
    p.add_argument("--config", default=str(ROOT / "configs/casnet/pointnet_objects.yaml"))
    p.add_argument("--data", default=None, help="the object-set cache (default: the config's DATA_PATH; built when "
                                                "absent)")
    p.add_argument("--key", required=True, help="the object set's cache key the device built (objects_KEY.json)")
    p.add_argument("--commit", required=True, help="the commit the runs were made at")
    args = p.parse_args(argv)

    run = torch.load(args.casnet, map_location="cpu", weights_only=False)
    model = CASNetPointNet(dict(run["model_config_of_run"], task_checkpoint=None), load_task=False)
    model.casnet.load_state_dict(load_casnet(args.casnet).state_dict())
    task = PointNet.from_checkpoint(args.pointnet)
    model.task.load_state_dict(task.state_dict())
    if model.config.task != task.config.to_dict():
        raise SystemExit(f"the CAS-Net's run names another PointNet: {model.config.task} vs {task.config.to_dict()}")

    # the training set's own recipe, as a lidarops train run records it (the set is read from its cache)
    data_recipe = datasets_from_config(load_config(args.config), data_path=args.data)[0].recipe
    if data_recipe["key"] != args.key:
        raise SystemExit(f"{args.config} names the object set {data_recipe['key']}, the runs used {args.key}")

    table = json.loads(Path(args.table).read_text())
    ratio = model.config.ratio
    rows = [{k: r[k] for k in ("method", "accuracy", "mean_class_accuracy")}
            for r in table["rows"] if r["ratio"] == ratio]
    evaluation = {"protocol": f"classification_table.py: the {table['objects']:,} test objects of "
                              f"configs/casnet/pointnet_objects.yaml's object set, {table['num_points']:,} points "
                              f"each, {table['num_points'] // ratio} kept",
                  "device": table["device"], "commit": args.commit, "full_density": table["full_density"],
                  f"rows_d{ratio}": rows}
    model.save(args.out, train_command=run["train_command"],
               task_train_command=read_checkpoint(args.pointnet).get("train_command"), data_recipe=data_recipe,
               evaluation=evaluation, it=int(run["it"]))
    print(f"wrote {args.out} ({Path(args.out).stat().st_size:,} bytes): D = {ratio}, "
          + ", ".join(f"{r['method']} {r['accuracy']:.1f} %" for r in rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
