"""Shim: ``pytorch3d.ops``' neighbour ops resolve to lidarops' face (only the ops the face offers).

Besides the face, the PyTorch3D test files import a few things that are not ops of the face:
upstream's pure-PyTorch modules run unchanged from the fetched copy (``pytorch3d.ops.utils``, and
``sample_farthest_points_naive``, see ``ops/__init__.py``); modules here stand in only for upstream
modules that need compiled PyTorch3D (``_C``, ``io``, ``utils``, ``ops.sample_points_from_meshes``).
"""
