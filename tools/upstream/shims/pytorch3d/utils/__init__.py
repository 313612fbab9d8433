"""Shim: ``ico_sphere`` for test_ball_query.py's CUDA test (its point clouds are sampled from one).

Upstream's ``utils/ico_sphere.py`` builds a ``pytorch3d.structures.Meshes`` (whose package also loads
``Volumes`` and ``transforms``) with ``SubdivideMeshes``, and ``pytorch3d.utils`` imports the renderer,
which needs compiled PyTorch3D. This builds the same sphere (upstream's level-0 icosahedron, each level
splitting every face in four at its edge midpoints, vertices projected to the unit sphere) as a batch
with the three ``Meshes`` methods the tests and the sampling shim call.
"""
import torch

_ico_verts0 = [
    [-0.5257, 0.8507, 0.0000], [0.5257, 0.8507, 0.0000], [-0.5257, -0.8507, 0.0000],
    [0.5257, -0.8507, 0.0000], [0.0000, -0.5257, 0.8507], [0.0000, 0.5257, 0.8507],
    [0.0000, -0.5257, -0.8507], [0.0000, 0.5257, -0.8507], [0.8507, 0.0000, -0.5257],
    [0.8507, 0.0000, 0.5257], [-0.8507, 0.0000, -0.5257], [-0.8507, 0.0000, 0.5257],
]
_ico_faces0 = [
    [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
    [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
    [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
]


class _Meshes:
    """A batch of equal meshes: ``verts (N, V, 3)``, ``faces (N, F, 3)``."""

    def __init__(self, verts: torch.Tensor, faces: torch.Tensor):
        self._verts, self._faces = verts, faces

    def verts_padded(self) -> torch.Tensor:
        return self._verts

    def faces_padded(self) -> torch.Tensor:
        return self._faces

    def extend(self, N: int) -> "_Meshes":
        return _Meshes(self._verts.repeat(N, 1, 1), self._faces.repeat(N, 1, 1))


def ico_sphere(level: int = 0, device=None) -> _Meshes:
    if level < 0:
        raise ValueError("level must be >= 0.")
    verts = torch.tensor(_ico_verts0, dtype=torch.float32)
    faces = torch.tensor(_ico_faces0, dtype=torch.int64)
    for _ in range(level):
        a, b, c = faces.unbind(1)
        edges = torch.cat([torch.stack(e, 1) for e in ((a, b), (b, c), (c, a))]).sort(dim=1).values
        unique, inverse = torch.unique(edges, dim=0, return_inverse=True)
        ab, bc, ca = (inverse.view(3, -1) + len(verts)).unbind(0)  # midpoint vertex of each face edge
        verts = torch.cat([verts, verts[unique].mean(1)])
        verts = verts / verts.norm(dim=1, keepdim=True)
        faces = torch.cat([torch.stack(f, 1) for f in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return _Meshes(verts[None].to(device or "cpu"), faces[None].to(device or "cpu"))
