"""The round trip of backward skinning: a posed point keeps its canonical point only where the part nearest
that canonical point carries it back (``deformers/knn.py``, ``render.round_trip``).

The bodies are rigid parts of icosphere and tube vertices (``test_contact``'s), a canonical density field
stands for the NeRF. The case that needs it: an arm that hangs beside the torso in the canonical space is
crossed in front of the chest; the empty space where it hung is nearest the torso in the pose, and the
torso's map takes it back to the canonical sleeve.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from delta.deformers.knn import canonical_grid, deform, prepare, round_trip
from tests.deformers.test_contact import D, rigid, rot_z, shell, sphere, tube

STILL = rigid(np.eye(3), (0, 0, 0))
TORSO = sphere((0, 0, 0), 0.15)
ARM = sphere((0.3, 0, 0), 0.05)  # hangs beside the torso in the canonical space
SLEEVE = shell((0.3, 0, 0), 0.05, 0.07)
SHIRT = shell((0, 0, 0), 0.15, 0.17)
CROSSED = rigid(np.eye(3), (-0.3, 0, 0.3))  # the arm's centre in front of the chest, at (0, 0, 0.3)


def parts(canonical_parts, transforms, trip=True, cell=0.01, pad=0.25):
    """Skinning frame of rigid parts (canonical = the canonical vertices), with the round trip's grid."""
    verts = torch.cat(canonical_parts)
    part = torch.cat([torch.full((len(v),), i, device=verts.device) for i, v in enumerate(canonical_parts)])
    G = torch.stack(transforms)[part]
    posed = (G[..., :3] @ verts[..., None]).squeeze(-1) + G[..., 3]
    eye = torch.eye(3, 4, dtype=D, device=verts.device).expand(len(verts), 3, 4)
    weights = torch.nn.functional.one_hot(part, len(canonical_parts)).to(D)
    grid = canonical_grid(verts, cell, pad) if trip else None
    return prepare(posed, G, torch.zeros_like(verts), eye, weights, canonical_near=grid)


def density(frame, points, field, max_dist=0.2):
    d = deform(frame, points, k=6, sigma=0.1, max_dist=max_dist)
    return torch.where(d.valid, field(d.canonical), torch.zeros(len(points), dtype=D))


def test_a_crossed_arm_leaves_no_sleeve_where_it_hung():
    ghost = torch.tensor([[0.24, 0.0, 0.0], [0.25, 0.03, 0.0]], dtype=D)  # 9-10 cm off the torso, in empty space
    plain = parts([TORSO, ARM], [STILL, CROSSED], trip=False)
    assert density(plain, ghost, SLEEVE).tolist() == [1.0, 1.0]  # backward skinning's ghost
    frame = parts([TORSO, ARM], [STILL, CROSSED])
    assert density(frame, ghost, SLEEVE).tolist() == [0.0, 0.0]
    # the part nearest the ghost's canonical point (the arm, 1 cm off) carries it by the arm's shift, 0.3√2 m
    d = deform(frame, ghost[:1], max_dist=0.2)
    assert math.isclose(round_trip(frame, ghost[:1], d.canonical).item(), 0.3 * math.sqrt(2), rel_tol=1e-9)


def test_the_sleeve_is_where_the_arm_is_and_the_shirt_where_the_torso_is():
    frame = parts([TORSO, ARM], [STILL, CROSSED])
    sleeve = torch.tensor([[0.06, 0.0, 0.3], [0.0, 0.06, 0.3], [0.0, 0.0, 0.36]], dtype=D)
    assert density(frame, sleeve, SLEEVE).tolist() == [1.0, 1.0, 1.0]
    shirt = torch.tensor([[-0.16, 0.0, 0.0], [0.0, 0.16, 0.0], [0.0, -0.16, 0.0]], dtype=D)
    assert density(frame, shirt, SHIRT).tolist() == [1.0, 1.0, 1.0]
    # a rigid part's points come back exactly
    d = deform(frame, torch.cat([sleeve, shirt]), max_dist=0.2)
    assert round_trip(frame, torch.cat([sleeve, shirt]), d.canonical).max().item() < 1e-9


def test_a_pose_that_moves_nothing_apart_keeps_every_point_of_the_plain_blend():
    frame, plain = parts([TORSO, ARM], [STILL, STILL]), parts([TORSO, ARM], [STILL, STILL], trip=False)
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(2000, 3, generator=gen, dtype=D) * 0.8 - torch.tensor([0.3, 0.4, 0.4], dtype=D)
    a, b = deform(frame, pts, max_dist=0.2), deform(plain, pts, max_dist=0.2)
    assert bool(b.valid.any()) and torch.equal(a.valid, b.valid)
    torch.testing.assert_close(a.canonical, b.canonical, rtol=0, atol=0)


