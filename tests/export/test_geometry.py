"""Pure pieces of the export: marching cubes (analytic sphere), the body-side mask, forward skinning, rasterising."""

import math

import numpy as np
import pytest

from delta import DeltaError
import torch
import trimesh

from delta.body.lbs import lbs
from delta.body.model import BodyModel
from delta.deformers.knn import deform, prepare
from delta.export import lineup, marching
from delta.geometry.closest import closest_point_on_triangles
from delta.export.meshes import MeshPart, clean, edge_lengths, split_long_edges
from delta.export.settings import ExportSettings
from delta.export.skinning import forward_skin, prepare_forward
from delta.body.upright import axis_angle_matrix
from delta.export.video import moved_params
from tests.conftest import soft_tree_model

D = torch.float64


# ------------------------------------------------------------------ marching cubes
def test_marching_cubes_of_a_gaussian_ball_has_the_analytic_radius():
    """σ = 100 exp(-(r/0.5)²) cut at 100/e: a sphere of radius 0.5, normals outward."""
    grid = marching.make_grid(np.full(3, -0.8), np.full(3, 0.8), 48)
    values = marching.sample(grid, lambda p: 100 * np.exp(-((np.linalg.norm(p, axis=1) / 0.5) ** 2)), chunk=1000)
    verts, faces = marching.extract_surface(values, grid, 100 / math.e)
    radius = np.linalg.norm(verts, axis=1)
    assert abs(radius.mean() - 0.5) < 2e-3 and np.abs(radius - 0.5).max() < 0.2 * grid.spacing
    mesh = trimesh.Trimesh(verts, faces, process=False)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * 0.5**3, rel=0.02)  # > 0: normals point outwards


def test_surfaces_touching_the_box_are_closed_and_empty_fields_give_no_surface():
    grid = marching.make_grid(np.zeros(3), np.ones(3), 10)
    values = np.full(grid.shape, 5.0, dtype=np.float32)  # dense everywhere: the box itself
    verts, faces = marching.extract_surface(values, grid, 1.0)
    box = trimesh.Trimesh(verts, faces, process=False)
    assert box.is_watertight and box.volume > 0
    # the level 1 lies 4/5 of a cell beyond the boundary samples (σ = 5) towards the padding (σ = 0)
    np.testing.assert_allclose(verts.min(0), -0.08, atol=1e-6)
    np.testing.assert_allclose(verts.max(0), 1.08, atol=1e-6)
    v, f = marching.extract_surface(np.zeros(grid.shape, np.float32), grid, 1.0)
    assert v.shape == (0, 3) and f.shape == (0, 3)
    with pytest.raises(ValueError, match="non-finite"):
        marching.extract_surface(np.full(grid.shape, np.nan, np.float32), grid, 1.0)


def test_only_points_near_the_body_and_outside_it_are_kept():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    pts = np.array([[0, 0, 0.5], [0, 0, 0.97], [0, 0, 1.05], [0, 0, 1.15], [0.7, 0.72, 0.0], [0, 0, 3.0]])
    keep = marching.near_and_outside(pts, sphere.vertices, sphere.vertex_normals, max_dist=0.1)
    assert keep.tolist() == [False, False, True, False, True, False]


def test_the_wall_the_mask_makes_on_the_skin_is_told_from_the_garment():
    """A garment 6 cm thick over a ball of 0.5 m, its density cut to 0 inside the ball as the export cuts it:
    the level set has a wall on the skin (normals into the ball) and the garment's outside; the skin faces
    are the first, every one, and none of the second."""
    body = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    grid = marching.make_grid(np.full(3, -0.7), np.full(3, 0.7), 64)
    mask = marching.near_and_outside(grid.points(), body.vertices, body.vertex_normals, max_dist=0.15)
    values = marching.sample(grid, lambda p: 10.0 * (np.linalg.norm(p, axis=1) < 0.56), mask, chunk=4096)
    verts, faces = marching.extract_surface(values, grid, 5.0)
    skin = marching.skin_faces(verts, faces, body.vertices, body.vertex_normals, grid.spacing)
    radius = np.linalg.norm(verts[faces].mean(1), axis=1)
    assert radius[skin].max() < 0.5 + grid.spacing and radius[~skin].min() > 0.56 - grid.spacing
    assert skin.any() and (~skin).any()
    area = trimesh.Trimesh(verts, faces, process=False).area_faces
    assert area[skin].sum() / area.sum() == pytest.approx(0.5**2 / (0.5**2 + 0.56**2), abs=0.03)
    assert marching.skin_faces(verts, faces[:0], body.vertices, body.vertex_normals, grid.spacing).shape == (0,)


