"""Backward skinning where two body parts touch in a pose: each exterior point follows the part it belongs to.

The bodies here are rigid parts made of icosphere and tube vertices, each part skinned to its own joint,
placed apart in the canonical space and brought into contact by the pose. A canonical density field
stands for the NeRF; a posed point's density is that of its densest candidate, as the renderer takes it.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import trimesh

from delta.deformers.knn import deform, prepare, voxel_subset
from delta.render.hybrid import PosedMesh, denser, early_cull, render_rays
from delta.render.settings import RenderSettings

D = torch.float64
CELL = 0.03  # the contact probe's voxel


def sphere(centre, radius, subdivisions=4) -> torch.Tensor:
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return torch.tensor(s.vertices, dtype=D) + torch.tensor(centre, dtype=D)


def tube(start, end, radius, rings=60, around=24) -> torch.Tensor:
    """Vertices of an open cylinder from ``start`` to ``end`` (any direction)."""
    a, b = np.asarray(start, float), np.asarray(end, float)
    axis = (b - a) / np.linalg.norm(b - a)
    u = np.cross(axis, [0, 0, 1] if abs(axis[2]) < 0.9 else [1, 0, 0])
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    t = np.linspace(0, 1, rings)[:, None, None]
    phi = np.linspace(0, 2 * np.pi, around, endpoint=False)[None, :, None]
    pts = a + t * (b - a) + radius * (np.cos(phi) * u + np.sin(phi) * w)
    return torch.tensor(pts.reshape(-1, 3), dtype=D)


def rigid(rotation: np.ndarray, translation) -> torch.Tensor:
    return torch.cat([torch.tensor(rotation, dtype=D), torch.tensor(translation, dtype=D)[:, None]], dim=1)


def rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def two_parts(canonical_parts, transforms, dtype=D, contact_cell=CELL, **grid):
    """A body of rigid parts: canonical vertices per part (list of (V_p, 3)) and each part's posed rigid
    (3, 4) transform. Returns the skinning frame (canonical space = the canonical vertices); ``grid``:
    ``prepare``'s distance-grid arguments."""
    verts = torch.cat(canonical_parts).to(dtype)
    part = torch.cat([torch.full((len(v),), i) for i, v in enumerate(canonical_parts)])
    G = torch.stack(transforms)[part].to(dtype)
    posed = (G[..., :3] @ verts[..., None]).squeeze(-1) + G[..., 3]
    eye = torch.eye(3, 4, dtype=dtype).expand(len(verts), 3, 4)
    weights = torch.nn.functional.one_hot(part, len(canonical_parts)).to(dtype)
    # template = the canonical vertices, canonical transforms the identity, no displacement
    return prepare(posed, G, torch.zeros_like(verts), eye, weights, contact_cell=contact_cell, **grid)


def density(frame, points, field, max_dist=0.1):
    """What the renderer gives each posed point: the field at its densest valid candidate (0 when none)."""
    d = deform(frame, points, k=6, sigma=0.1, max_dist=max_dist)
    x, valid, rows = d.canonical, d.valid, torch.arange(len(points))
    if d.other is not None:
        x, valid = torch.cat([x, d.other.canonical]), torch.cat([valid, d.other.valid])
        rows = torch.cat([rows, d.other.rows])
    sigma = torch.where(valid, field(x), torch.zeros_like(valid, dtype=D))
    at, pick = denser(rows, sigma)
    out = torch.zeros(len(points), dtype=D)
    out[at] = sigma[pick]
    return out


def shell(centre, inner, outer):
    c = torch.tensor(centre, dtype=D)
    return lambda x: (((x - c).norm(dim=-1) > inner) & ((x - c).norm(dim=-1) < outer)).to(D)


