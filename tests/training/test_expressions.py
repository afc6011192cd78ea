"""An avatar of a tracked face: per-frame expressions pose its mesh, train with the pose, and travel in
checkpoints; an avatar without them is the one it always was."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.body.lbs import lbs
from delta.cameras.models import OrthographicCamera
from delta.body.face_points import FacePoints
from delta.data.frames import RayBatch
from delta.io import save_npz
from delta import losses as L
from delta.models.avatar import HybridAvatar, InitParams
from delta.models.init import load_init
from delta.training.presets import resolve
from delta.training.run import load_init_from_state
from delta.training.trainer import face_targets, loss_terms
from tests.test_extremes import blob_body

N, E = 3, 4


def face_body():
    body = blob_body()
    gen = torch.Generator().manual_seed(1)
    return dataclasses.replace(body, exprdirs=0.03 * torch.randn(body.num_vertices, 3, E, generator=gen),
                               expression_names=[f"a{k}" for k in range(E)]).validate("face blob")  # fmt: skip


def init(expression=None):
    camera = OrthographicCamera(torch.full((N,), 1.5), torch.zeros(N, 2), 32, 32)
    poses = 0.2 * torch.randn(N, 3, 3, generator=torch.Generator().manual_seed(2))
    return InitParams(torch.zeros(4), poses, torch.zeros(N, 3), camera, expression)


def avatar(body, params):
    st = resolve("fast", {"render": {"samples": 8}})
    spec = dataclasses.replace(st.avatar, nerf=None)
    return HybridAvatar(body, spec, params, torch.tensor([0.8, 0.6, 0.5]), torch.ones(3), 32)


def test_each_frame_is_posed_with_its_expression():
    body = face_body()
    acts = torch.rand(N, E, generator=torch.Generator().manual_seed(3))
    model = avatar(body, init(acts))
    for f in range(N):
        out = model.pose_body(f, model.offsets())
        ref = lbs(body, model.betas[None], model.poses[f : f + 1], acts[f : f + 1], offsets=model.offsets(),
                  transl=model.transl[f : f + 1])  # fmt: skip
        torch.testing.assert_close(out.vertices, ref.vertices)
    neutral = lbs(body, model.betas[None], model.poses[:1], offsets=model.offsets(), transl=model.transl[:1])
    assert (model.pose_body(0, model.offsets()).vertices - neutral.vertices).abs().max() > 1e-3
    # a frame's expression moves only with that frame's loss, in the pose group, as a per-frame parameter
    model.pose_body(1, model.offsets()).vertices.square().sum().backward()
    grad = model.expression.grad
    assert grad[1].abs().sum() > 0 and grad[0].abs().sum() == 0 and grad[2].abs().sum() == 0
    pose_group = next(g for g in model.param_groups(resolve("fast").stage1.lr) if g["name"] == "pose")
    assert any(p is model.expression for p in pose_group["params"])
    assert any(p is model.expression for p in model.per_frame_parameters())


def test_a_still_face_models_no_expression():
    model = avatar(face_body(), init())
    assert model.expression is None and "expression" not in model.state_dict()


def test_expressions_travel_in_the_checkpoint(tmp_path):
    acts = torch.rand(N, E, generator=torch.Generator().manual_seed(4))
    model = avatar(face_body(), init(acts))
    with torch.no_grad():
        model.expression.add_(0.1)
    data = SimpleNamespace(camera=None, resolution=32)
    again = load_init_from_state(model.state_dict(), data)
    torch.testing.assert_close(again.expression, acts + 0.1)
    assert load_init_from_state(avatar(face_body(), init()).state_dict(), data).expression is None


def test_expressions_that_do_not_fit_are_refused(tmp_path):
    with pytest.raises(ValueError, match="6 expression coefficients, the body model 'blob' 0"):
        avatar(blob_body(), init(torch.zeros(N, 6)))
    path = tmp_path / "params.npz"
    save_npz(path, betas=np.zeros(4), poses=np.zeros((N, 3, 3)), transl=np.zeros((N, 3)), frame_ids=np.arange(N),
             camera_model=np.array("pinhole"), expression=np.zeros((N + 1, E)))  # fmt: skip
    data = SimpleNamespace(frame_ids=np.arange(N), camera=None, resolution=32)
    with pytest.raises(DeltaError, match="'expression' has 4 rows for 3 frames"):
        load_init(path, data)


def _batch(frame: int, rays: int = 8) -> RayBatch:
    px = torch.rand(rays, 2, generator=torch.Generator().manual_seed(5)) * 32
    return RayBatch(frame, px, torch.full((rays, 3), 0.5), torch.ones(rays), torch.zeros(rays), torch.ones(rays))


def test_the_face_points_term_pulls_the_face_to_its_detections():
    """Posed face points projected by the frame's camera, against detections 3 px right and 4 px down:
    the term is the Huber of 5 px over the image's 32, and a step along its gradient brings them nearer."""
    acts = torch.rand(N, E, generator=torch.Generator().manual_seed(6))
    model = avatar(face_body(), init(acts))
    points = FacePoints.at_vertices([0, 5, 9, 17])
    st = resolve("fast", {"weights": {"face_points": 10.0}})
    with torch.no_grad():
        uv, _ = model.camera(1).project(points(model.pose_body(1, model.offsets()).vertices)[0])
    seen = torch.cat([uv + torch.tensor([3.0, 4.0]), torch.ones(4, 1)], 1)
    terms, _ = loss_terms(model, _batch(1), st, torch.tensor([0.8, 0.6, 0.5]), face=(points, seen))
    r = 5.0 / 32
    torch.testing.assert_close(terms["face_points"], torch.tensor(L.FACE_DELTA * (r - L.FACE_DELTA / 2)))
    terms["face_points"].backward()
    with torch.no_grad():  # the orthographic frame moves the face by its translation: a small step down it
        model.transl -= 1e-3 * model.transl.grad / model.transl.grad.norm()
        moved, _ = model.camera(1).project(points(model.pose_body(1, model.offsets()).vertices)[0])
    assert (moved - seen[:, :2]).norm(dim=1).mean() < (uv - seen[:, :2]).norm(dim=1).mean()
    assert model.transl.grad[0].abs().sum() == 0 and model.transl.grad[2].abs().sum() == 0  # that frame's only
    # without detections for the frame, or with the term off, there is none
    assert "face_points" not in loss_terms(model, _batch(1), st, torch.tensor([0.8, 0.6, 0.5]))[0]
    data = SimpleNamespace(face=points, face_points=seen[None].expand(N, -1, -1))
    assert face_targets(data, resolve("fast"), "cpu") is None
    assert face_targets(SimpleNamespace(face=None, face_points=None), st, "cpu") is None
    taken = face_targets(data, st, "cpu")
    assert torch.equal(taken[0].vertex_ids, points.vertex_ids) and taken[1].shape == (N, 4, 3)
