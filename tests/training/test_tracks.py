"""Points of the exterior tracked between training frames, the canonical points their rays see, the track term."""

import numpy as np
import pytest
import torch

from delta import losses as L
from delta.data.tracks import EDGE_MARGIN, MAX_CORNERS, Frame, corners, follow, frame_tracks
from delta.render.hybrid import exterior_surface, render_rays
from delta.render.settings import RenderSettings
from tests.render.test_hybrid import BG, rays, sphere_avatar


def track_pair(image_a, image_b, mask_a, mask_b, max_corners=MAX_CORNERS):
    """Corners of ``mask_a``'s region followed into the next frame: (M, 2) ray pixels in a and in b."""
    a, b = Frame.of(image_a, mask_a), Frame.of(image_b, mask_b)
    start = corners(a, max_corners)
    kept, end = follow(a, b, start)
    return start[kept] + 0.5, end + 0.5


def texture(h=96, w=96, seed=0):
    """A random blotchy texture in [0, 1] (corners everywhere, no repeats for the tracker to confuse)."""
    rng = np.random.default_rng(seed)
    small = rng.random((h // 6, w // 6, 3)).astype(np.float32)
    import cv2

    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 1)


def shifted(img, dx, dy):
    out = np.roll(np.roll(img, dy, axis=0), dx, axis=1)
    return out


def test_a_shifted_texture_is_tracked_by_its_shift():
    a = texture()
    b = shifted(a, 3, -2)
    mask = np.zeros(a.shape[:2], np.float32)
    mask[20:76, 20:76] = 1.0
    pa, pb = track_pair(a, b, mask, shifted(mask, 3, -2))
    assert len(pa) >= 20
    np.testing.assert_allclose(pb - pa, np.tile([3.0, -2.0], (len(pa), 1)), atol=0.1)
    # ray pixels: a pixel's centre at (column + 0.5, row + 0.5); starts inside the mask, off its edge
    cols, rows = np.floor(pa[:, 0]).astype(int), np.floor(pa[:, 1]).astype(int)
    assert (cols >= 20 + EDGE_MARGIN).all() and (cols < 76 - EDGE_MARGIN).all()
    assert (rows >= 20 + EDGE_MARGIN).all() and (rows < 76 - EDGE_MARGIN).all()


def test_points_that_leave_the_exterior_or_cannot_be_tracked_back_are_dropped():
    a = texture()
    mask = np.zeros(a.shape[:2], np.float32)
    mask[10:86, 10:86] = 1.0
    b = shifted(a, 2, 0)
    half = mask.copy()
    half[:, 48:] = 0.0  # the next frame's exterior covers the left half only
    pa, pb = track_pair(a, b, mask, half)
    assert len(pa) > 0 and (pb[:, 0] < 48 - EDGE_MARGIN + 0.5).all()
    # the right half of the next frame shows another texture: nothing tracked there survives the check back
    c = b.copy()
    c[:, 48:] = texture(seed=7)[:, 48:]
    pa, pb = track_pair(a, c, mask, mask)
    assert len(pa) > 0 and (pb[:, 0] < 48 + 2).all()
    # no exterior, or a flat image: nothing
    assert len(track_pair(a, b, np.zeros_like(mask), mask)[0]) == 0
    flat = np.full_like(a, 0.5)
    assert len(track_pair(flat, flat, mask, mask)[0]) == 0


def test_tracks_follow_the_exterior_through_the_training_frames_and_end_at_a_cut():
    base = texture(80, 80)
    ids = np.array([0, 1, 2, 3, 4, 20, 21])  # frame 2 held out; 4 -> 20 is a cut
    images = torch.from_numpy(np.stack([shifted(base, int(i) % 20, 0) for i in ids]))
    mask = np.zeros((80, 80), np.float32)
    mask[10:70, 10:44] = 1.0
    exterior = torch.from_numpy(np.stack([shifted(mask, int(i) % 20, 0) for i in ids]))
    train = np.array([6, 0, 1, 3, 4, 5])  # any order
    tr = frame_tracks(images, exterior, ids, train, max_gap=2)
    seen = ~tr.pixels[..., 0].isnan()
    assert tr.count > 10 and not seen[:, 2].any()  # never in the held-out frame
    assert not (seen[:, :5].any(1) & seen[:, 5:].any(1)).any()  # none across the cut
    assert (seen.sum(1) >= 2).all()
    long = seen[:, [0, 1, 3, 4]].all(1)  # followed through the whole first part
    assert long.sum() > 10
    steps = tr.pixels[long][:, [1, 3, 4]] - tr.pixels[long][:, [0, 1, 3]]
    torch.testing.assert_close(steps, torch.tensor([[1.0, 0.0], [2.0, 0.0], [1.0, 0.0]]).expand_as(steps), atol=0.15,
                               rtol=0)  # fmt: skip
    torch.testing.assert_close(tr.shared, tr.shared.T)
    assert int(tr.shared[0, 0]) == int(seen[:, 0].sum()) and int(tr.shared[0, 4]) == int(long.sum())
    assert set(tr.partners(0).tolist()) == {1, 3, 4} and set(tr.partners(5).tolist()) == {6}
    start, end = tr.between(0, 4)
    assert len(start) == int(long.sum())
    torch.testing.assert_close(end - start, torch.tensor([4.0, 0.0]).expand_as(start), atol=0.3, rtol=0)


def test_the_track_term_by_hand():
    u = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
    a = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    # the first gap: 5 mm across the rays and 2 cm along them (left out); the third's ray is not opaque
    b = torch.tensor([[0.003, 0.004, 0.02], [1.0, 0.0, 0.0], [5.0, 0.0, 0.0]], requires_grad=True)
    opaque = torch.tensor([1.0, 0.9, 0.2])
    value = L.track(a, b, u, u, opaque, torch.ones(3))
    eps = L.TRACK_EPS
    expected = (np.sqrt(0.005**2 + eps**2) + eps) / 2
    assert float(value.detach()) == pytest.approx(expected, rel=1e-5)
    value.backward()
    assert torch.isfinite(b.grad).all() and b.grad[1].abs().sum() == 0 and b.grad[2].abs().sum() == 0
    torch.testing.assert_close(b.grad[0], torch.tensor([0.003, 0.004, 0.0]) / np.sqrt(0.005**2 + eps**2) / 2)
    assert float(L.track(a, b.detach(), u, u, torch.zeros(3), torch.ones(3))) == 0.0
    # the rays' directions in the two frames are averaged: opposite halves of a turn leave the mean's
    tilted = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 1.0]]), dim=-1).expand(3, 3)
    other = torch.nn.functional.normalize(torch.tensor([[-1.0, 0.0, 1.0]]), dim=-1).expand(3, 3)
    gap = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    moved = torch.tensor([[0.01, 0.0, 0.03], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    value = L.track(moved, gap, tilted, other, torch.tensor([1.0, 0.0, 0.0]), torch.ones(3))
    assert float(value) == pytest.approx(np.sqrt(0.01**2 + eps**2), rel=1e-5)


def test_the_surface_a_ray_sees_is_where_the_exterior_is():
    mesh = sphere_avatar(0.3)

    def nerf(x):
        r = x.norm(dim=-1)
        return torch.full_like(x, 0.5), torch.where((r > 0.32) & (r < 0.34), 400.0, 0.0)

    o, d = rays([0.0, 0.1, 0.2, 0.5])  # the last passes 0.2 m from the shell: no exterior
    st = RenderSettings(samples=64, box_margin=0.3, max_dist=0.1, perturb=False)
    point, opacity = exterior_surface(mesh, o, d, st, nerf)
    full = render_rays(mesh, o, d, o[:, :2] * 100, BG, st, nerf)
    torch.testing.assert_close(opacity, full.nerf_mask)
    assert (opacity[:3] > 0.99).all() and float(opacity[3]) == 0.0
    torch.testing.assert_close(point[:, :2], o[:, :2], atol=1e-5, rtol=0)  # along the rays (x, 0)
    r = point[:3].norm(dim=-1)
    assert ((r > 0.32) & (r < 0.345)).all() and (point[:3, 2] > 0).all()  # the shell's side facing the camera
    # a constant offset F_e moves the shell the other way in posed space
    offset = torch.tensor([0.0, 0.0, 0.01])
    moved, _ = exterior_surface(mesh, o[:1], d[:1], st, nerf, lambda x, ref: offset.expand_as(x))
    assert float(moved[0, 2]) == pytest.approx(float(point[0, 2]) - 0.01, abs=0.002)


@pytest.mark.slow
def test_canonical_points_move_with_f_e_alone(tiny_training):
    from delta.body.model import load_body_model
    from delta.data.frames import load_frames
    from delta.models.init import load_init
    from delta.training.presets import resolve
    from delta.training.run import build_avatar

    st = resolve("fast", {"resolution": 32, "render": {"samples": 8}})
    inputs = tiny_training["loose"]
    data = load_frames(inputs["record"], st.resolution, st.background, st.box_margin)
    model = build_avatar(load_body_model(inputs["body"]), st, load_init(inputs["init"], data), data, 2,
                         torch.device("cpu"))  # fmt: skip
    frame = int(data.train[0])
    inside = torch.nonzero(data.exterior[frame] > 0.5)[:, [1, 0]].float() + 0.5
    points, along, opacity = model.canonical_points(frame, inside[:64])
    assert points.shape == (len(inside[:64]), 3) and torch.isfinite(points).all()
    torch.testing.assert_close(along.norm(dim=-1), torch.ones(len(points)))
    (points * opacity[:, None]).sum().backward()
    assert model.poses.grad is None and all(p.grad is None for p in model.nerf.parameters())
    assert sum(float(p.grad.abs().sum()) for p in model.deformation.parameters() if p.grad is not None) > 0


def test_a_step_that_disagrees_with_its_neighbours_is_dropped():
    from delta.data.tracks import coherent

    g = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0)), -1).reshape(-1, 2) * 5
    steps = np.tile([2.0, -1.0], (len(g), 1)) + 0.05 * np.sin(g)  # a smooth motion
    steps[14] += [11.0, 0.0]  # one point matched on the next dot of a repeating pattern
    keep = coherent(g, steps)
    assert not keep[14] and keep[np.arange(len(g)) != 14].all()
    assert coherent(g[:5], steps[:5]).all()  # too few points to tell: all kept


