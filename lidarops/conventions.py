"""The conventions every floor of lidarops shares, defined once (see CONTRIBUTING.md).

- **Boxes** are ``(x, y, z, dx, dy, dz, heading)`` in the LiDAR frame (x forward, y left, z up), ``z`` the
  box centre, ``heading`` the rotation about z from +x in radians (OpenPCDet's convention); with a class it
  is an 8th column (:data:`BOX_FIELDS`).
- **Class labels** a model or an evaluator meets are 1-based into the model's ``class_names`` (0 is
  padding or background, OpenPCDet's ``gt_boxes[..., 7]`` and ``pred_labels``). Records of the data
  floor (``Frame.labels``) index their own ``class_names`` from 0, with -1 for unknown classes;
  classification targets (an object set's labels) are 0-based as ``torch.nn.CrossEntropyLoss`` wants.
- **Grids** are named by OpenPCDet's keys: ``point_cloud_range`` ``(x0, y0, z0, x1, y1, z1)`` and
  ``voxel_size`` ``(vx, vy, vz)`` (a pillar's ``vz`` is the range's z extent). Cell coordinates list
  the axes in reverse, batch first where there is one: ``(batch, z, y, x)`` for voxels (OpenPCDet's
  ``voxel_coords``), ``(batch, y, x)`` for pillars on a 2D grid (spconv's 2D indices), and
  ``(z, y, x)`` for one frame's :func:`lidarops.voxelize`.
- **Seeds**: the simulator's frames are functions of (scenario, seed, index). The shipped models were
  trained on seeds below :data:`HELD_OUT_SEED`; every command that simulates frames to score or show
  defaults to it, so a documented flow never scores a model on its own training frames.
"""
from __future__ import annotations

__all__ = ["KITTI_CLASSES", "BOX_FIELDS", "BACKGROUND_LABEL", "HELD_OUT_SEED"]

#: The classes of KITTI's object benchmark, in OpenPCDet's order: the default of every detector and evaluator.
KITTI_CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")

#: The columns of a box (``gt_boxes`` adds the 1-based class id as an 8th).
BOX_FIELDS: tuple[str, ...] = ("x", "y", "z", "dx", "dy", "dz", "heading")

#: The label of padding rows and background anchors (class ids start at 1).
BACKGROUND_LABEL = 0

#: The default seed of ``lidarops data synth``, ``detect --scenario`` and ``data show``: no shipped model
#: was trained on it (their recipes use seeds 0 and 1000; ``data synth`` gives scenario k the seed
#: ``--seed + 1000 k``, so 5000, 6000, ... stay clear of them).
HELD_OUT_SEED = 5000
