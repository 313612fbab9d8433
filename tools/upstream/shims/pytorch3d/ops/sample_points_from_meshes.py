"""Shim: ``sample_points_from_meshes`` for the meshes of the ``pytorch3d.utils.ico_sphere`` shim.

test_ball_query.py's CUDA test samples its clouds from an ico-sphere. Upstream's module needs compiled
PyTorch3D (``mesh_face_areas_normals``, ``packed_to_padded``) and the renderer; this is its rule in
plain PyTorch: a face drawn with probability proportional to its area, then uniform barycentric
coordinates ``(1 - sqrt(u), sqrt(u) (1 - v), sqrt(u) v)``. Points only (no normals or textures).
"""
import torch


def sample_points_from_meshes(meshes, num_samples: int = 10000, return_normals: bool = False,
                              return_textures: bool = False) -> torch.Tensor:
    if return_normals or return_textures:
        raise NotImplementedError("the shim samples points only")
    verts, faces = meshes.verts_padded(), meshes.faces_padded()  # (N, V, 3), (N, F, 3)
    N = verts.shape[0]
    corner = [torch.gather(verts, 1, faces[..., j, None].expand(-1, -1, 3)) for j in range(3)]  # (N, F, 3)
    areas = torch.linalg.cross(corner[1] - corner[0], corner[2] - corner[0], dim=-1).norm(dim=-1) / 2
    face = areas.multinomial(num_samples, replacement=True)[..., None].expand(-1, -1, 3)  # (N, S, 3)
    u, v = torch.rand(2, N, num_samples, 1, dtype=verts.dtype, device=verts.device)
    w = (1.0 - u.sqrt(), u.sqrt() * (1.0 - v), u.sqrt() * v)
    return sum(wj * torch.gather(c, 1, face) for wj, c in zip(w, corner))