def test_the_walls_no_outside_view_sees_are_told_from_the_garment():
    """A skirt over a leg (a vertical cylinder of radius 0.2 m): a waistband on the body (0.25 < y < 0.3) and,
    below it, a wall standing 0.1 m off the body (0.3 < r < 0.4) down to a hem at y = -0.3. From the side and
    from above the views see the wall's outside (r = 0.4) and the band's top (y = 0.3); its inside (r = 0.3),
    the gap's ceiling and the hem's underside face only the body or the ground and are hidden."""
    body = trimesh.creation.cylinder(radius=0.2, height=2.0, sections=48)
    body.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # its axis along y
    grid = marching.make_grid(np.full(3, -0.5), np.full(3, 0.5), 80)

    def density(p):
        r, y = np.linalg.norm(p[:, [0, 2]], axis=1), p[:, 1]
        band = (y > 0.25) & (y < 0.3) & (r > 0.2) & (r < 0.4)
        wall = (y > -0.3) & (y <= 0.25) & (r > 0.3) & (r < 0.4)
        return 10.0 * (band | wall)

    verts, faces = marching.extract_surface(marching.sample(grid, density, chunk=1 << 16), grid, 5.0)
    hidden = marching.hidden_faces(verts, faces, body.vertices, body.faces, 12, grid.spacing / 2, 0.01)
    normals, area = marching.face_normals(verts, faces)
    c = verts[faces].mean(1)
    r, y = np.linalg.norm(c[:, [0, 2]], axis=1), c[:, 1]
    radial = (normals[:, [0, 2]] * c[:, [0, 2]]).sum(1) / np.maximum(r, 1e-9)
    h = 1.5 * grid.spacing  # away from the shape's edges, where marching cubes bevels
    outside = (np.abs(r - 0.4) < h) & (radial > 0.9) & (np.abs(y) < 0.3 - h)
    top = (np.abs(y - 0.3) < h) & (normals[:, 1] > 0.9) & (r > 0.2 + h) & (r < 0.4 - h)
    inside = (np.abs(r - 0.3) < h) & (radial < -0.9) & (y > -0.3 + h) & (y < 0.25 - h)
    under = (normals[:, 1] < -0.9) & (np.abs(r - 0.35) < 0.05 - h)  # the gap's ceiling and the hem
    for part in (outside, top, inside, under):
        assert part.sum() > 50
    assert not hidden[outside | top].any()
    assert hidden[inside | under].all()
    assert area[hidden].sum() / area.sum() > 0.4  # the inside is as large as the outside
    # hidden patches smaller than the area kept stay; no views: nothing is hidden
    assert not marching.hidden_faces(verts, faces, body.vertices, body.faces, 12, grid.spacing / 2, 10.0).any()
    assert not marching.hidden_faces(verts, faces, body.vertices, body.faces, 0, grid.spacing / 2, 0.01).any()


def test_cleaning_drops_small_components_and_decimates():
    big = trimesh.creation.icosphere(subdivisions=4)  # 5120 faces
    small = trimesh.creation.icosphere(subdivisions=0, radius=0.1)  # 20 faces
    small.apply_translation([3, 0, 0])
    both = trimesh.util.concatenate([big, small])
    st = ExportSettings(min_component_faces=50, smooth=0, decimate=1000)
    v, f = clean(both.vertices, both.faces, st)
    out = trimesh.Trimesh(v, f, process=False)
    assert len(f) == 1000 and v[:, 0].max() < 1.01  # the far small sphere is gone
    assert out.is_watertight and out.volume == pytest.approx(big.volume, rel=0.03)
    # Taubin smoothing does not shrink a sphere the way Laplacian smoothing does
    v, f = clean(big.vertices, big.faces, ExportSettings(min_component_faces=0, smooth=10, decimate=0))
    assert len(f) == len(big.faces) and abs(np.linalg.norm(v, axis=1).mean() - 1) < 0.01


def test_long_edges_are_split_on_the_surface_until_none_is_longer():
    sphere = trimesh.creation.icosphere(subdivisions=1)  # edges ~1.05
    v, f = split_long_edges(sphere.vertices, sphere.faces, 0.2)
    split = trimesh.Trimesh(v, f, process=False)
    assert edge_lengths(MeshPart(v, f, np.zeros_like(v))).max() <= 0.2 < len(f) / len(sphere.faces)
    assert split.is_watertight and split.area == pytest.approx(sphere.area, rel=1e-9)  # nothing moved off it
    tri = sphere.vertices[sphere.faces]  # every new vertex on an old face
    n, k = len(v), len(tri)
    pairs = [np.repeat(v, k, 0)] + [np.tile(tri[:, i], (n, 1)) for i in range(3)]
    nearest = closest_point_on_triangles(*pairs).reshape(n, k, 3)
    assert np.linalg.norm(nearest - v[:, None], axis=-1).min(1).max() < 1e-9
    # short enough already, or no limit: the mesh comes back as it was
    for longest in (2.0, 0.0):
        same_v, same_f = split_long_edges(sphere.vertices, sphere.faces, longest)
        assert same_v is sphere.vertices and same_f is sphere.faces


