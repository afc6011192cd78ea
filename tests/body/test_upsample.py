"""Midpoint subdivision with a barycentric embedding."""

import numpy as np
import pytest
import torch
import trimesh

from delta.body.lbs import lbs
from delta.body.model import BodyModel
from delta.body.upsample import embedding, interpolation_matrix, subdivide_faces, upsample_body_model


def sphere_model(subdivisions=2) -> BodyModel:
    """A closed icosphere with two joints (lower half / upper half) and blended weights."""
    mesh = trimesh.creation.icosphere(subdivisions)
    v = torch.from_numpy(mesh.vertices.copy())
    w1 = torch.sigmoid(8 * v[:, 1])
    weights = torch.stack([1 - w1, w1], 1)
    gen = torch.Generator().manual_seed(0)
    return BodyModel(
        name="sphere",
        v_template=v,
        faces=torch.from_numpy(mesh.faces.astype(np.int64)),
        shapedirs=0.1 * torch.randn(len(v), 3, 3, generator=gen, dtype=torch.float64),
        joints_template=torch.tensor([[0.0, -0.5, 0.0], [0.0, 0.5, 0.0]], dtype=torch.float64),
        joints_shapedirs=torch.zeros(2, 3, 3, dtype=torch.float64),
        parents=torch.tensor([-1, 0]),
        joint_names=["lower", "upper"],
        weights=weights,
        regions=(v[:, 1] > 0).long(),
        canonical_pose=torch.zeros(2, 3, dtype=torch.float64),
    ).validate("sphere")


def test_subdivide_counts_and_closedness():
    mesh = trimesh.creation.icosphere(1)
    faces, edges = subdivide_faces(mesh.faces, len(mesh.vertices))
    assert len(faces) == 4 * len(mesh.faces)
    assert len(edges) == len(mesh.edges_unique)
    verts = np.concatenate([mesh.vertices, mesh.vertices[edges].mean(1)])
    sub = trimesh.Trimesh(verts, faces, process=False)
    assert sub.is_watertight and sub.is_winding_consistent
    assert np.isclose(sub.area, mesh.area)  # midpoint subdivision keeps the surface


@pytest.mark.parametrize("level", [1, 2])
def test_embedding_matches_repeated_subdivision(level):
    mesh = trimesh.creation.icosphere(1)
    faces, ids, bary = embedding(mesh.faces, len(mesh.vertices), level)
    verts = mesh.vertices
    f = mesh.faces
    for _ in range(level):
        f, e = subdivide_faces(f, len(verts))
        verts = np.concatenate([verts, verts[e].mean(1)])
    np.testing.assert_array_equal(faces, f)
    np.testing.assert_allclose((mesh.vertices[ids] * bary[..., None]).sum(1), verts, atol=1e-12)
    np.testing.assert_allclose(bary.sum(1), 1.0)
    # every vertex lies in one base triangle: its three ids are corners of a base face (or itself)
    assert (bary >= 0).all()


def test_upsampled_model_at_rest_and_under_rigid_motion():
    base = sphere_model()
    up = upsample_body_model(base, 1).validate("upsampled")
    E = len(trimesh.Trimesh(base.v_template.numpy(), base.faces.numpy(), process=False).edges_unique)
    assert up.num_vertices == base.num_vertices + E
    M = interpolation_matrix(up.embed_vertex_ids, up.embed_bary, base.num_vertices)
    betas = torch.randn(2, 3, dtype=torch.float64)
    zero = torch.zeros(2, 2, 3, dtype=torch.float64)
    rest_base = lbs(base, betas, zero).vertices
    rest_up = lbs(up, betas, zero).vertices
    torch.testing.assert_close(rest_up, torch.stack([M @ r for r in rest_base]))
    # a rigid global motion commutes with the interpolation
    pose = zero.clone()
    pose[:, 0] = torch.tensor([0.3, -1.2, 0.4], dtype=torch.float64)
    t = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64).expand(2, 3)
    posed_base = lbs(base, betas, pose, transl=t).vertices
    posed_up = lbs(up, betas, pose, transl=t).vertices
    torch.testing.assert_close(posed_up, torch.stack([M @ r for r in posed_base]))
    # labels are carried, weights stay normalised
    assert set(up.regions.tolist()) == {0, 1}
    torch.testing.assert_close(up.weights.sum(1), torch.ones(up.num_vertices, dtype=torch.float64))
    mesh = trimesh.Trimesh(up.v_template.numpy(), up.faces.numpy(), process=False)
    assert mesh.is_watertight


def test_level_zero_is_identity():
    base = sphere_model(1)
    assert upsample_body_model(base, 0) is base