def test_a_bent_limb_keeps_its_cloth_across_the_joint():
    """A tube bent 60° at a joint with skinning blended over ±5 cm: the blended maps near the joint differ
    from the nearest vertex's, and cloth up to 8 cm off the tube on both sides passes the round trip."""
    verts = tube((0, 0, 0), (0.6, 0, 0), 0.05, rings=121, around=32)
    w1 = ((verts[:, 0] - 0.25) / 0.1).clamp(0, 1)
    weights = torch.stack([1 - w1, w1], dim=1)
    joint = torch.tensor([0.3, 0, 0], dtype=D)
    R = torch.tensor(rot_z(60), dtype=D)
    T1 = torch.cat([R, (joint - R @ joint)[:, None]], dim=1)
    G = weights[:, 0, None, None] * torch.eye(3, 4, dtype=D) + weights[:, 1, None, None] * T1
    posed = (G[..., :3] @ verts[..., None]).squeeze(-1) + G[..., 3]
    eye = torch.eye(3, 4, dtype=D).expand(len(verts), 3, 4)
    frame = prepare(posed, G, torch.zeros_like(verts), eye, weights, canonical_near=canonical_grid(verts, 0.01, 0.25))
    s = torch.linspace(0.1, 0.5, 161, dtype=D)
    for off in (-0.13, -0.08, 0.08, 0.13):  # 3 and 8 cm off the tube, outside and inside the bend
        line = torch.stack([s, torch.full_like(s, off), torch.zeros_like(s)], 1)
        line = torch.where((s > 0.3)[:, None], (R @ (line - joint).T).T + joint, line)
        d = deform(frame, line, max_dist=0.2)
        inside_bend = off > 0 and bool(((line - joint).norm(dim=-1) < 0.1).any())
        keep = d.valid.double().mean().item()
        assert keep == 1.0 or (inside_bend and keep > 0.9), (off, keep)


def test_a_canonical_point_off_the_grid_fails_and_nothing_is_not_a_number():
    frame = parts([TORSO, ARM], [STILL, CROSSED], pad=0.05)
    far = torch.tensor([[0.0, 0.0, 0.4], [float("nan"), 0.0, 0.0]], dtype=D)
    err = round_trip(frame, far, torch.tensor([[0.0, 0.0, 2.0], [float("nan"), 0.0, 0.0]], dtype=D))
    assert err.isinf().all()


def test_the_avatars_grid_holds_every_frames_canonical_vertices():
    """The grid is built once from the canonical transforms and the template: each frame's per-vertex maps
    (with shape, pose correctives and offsets) take its posed vertices to those same positions."""
    import dataclasses

    from delta.cameras.models import OrthographicCamera
    from delta.geometry.distance_grid import lookup
    from tests.test_extremes import tiny_avatar

    poses = 0.4 * torch.randn(3, 3, 3, generator=torch.Generator().manual_seed(1))
    cam = OrthographicCamera(torch.full((3, 4), 1.5), torch.zeros(3, 2), 32, 32)
    model, _ = tiny_avatar(cam, poses, torch.zeros(3, 3))
    for f in range(3):
        skin = model.posed_mesh(f)[0].skinning
        tc = skin.to_canonical.detach()
        canonical = (tc[..., :3] @ skin.posed.detach()[..., None]).squeeze(-1) + tc[..., 3]
        ids = model.knn_ids
        template = (model.canonical_T[ids, :, :3] @ model.body.v_template[ids, :, None]).squeeze(-1)
        torch.testing.assert_close(canonical, template + model.canonical_T[ids, :, 3], rtol=0, atol=2e-5)
        assert lookup(skin.canonical_near, canonical).max().item() <= math.sqrt(3) * skin.canonical_near.cell
        err = round_trip(skin, skin.posed.detach(), canonical)
        assert err.max().item() < 0.03  # a vertex's own canonical point comes back (to a neighbour's map)
    model.spec = dataclasses.replace(model.spec, render=dataclasses.replace(model.spec.render, round_trip=False))
    assert model.posed_mesh(0)[0].skinning.canonical_near is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_round_trip_on_cuda_keeps_what_the_cpu_keeps():
    """The same frame built on CUDA (grid, maps, points there) keeps and carries the same points."""
    gen = torch.Generator().manual_seed(2)
    pts = torch.rand(4000, 3, generator=gen, dtype=D) * 0.9 - torch.tensor([0.45, 0.45, 0.2], dtype=D)
    out = {}
    for dev in ("cpu", "cuda"):
        to = [t.to(dev) for t in (TORSO, ARM)]
        frame = parts(to, [STILL.to(dev), CROSSED.to(dev)])
        assert frame.canonical_near is not None
        d = deform(frame, pts.to(dev), max_dist=0.2)
        assert d.canonical.device.type == dev
        out[dev] = d.valid.cpu(), d.canonical.cpu()
    assert torch.equal(out["cpu"][0], out["cuda"][0]) and bool(out["cpu"][0].any()) and not bool(out["cpu"][0].all())
    keep = out["cpu"][0]
    torch.testing.assert_close(out["cuda"][1][keep], out["cpu"][1][keep], rtol=0, atol=1e-9)
