"""Shim: ``mmcv`` with only ``mmcv.ops`` (lidarops' face) and the device flags mmcv's tests read."""
