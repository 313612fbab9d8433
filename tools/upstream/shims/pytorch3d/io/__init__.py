"""Shim: ``load_obj`` returning the vertex positions of an ``.obj`` file (``faces`` and ``aux`` are None).

test_sample_farthest_points.py's CUDA-vs-CPU test samples the vertices of PyTorch3D's tutorial cow
(``docs/tutorials/data/cow_mesh/cow.obj``, not fetched: see tools/upstream/fetch.md). Upstream's
``pytorch3d.io`` imports the renderer, which needs compiled PyTorch3D.
"""
import torch


def load_obj(f, load_textures=True, create_texture_atlas=False, texture_atlas_size=4,
             texture_wrap="repeat", device="cpu", path_manager=None):
    with open(f) as lines:
        verts = [[float(x) for x in line.split()[1:4]] for line in lines if line.startswith("v ")]
    return torch.tensor(verts, dtype=torch.float32, device=device), None, None
