"""Shim: ``import torch_cluster`` resolves to lidarops' face, so upstream test files run unmodified.

``torch_cluster.testing`` (upstream's test helpers, not ours) is found in the fetched copy: the runner
puts ``$UPSTREAM_DIR/torch_cluster/torch_cluster`` on this package's search path.
"""
import os

from lidarops.compat.torch_cluster import fps, knn, knn_graph, radius, radius_graph  # noqa: F401

_fetched = os.path.join(os.environ.get("UPSTREAM_DIR", ""), "torch_cluster", "torch_cluster")
if os.path.isdir(_fetched):
    __path__.append(_fetched)  # noqa: F821 (a package's __path__)
