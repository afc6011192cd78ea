"""A tracked face's expressions scored against a capture's truth: names matched, errors by hand and
through the body model's own skinning."""

import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.body.lbs import lbs
from delta.eval.expressions import AvatarExpressions, expression_errors, face_moved, truth_expressions
from tests.training.test_expressions import N, avatar, face_body, init


def _truth_file(path, values, names):
    np.savez(path, expression=np.asarray(values, np.float32), expression_names=np.array(names))
    return path


def test_errors_by_hand_with_actions_matched_by_name(tmp_path):
    # the truth lists its actions in another order and has one the model lacks ("d")
    params = _truth_file(tmp_path / "params.npz", [[0.0, 0.0, 0.0], [0.1, 0.2, 0.3]], ["b", "a", "d"])
    truth = truth_expressions(params, [1], ["a", "b", "c"])
    np.testing.assert_allclose(truth.values[1], [0.2, 0.1, 0.0], rtol=1e-6)
    np.testing.assert_allclose(truth.unmodelled[1], [0.3], rtol=1e-6)
    dirs = torch.zeros(3, 3, 3)
    dirs[0, 0, 0] = 1.0  # "a" moves vertex 0 along x by 1 m a unit
    dirs[1, 1, 1] = 2.0  # "b" moves vertex 1 along y by 2 m a unit; "c" and vertex 2 move nothing
    moved = face_moved(dirs)
    assert moved.tolist() == [True, True, False]
    err = expression_errors(torch.tensor([0.5, 0.0, 0.0]), truth, 1, dirs, moved)
    # differences a +0.3, b -0.1, c 0, and d fitted at 0 against 0.3
    assert err["expr_mae"] == pytest.approx((0.3 + 0.1 + 0.0 + 0.3) / 4, rel=1e-6)
    assert err["expr_err_mm"] == pytest.approx(1000 * (0.3 * 1.0 + 0.1 * 2.0) / 2, rel=1e-6)


def test_an_avatars_errors_are_its_faces_displacement_through_skinning(tmp_path):
    body = face_body()
    acts = torch.rand(N, 4, generator=torch.Generator().manual_seed(5))
    model = avatar(body, init(acts))
    ids = [10, 11, 12]  # the frames' video ids
    truth = np.zeros((13, 4), np.float32)
    truth[ids] = acts.numpy()
    truth[11, 2] += 0.25  # one action of one frame off
    params = _truth_file(tmp_path / "params.npz", truth, body.expression_names)
    scorer = AvatarExpressions.of(model, params, ids)
    assert scorer(0, 10) == pytest.approx({"expr_mae": 0.0, "expr_err_mm": 0.0}, abs=1e-6)
    err = scorer(1, 11)
    assert err["expr_mae"] == pytest.approx(0.25 / 4, rel=1e-5)
    # an independent route: the neutral body skinned with the fitted and the true activations
    rest = torch.zeros(1, body.num_joints, 3)
    fit = lbs(body, torch.zeros(1, body.num_shape), rest, acts[1:2]).vertices[0]
    true = lbs(body, torch.zeros(1, body.num_shape), rest, torch.from_numpy(truth[11:12])).vertices[0]
    moved = body.exprdirs.abs().flatten(1).amax(1) > 0
    assert err["expr_err_mm"] == pytest.approx(1000 * float((fit - true)[moved].norm(dim=1).mean()), rel=1e-4)


def test_nothing_to_score_and_files_that_do_not_fit(tmp_path):
    body = face_body()
    still = avatar(body, init())
    params = _truth_file(tmp_path / "params.npz", np.zeros((3, 4)), body.expression_names)
    assert AvatarExpressions.of(still, params, [0]) is None  # a still face: no expressions modelled
    np.savez(tmp_path / "still.npz", betas=np.zeros(4))
    talking = avatar(body, init(torch.zeros(N, 4)))
    assert AvatarExpressions.of(talking, tmp_path / "still.npz", [0]) is None  # the capture made none
    with pytest.raises(DeltaError, match="no expression for frame 7 \\(it holds 3 frames\\)"):
        AvatarExpressions.of(talking, params, [0, 7])
    np.savez(tmp_path / "unnamed.npz", expression=np.zeros((3, 4)))
    with pytest.raises(DeltaError, match="unnamed.npz: 'expression' without 'expression_names'"):
        truth_expressions(tmp_path / "unnamed.npz", [0], body.expression_names)
    with pytest.raises(DeltaError, match="missing.npz: no such ground-truth parameter file"):
        truth_expressions(tmp_path / "missing.npz", [0], body.expression_names)