# a 'hip' (radius 0.1 at the origin) and a 'hand' (radius 0.04) that lies 0.6 m away in the canonical space
HIP, HAND = sphere((0, 0, 0), 0.1), sphere((0.6, 0, 0), 0.04)
TROUSERS = shell((0, 0, 0), 0.1, 0.125)  # 2.5 cm of cloth on the hip
GLOVE = shell((0.6, 0, 0), 0.04, 0.055)  # 1.5 cm of cloth on the hand
STILL = rigid(np.eye(3), (0, 0, 0))


def hand_at(x, y=0.0):
    """The hand's transform that puts its centre at (x, y, 0)."""
    return rigid(np.eye(3), (x - 0.6, y, 0))


def test_cloth_on_the_hip_stays_where_a_hand_rests_beside_it():
    # the hand's surface 3 cm from the hip's; p is 2 cm off the hip, 1 cm off the hand: in the trousers
    frame = two_parts([HIP, HAND], [STILL, hand_at(0.17)])
    p = torch.tensor([[0.12, 0.0, 0.0], [0.0, 0.12, 0.0]], dtype=D)  # beside the hand, and away from it
    assert density(frame, p, TROUSERS).tolist() == [1.0, 1.0]
    # the one blend over the nearest surface takes p to the hand, where there is no cloth
    plain = two_parts([HIP, HAND], [STILL, hand_at(0.17)], contact_cell=0)
    assert density(plain, p, TROUSERS).tolist() == [0.0, 1.0]
    # the hand moving does not carry the cloth
    for x, y in [(0.16, 0.0), (0.18, 0.02), (0.17, -0.02)]:
        moved = two_parts([HIP, HAND], [STILL, hand_at(x, y)])
        assert density(moved, p[:1], TROUSERS).item() == 1.0
    # the hip moving does: the cloth is found at p moved with it, no longer at p
    t = torch.tensor([0.0, 0.05, 0.0], dtype=D)
    moved = two_parts([HIP, HAND], [rigid(np.eye(3), t.tolist()), hand_at(0.17)])
    assert density(moved, p[:1] + t, TROUSERS).item() == 1.0
    assert density(moved, p[:1], TROUSERS).item() == 0.0


def test_cloth_on_the_hand_moves_with_the_hand_not_the_hip():
    frame = two_parts([HIP, HAND], [STILL, hand_at(0.17)])
    q = torch.tensor([[0.12, 0.0, 0.0]], dtype=D)  # 1 cm off the hand: in the glove
    assert density(frame, q, GLOVE).item() == 1.0
    shift = torch.tensor([0.0, 0.03, 0.0], dtype=D)
    moved = two_parts([HIP, HAND], [STILL, hand_at(0.17, 0.03)])
    assert density(moved, q + shift, GLOVE).item() == 1.0
    assert density(moved, q, GLOVE).item() == 0.0  # 5.8 cm from the moved hand's centre: out of the glove
    # the hip moving leaves the glove where the hand is
    hip_moved = two_parts([HIP, HAND], [rigid(np.eye(3), (0, -0.03, 0)), hand_at(0.17)])
    assert density(hip_moved, q, GLOVE).item() == 1.0


def test_hair_stays_with_the_head_when_an_arm_is_raised_beside_it():
    head = sphere((0, 0, 0), 0.1)
    hair = shell((0, 0, 0), 0.1, 0.13)
    # the arm lies along +x from the shoulder in the canonical space; raised, it stands upright beside the head
    arm = tube((0.3, -0.3, 0), (0.9, -0.3, 0), 0.04)
    down = two_parts([head, arm], [STILL, STILL])
    raised = two_parts([head, arm], [STILL, rigid(rot_z(90), (0.16 - 0.3, -0.6, 0))])
    # the raised arm's axis is the line x = 0.16, z = 0: its surface 2 cm from the head's
    axis_x = float(raised.posed[len(head) :, 0].mean())
    assert abs(axis_x - 0.16) < 1e-9
    ring = torch.stack([torch.tensor([0.1 + r, 0.0, 0.0], dtype=D) for r in (0.005, 0.01, 0.015)])
    others = torch.tensor([[0.0, 0.115, 0.0], [-0.115, 0.0, 0.0], [0.0, 0.0, 0.115]], dtype=D)
    points = torch.cat([ring, others])
    assert density(down, points, hair).tolist() == [1.0] * 6
    assert density(raised, points, hair).tolist() == [1.0] * 6
    # without telling the surfaces apart, the hair nearest the arm is lost
    plain = two_parts([head, arm], [STILL, rigid(rot_z(90), (0.16 - 0.3, -0.6, 0))], contact_cell=0)
    assert density(plain, ring, hair).min().item() == 0.0


