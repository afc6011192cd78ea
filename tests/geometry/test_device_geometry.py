"""The geometry of a training step on a GPU gives the CPU's answers: ray-mesh hits, nearest points, the
distance grid, the silhouette's candidate faces and backward skinning. Skipped without CUDA."""

from __future__ import annotations

import pytest
import torch
import trimesh

from delta.geometry import distance_grid
from delta.geometry.nearest import PointIndex
from delta.geometry.raymesh import embree_available, ray_mesh_hits
from delta.render.silhouette import nearest_faces

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
CUDA = torch.device("cuda")


def _scene(dtype=torch.float32):
    g = torch.Generator().manual_seed(0)
    ball = trimesh.creation.icosphere(subdivisions=5)  # 20480 faces
    v = torch.tensor(ball.vertices, dtype=dtype) * torch.tensor([0.3, 0.9, 0.2], dtype=dtype)
    f = torch.tensor(ball.faces)
    n = 20000
    origins = 3 * torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1).to(dtype)
    dirs = v[torch.randint(len(v), (n,), generator=g)] + 0.05 * torch.randn(n, 3, generator=g).to(dtype) - origins
    return v, f, origins, dirs


@pytest.mark.skipif(not embree_available(), reason="no embreex")
def test_cuda_ray_hits_match_embree_on_the_cpu():
    v, f, o, d = _scene()
    cpu = ray_mesh_hits(v, f, o, d, backend="embree")
    gpu = ray_mesh_hits(v.to(CUDA), f.to(CUDA), o.to(CUDA), d.to(CUDA))  # auto: the torch search on CUDA
    assert gpu.t.device.type == "cuda"
    assert int((cpu.hit != gpu.hit.cpu()).sum()) <= 2
    both = cpu.hit & gpu.hit.cpu()
    torch.testing.assert_close(gpu.t.cpu()[both], cpu.t[both], rtol=1e-5, atol=1e-6)


def test_cuda_ray_hits_match_the_torch_search_on_the_cpu():
    v, f, o, d = _scene(torch.float64)
    cpu = ray_mesh_hits(v, f, o, d, backend="torch")
    gpu = ray_mesh_hits(v.to(CUDA), f.to(CUDA), o.to(CUDA), d.to(CUDA), backend="torch")
    assert torch.equal(cpu.hit, gpu.hit.cpu()) and torch.equal(cpu.face, gpu.face.cpu())
    torch.testing.assert_close(gpu.t.cpu(), cpu.t, rtol=1e-12, atol=0)


@pytest.mark.parametrize("k", [1, 6])
def test_cuda_nearest_points_match_the_kdtree(k):
    v, *_ = _scene(torch.float64)
    g = torch.Generator().manual_seed(k)
    q = v[torch.randint(len(v), (50000,), generator=g)] + 0.1 * torch.randn(50000, 3, generator=g, dtype=v.dtype)
    want_d, want_i = PointIndex(v, "kdtree").query(q, k)
    got_d, got_i = PointIndex(v.to(CUDA)).query(q.to(CUDA), k)
    assert got_i.device.type == "cuda"
    assert torch.equal(got_i.cpu(), want_i)
    torch.testing.assert_close(got_d.cpu(), want_d, rtol=1e-12, atol=1e-15)


def test_cuda_distance_grid_matches_scipys_transform():
    v, *_ = _scene(torch.float64)
    cpu = distance_grid.build(v, 0.02, 0.2, nearest=True, method="scipy")
    gpu = distance_grid.build(v.to(CUDA), 0.02, 0.2, nearest=True)
    assert gpu.distance.device.type == "cuda"
    torch.testing.assert_close(gpu.distance.cpu(), cpu.distance)
    q = 0.6 * torch.randn(5000, 3, dtype=torch.float64)
    torch.testing.assert_close(distance_grid.lookup(gpu, q.to(CUDA)).cpu(), distance_grid.lookup(cpu, q))


def test_cuda_silhouette_candidates_match_the_cpu():
    g = torch.Generator().manual_seed(1)
    uv = 512 * torch.rand(3000, 2, generator=g, dtype=torch.float64)
    faces = torch.randint(3000, (6000, 3), generator=g)
    pixels = 512 * torch.rand(4096, 2, generator=g, dtype=torch.float64)
    cpu = nearest_faces(uv, faces, pixels, 16)
    gpu = nearest_faces(uv.to(CUDA), faces.to(CUDA), pixels.to(CUDA), 16)
    assert gpu.device.type == "cuda" and torch.equal(gpu.cpu(), cpu)
