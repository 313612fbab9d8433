"""Stand-in for compiled PyTorch3D (``pytorch3d._C``), which is not installed.

Upstream modules that import ``_C`` at the top then load, so their pure-PyTorch functions can run
(``ops/sample_farthest_points.py``'s ``sample_farthest_points_naive``); every compiled function is
missing: ``_C.name`` raises AttributeError and ``from pytorch3d._C import name`` ImportError, as in a
PyTorch3D build without that function.
"""


def __getattr__(name):
    raise AttributeError(f"pytorch3d._C.{name}: compiled PyTorch3D is not installed (the shims run lidarops' face)")