# ------------------------------------------------------------------ forward skinning
def _posed_tree(seed=0):
    model = soft_tree_model()
    model.canonical_pose = torch.tensor([[0, 0, 0.3], [0, 0, -0.4], [0.2, 0, 0], [0, 0.5, 0]], dtype=D)
    gen = torch.Generator().manual_seed(seed)
    out = lbs(model, torch.randn(1, 2, generator=gen, dtype=D), 0.6 * torch.randn(1, 4, 3, generator=gen, dtype=D),
              offsets=0.02 * torch.randn(model.num_vertices, 3, generator=gen, dtype=D),
              transl=torch.randn(1, 3, generator=gen, dtype=D))  # fmt: skip
    cano_T = lbs(model, torch.zeros(1, 2, dtype=D), model.canonical_pose[None]).vertex_transforms_3x4[0]
    # canonical space: the template in the canonical pose, G^c_i template_i (no pose correctives)
    cano = (cano_T[..., :3] @ model.v_template[..., None]).squeeze(-1) + cano_T[..., 3]
    disp = out.rest_vertices[0] - model.v_template
    return model, out, (cano, cano_T), disp


def test_forward_skinning_sends_canonical_vertices_to_posed_vertices():
    model, out, cano, disp = _posed_tree()
    fwd = prepare_forward(cano[0], cano[1], out.vertex_transforms_3x4[0], disp, model.weights)
    torch.testing.assert_close(forward_skin(fwd, cano[0], k=1), out.vertices[0], rtol=0, atol=1e-10)


def bent_tube(dtype=D) -> BodyModel:
    """A dense tube along x (1 m, radius 0.1, 2 cm rings) with an elbow at x = 0.5: two joints, weights
    blending smoothly over the elbow; shape moves the tip; canonical pose bends the elbow by 0.3 rad."""
    x = torch.linspace(0, 1, 51, dtype=dtype)
    a = torch.linspace(0, 2 * math.pi, 33, dtype=dtype)[:-1]
    X, A = torch.meshgrid(x, a, indexing="ij")
    verts = torch.stack([X, 0.1 * torch.cos(A), 0.1 * torch.sin(A)], -1).reshape(-1, 3)
    i, j = torch.meshgrid(torch.arange(50), torch.arange(32), indexing="ij")
    q = [i * 32 + j, (i + 1) * 32 + j, (i + 1) * 32 + (j + 1) % 32, i * 32 + (j + 1) % 32]
    faces = torch.cat([torch.stack([q[0], q[1], q[2]], -1), torch.stack([q[0], q[2], q[3]], -1)]).reshape(-1, 3)
    w1 = torch.sigmoid((verts[:, 0] - 0.5) / 0.05)
    shapedirs = torch.zeros(len(verts), 3, 1, dtype=dtype)
    shapedirs[:, 0, 0] = 0.05 * verts[:, 0]
    return BodyModel(
        name="tube", v_template=verts, faces=faces, shapedirs=shapedirs,
        joints_template=torch.tensor([[0.0, 0, 0], [0.5, 0, 0]], dtype=dtype),
        joints_shapedirs=torch.tensor([[[0.0], [0], [0]], [[0.025], [0], [0]]], dtype=dtype),
        parents=torch.tensor([-1, 0]), joint_names=["root", "elbow"], weights=torch.stack([1 - w1, w1], -1),
        regions=torch.zeros(len(verts), dtype=torch.int64),
        canonical_pose=torch.tensor([[0, 0, 0], [0, 0, 0.3]], dtype=dtype),
    ).validate("bent tube")  # fmt: skip


