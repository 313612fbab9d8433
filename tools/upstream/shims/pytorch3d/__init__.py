"""Shim: ``pytorch3d.ops`` resolves to lidarops' face (only the ops the face offers)."""
