"""Reenactment: a head avatar driven by another's expressions and head motion."""

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from delta import DeltaError
from delta.applications.reenact import avatar_drive, check_driver, reenact_frames, still_drive
from delta.body.face_motion import driven_face, face_joints
from delta.models.image import render_image
from tests.training.test_expressions import E, N, avatar, face_body, init

ANNY_NAMES = ["root", "pelvis.L", "spine01", "clavicle.L", "upperarm01.L", "wrist.L", "neck01", "neck02", "neck03",
              "head", "eye.L", "eye.R"]  # fmt: skip
SMPLX_NAMES = ["pelvis", "spine3", "neck", "left_collar", "head", "jaw", "left_eye_smplhf", "right_eye_smplhf",
               "left_wrist"]  # fmt: skip


def test_the_face_joints_are_the_neck_head_jaw_and_eyes():
    assert [ANNY_NAMES[j] for j in face_joints(ANNY_NAMES)] == ["neck01", "neck02", "neck03", "head", "eye.L", "eye.R"]
    assert [SMPLX_NAMES[j] for j in face_joints(SMPLX_NAMES)] == ["neck", "head", "jaw", "left_eye_smplhf",
                                                                  "right_eye_smplhf"]  # fmt: skip


def test_the_driver_turn_from_its_reference_goes_on_top_of_the_target_pose():
    gen = np.random.default_rng(0)
    target = torch.tensor(gen.normal(size=(4, 3)) * 0.4)
    driver = torch.tensor(gen.normal(size=(5, 4, 3)) * 0.4)
    joints = [1, 3]
    got = driven_face(target, driver, reference=driver[2], joints=joints)
    for f in range(5):
        for k, j in enumerate(joints):
            want = (Rotation.from_rotvec(driver[f, j]) * Rotation.from_rotvec(driver[2, j]).inv()
                    * Rotation.from_rotvec(target[j]))  # fmt: skip
            np.testing.assert_allclose(Rotation.from_rotvec(got[f, k].numpy()).as_matrix(), want.as_matrix(), atol=1e-9)
    # the reference frame itself leaves the target's pose as it was
    np.testing.assert_allclose(Rotation.from_rotvec(got[2].numpy()).as_matrix(),
                               Rotation.from_rotvec(target[joints].numpy()).as_matrix(), atol=1e-9)  # fmt: skip


def head_avatar(seed=3):
    body = dataclasses.replace(face_body(), joint_names=["root", "head", "neck01"])
    acts = torch.rand(N, E, generator=torch.Generator().manual_seed(seed))
    return avatar(body, init(acts))


def test_driving_an_avatar_with_itself_reproduces_its_frames_and_restores_it():
    model = head_avatar()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    times = model.frame_time.clone()
    anchor = 1
    own = render_image(model, anchor, soft_silhouette=False)["rgb"]
    images = [img["rgb"] for img in reenact_frames(model, anchor, avatar_drive(model, [anchor, 0, 2], anchor), None)]
    # its own frame with itself as the reference: the anchor's render, as is the anchor not driven at all
    torch.testing.assert_close(images[0], own, rtol=0, atol=1e-5)
    (still,) = reenact_frames(model, anchor, still_drive(model, anchor, 1), None)
    torch.testing.assert_close(still["rgb"], own, rtol=0, atol=1e-5)
    # another frame's face: its expression and its head and neck rotations, on the anchor's root
    for img, f in zip(images[1:], (0, 2)):
        assert torch.isfinite(img).all()
        assert (img - own).abs().max() > 1e-3
        posed = model.poses.data.clone()
        posed[anchor, 1:] = posed[f, 1:]
        expr = model.expression.data.clone()
        expr[anchor] = expr[f]
        with torch.no_grad():
            ref = head_avatar()
            ref.poses.data.copy_(posed)
            ref.expression.data.copy_(expr)
            ref.load_state_dict({k: v for k, v in model.state_dict().items() if k not in ("poses", "expression")},
                                strict=False)  # fmt: skip
            ref.frame_time[anchor] = float("nan")
            want = render_image(ref, anchor, soft_silhouette=False)["rgb"]
        torch.testing.assert_close(img, want, rtol=0, atol=1e-4)
    for k, v in model.state_dict().items():
        torch.testing.assert_close(v, before[k], rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(model.frame_time, times, equal_nan=True)


def test_a_still_face_or_another_expression_space_is_refused():
    model = head_avatar()
    still = avatar(dataclasses.replace(face_body(), joint_names=["root", "head", "neck01"]), init())
    with pytest.raises(DeltaError, match="without expressions"):
        check_driver(model, still)
    with pytest.raises(DeltaError, match="without expressions"):
        check_driver(still, model)
    other = head_avatar()
    other.expression = torch.nn.Parameter(torch.zeros(N, E + 1))
    with pytest.raises(DeltaError, match=f"{E + 1} expression coefficients, the avatar {E}"):
        check_driver(model, other)


def test_a_missing_driver_is_named(tmp_path):
    from delta.applications.reenact import reenact_avatar

    for name in ("model.pt", "frames.h5", "body.npz"):
        (tmp_path / name).write_bytes(b"x")
    with pytest.raises(DeltaError, match="driver_model.*nowhere.pt|nowhere.pt"):
        reenact_avatar(tmp_path / "model.pt", tmp_path / "frames.h5", tmp_path / "body.npz", tmp_path / "nowhere.pt",
                       tmp_path / "frames.h5", tmp_path / "out")  # fmt: skip