def test_backward_of_forward_is_the_identity_near_the_body():
    """Points up to 3 cm off a dense body, posed with the elbow bent by 1.2 rad and back."""
    model = bent_tube()
    out = lbs(
        model,
        torch.tensor([[1.0]], dtype=D),
        torch.tensor([[[0.2, 0.3, 0.1], [0, 0, 1.2]]], dtype=D),
        offsets=0.01 * torch.sin(5 * model.v_template),
        transl=torch.tensor([[0.1, 0.2, 0.3]], dtype=D),
    )
    cano_T = lbs(model, torch.zeros(1, 1, dtype=D), model.canonical_pose[None]).vertex_transforms_3x4[0]
    cano = (cano_T[..., :3] @ model.v_template[..., None]).squeeze(-1) + cano_T[..., 3]
    disp = out.rest_vertices[0] - model.v_template
    fwd = prepare_forward(cano, cano_T, out.vertex_transforms_3x4[0], disp, model.weights)
    bwd = prepare(out.vertices[0], out.vertex_transforms_3x4[0], disp, cano_T, model.weights)
    gen = torch.Generator().manual_seed(3)
    x_c = cano[::7] + 0.03 * (2 * torch.rand(len(cano[::7]), 3, generator=gen, dtype=D) - 1)
    posed = forward_skin(fwd, x_c)
    assert (posed - x_c).norm(dim=-1).max() > 0.3  # the pose moves the points a lot
    err = (deform(bwd, posed).canonical - x_c).norm(dim=-1)
    # nearly exact where the blend is locally rigid; at the elbow (and the open ends) the kNN sets differ a little
    assert float(err.median()) < 1e-5 and float(err.quantile(0.9)) < 1e-3 and float(err.max()) < 0.01, err.max()
    assert float(err[(x_c[:, 0] - 0.5).abs() > 0.25].median()) < 1e-6


# ------------------------------------------------------------------ rasterising
def test_rasterised_triangles_cover_their_area_and_overlaps_do_not_cancel():
    uv = np.array([[2.0, 2.0], [30.0, 2.0], [2.0, 30.0], [30.0, 30.0]])
    depth = np.ones(4)
    tri = lineup.rasterize(uv, depth, np.array([[0, 1, 2]]), 32, 32)
    # pixel centres on or under the diagonal u + v <= 32: 28 + 27 + ... + 1
    assert int(tri.sum()) == 28 * 29 // 2 and tri[2, 2] and tri[2, 29] and not tri[2, 30] and not tri[29, 29]
    square = lineup.rasterize(uv, depth, np.array([[0, 1, 2], [1, 3, 2], [0, 1, 3]]), 32, 32)
    assert int(square.sum()) == 28 * 28  # overlapping triangles: still covered
    assert not lineup.rasterize(uv, -depth, np.array([[0, 1, 2]]), 32, 32).any()  # behind the camera
    assert lineup.iou(tri, square) == pytest.approx(tri.sum() / square.sum())
    assert lineup.iou(np.zeros((2, 2), bool), np.zeros((2, 2), bool)) == 1.0


def test_moving_the_root_rotates_the_whole_posed_body_about_the_centre():
    model, _, _, _ = _posed_tree()
    gen = torch.Generator().manual_seed(5)
    betas, pose = torch.randn(1, 2, generator=gen, dtype=D), 0.5 * torch.randn(1, 4, 3, generator=gen, dtype=D)
    transl = torch.randn(1, 3, generator=gen, dtype=D)
    out = lbs(model, betas, pose, transl=transl)
    centre = out.vertices[0].mean(0)
    axis = torch.tensor([0.3, 0.9, -0.2], dtype=D)
    A = axis_angle_matrix(axis, 1.1)
    root, t = moved_params(pose[0, 0], transl[0], out.rest_joints[0, 0], centre, A)
    moved = lbs(model, betas, torch.cat([root[None, None], pose[:, 1:]], 1), transl=t[None])
    torch.testing.assert_close(moved.vertices[0], (out.vertices[0] - centre) @ A.T + centre, rtol=0, atol=1e-6)
    # Rodrigues against the matrix exponential of the cross-product matrix
    k = axis / axis.norm()
    K = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=D)
    torch.testing.assert_close(A, torch.linalg.matrix_exp(1.1 * K), rtol=0, atol=1e-12)


def test_mesh_part_colours_survive_the_trimesh_conversion():
    part = MeshPart(np.eye(3), np.array([[0, 1, 2]]), np.array([[1.0, 0, 0], [0, 0.5, 0], [0, 0, 0.2]]))
    tm = part.to_trimesh()
    assert tm.visual.vertex_colors[:, :3].tolist() == [[255, 0, 0], [0, 128, 0], [0, 0, 51]]


def test_settings_reject_bad_values():
    with pytest.raises(DeltaError, match="export.grid"):
        ExportSettings(grid=2)
    with pytest.raises(DeltaError, match="export.threshold"):
        ExportSettings(threshold=0)
    with pytest.raises(DeltaError, match="export.decimate"):
        ExportSettings(decimate=-1)