@pytest.mark.slow
def test_stage_2_trains_with_the_track_term(tiny_training, tmp_path, perceptual_weights, monkeypatch):
    """Two stage-2 steps with ``weights.track`` on: the term is logged and finite in stage 2, absent in stage 1
    (tracks made by hand where the tiny capture's exterior is, the same pixels in every frame)."""
    import pandas as pd

    import delta.training.trainer as trainer
    from delta.data.frames import load_frames
    from delta.data.tracks import Tracks
    from delta.training.run import run_stage

    inputs = tiny_training["loose"]
    tiny = {"resolution": 32, "render": {"samples": 8}, "weights": {"track": 1.0}, "dynamics": {"dropout": 0.0},
            "stage1": {"iterations": 2, "rays": 64, "preview_every": 0},
            "stage2": {"iterations": 2, "rays": 64, "patch": 0, "preview_every": 0}}  # fmt: skip
    data = load_frames(inputs["record"], 32)
    inside = torch.nonzero(data.exterior[: len(data.frame_ids)].amin(0) > 0.5)[:, [1, 0]].float() + 0.5
    assert len(inside) >= 8
    pixels = inside[None].expand(len(data.frame_ids), -1, -1).transpose(0, 1).clone()
    seen = torch.zeros(len(data.frame_ids), dtype=torch.bool)
    seen[torch.as_tensor(data.train)] = True
    pixels[:, ~seen] = float("nan")
    counts = seen.long()[:, None] * seen.long()[None] * len(inside)
    monkeypatch.setattr(trainer, "frame_tracks", lambda *a, **k: Tracks(pixels, counts))
    monkeypatch.setattr(trainer, "TRACK_LEAST", 1)
    run_stage(1, inputs["record"], inputs["body"], inputs["init"], str(tmp_path / "s1"), "fast", [tiny])
    run_stage(2, inputs["record"], inputs["body"], str(tmp_path / "s1" / "model.pt"), str(tmp_path / "s2"), "fast",
              [tiny], perceptual_dir=str(perceptual_weights))  # fmt: skip
    losses = pd.read_csv(tmp_path / "s2" / "losses.csv")
    assert "track" not in pd.read_csv(tmp_path / "s1" / "losses.csv")  # stage 1 has no F_e to move
    assert "track" in losses and np.isfinite(losses["track"].dropna()).all() and losses["track"].notna().any()