def bent_tube(angle_deg: float, contact_cell: float):
    """One tube along x from 0 to 0.6 bending at x = 0.3 (the far half turns by ``angle_deg`` about z,
    skinning weights blended over ±5 cm of the joint), as a skinning frame."""
    verts = tube((0, 0, 0), (0.6, 0, 0), 0.05, rings=121, around=32)
    w1 = ((verts[:, 0] - 0.25) / 0.1).clamp(0, 1)
    weights = torch.stack([1 - w1, w1], dim=1)
    joint = torch.tensor([0.3, 0, 0], dtype=D)
    R = torch.tensor(rot_z(angle_deg), dtype=D)
    T1 = torch.cat([R, (joint - R @ joint)[:, None]], dim=1)
    T0 = torch.eye(3, 4, dtype=D)
    G = weights[:, 0, None, None] * T0 + weights[:, 1, None, None] * T1
    posed = (G[..., :3] @ verts[..., None]).squeeze(-1) + G[..., 3]
    eye = torch.eye(3, 4, dtype=D).expand(len(verts), 3, 4)
    return prepare(posed, G, torch.zeros_like(verts), eye, weights, contact_cell=contact_cell)


def test_the_deformation_is_continuous_across_a_limb_boundary():
    frame = bent_tube(40, CELL)
    # a line 3 cm outside the tube's outer side (-y), across the joint, densely sampled
    s = torch.linspace(0.15, 0.45, 601, dtype=D)
    R = torch.tensor(rot_z(40), dtype=D)
    joint = torch.tensor([0.3, 0, 0], dtype=D)
    below = torch.stack([s, torch.full_like(s, -0.08), torch.zeros_like(s)], 1)
    line = torch.where((s > 0.3)[:, None], (R @ (below - joint).T).T + joint, below)
    with_contact = deform(frame, line, max_dist=0.2)
    plain = deform(bent_tube(40, 0.0), line, max_dist=0.2)
    # one surface: no second candidates, and the same map as the plain blend
    assert with_contact.other is None or len(with_contact.other.rows) == 0
    torch.testing.assert_close(with_contact.canonical, plain.canonical, rtol=0, atol=1e-12)
    step = (line[1:] - line[:-1]).norm(dim=-1)
    jump = (with_contact.canonical[1:] - with_contact.canonical[:-1]).norm(dim=-1)
    assert bool(with_contact.valid.all())
    assert (jump / step).max().item() < 3.0  # Lipschitz across the blend: no tear, no fold


def test_the_densest_candidate_is_picked_per_point_ties_to_the_first():
    rows = torch.tensor([0, 3, 0, 3, 5])
    sigma = torch.tensor([1.0, 2.0, 4.0, 2.0, 0.0])
    at, pick = denser(rows, sigma)
    assert at.tolist() == [0, 3, 5]
    assert pick.tolist() == [2, 1, 4]


def test_a_ray_past_a_hand_on_the_hip_renders_the_trousers():
    """Through the renderer: a ray down z through p (2 cm off the hip, 1 cm off the hand) meets cloth only
    when the surfaces in contact are told apart; its gradient reaches the field."""
    faces = trimesh.creation.icosphere(subdivisions=4).faces
    faces = torch.tensor(np.concatenate([faces, faces + len(HIP)]), dtype=torch.int64)
    meshes = {}
    for cell in (0.0, CELL):
        skin = two_parts([HIP, HAND], [STILL, hand_at(0.17)], torch.float32, cell, near_cell=0.01, near_pad=0.15)
        meshes[cell] = PosedMesh(
            skin.posed, faces, torch.full((len(skin.posed), 3), 0.5), skin.posed[:, :2] * 100, skin
        )
    scale = torch.ones((), requires_grad=True)

    def nerf(x):
        r = x.norm(dim=-1)
        dens = torch.where((r > 0.1) & (r < 0.125), 200.0 * scale, torch.zeros_like(r))
        return torch.tensor([0.9, 0.1, 0.1]).expand(len(x), 3), dens

    o = torch.tensor([[0.12, 0.0, 1.0]])
    dirs = torch.tensor([[0.0, 0.0, -1.0]])
    masks = {}
    st = RenderSettings(samples=64, box_margin=0.2, max_dist=0.1, perturb=False)
    for cell, mesh in meshes.items():
        masks[cell] = render_rays(mesh, o, dirs, o[:, :2] * 100, torch.ones(3), st, nerf).nerf_mask
    assert masks[0.0].item() < 0.05  # the hand's side of the map is bare
    assert masks[CELL].item() > 0.9
    masks[CELL].sum().backward()
    assert scale.grad is not None and scale.grad.item() > 0


def test_a_pose_without_contact_deforms_as_without_the_probe():
    points = HIP[::7] * 1.15  # 1.5 cm off the hip
    apart = two_parts([HIP, HAND], [STILL, STILL])  # the hand 0.46 m off the hip
    assert apart.sparse is None and apart.touching is None
    plain = two_parts([HIP, HAND], [STILL, STILL], contact_cell=0)
    a, b = deform(apart, points), deform(plain, points)
    assert a.other is None
    torch.testing.assert_close(a.canonical, b.canonical, rtol=0, atol=0)
    touching = two_parts([HIP, HAND], [STILL, hand_at(0.17)]).touching
    # the vertices near the contact are flagged, those on the hip's far side are not
    posed = torch.cat([HIP, HAND + torch.tensor([0.17 - 0.6, 0, 0], dtype=D)])
    assert bool(touching[posed[:, 0] > 0.08].all()) and not bool(touching[posed[:, 0] < -0.05].any())


def test_the_probe_subset_keeps_one_vertex_per_voxel_the_nearest_its_centre():
    gen = torch.Generator().manual_seed(3)
    pts = torch.rand(4000, 3, generator=gen, dtype=D) * 0.3 - 0.1
    cell = 0.05
    picked = voxel_subset(pts, cell)
    key = torch.floor(pts / cell)
    best = {}
    for i, (kk, p) in enumerate(zip(map(tuple, key.tolist()), pts)):
        off = float((p / cell - torch.tensor(kk, dtype=D) - 0.5).norm())
        if kk not in best or off < best[kk][0]:
            best[kk] = (off, i)
    assert picked.tolist() == sorted(i for _, i in best.values())


def test_the_early_cull_keeps_samples_near_a_contact():
    """The rough map (the voxel's nearest vertex: the hand's) of a point in the trousers lands where the
    occupancy grid is empty; near a contact the sample is kept for the exact candidates."""
    p = torch.tensor([[0.12, 0.0, 0.0], [-0.3, 0.0, 0.0]], dtype=D)  # in the trousers beside the hand; far off

    def occupied(x, grow=0):
        return TROUSERS(x) > 0

    for cell, kept in ((0.0, [False, False]), (CELL, [True, False])):
        skin = two_parts([HIP, HAND], [STILL, hand_at(0.17)], contact_cell=cell, near_cell=0.01, near_pad=0.15)
        assert early_cull(skin, p, 0.1, occupied).tolist() == kept
