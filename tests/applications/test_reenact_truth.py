"""The generated truth of a reenactment: a subject's frame driven by another subject's face, and what scores
a reenactment against it."""

import json
from types import SimpleNamespace

import cv2
import h5py
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from delta import DeltaError
from delta.applications.reenact import score_reenactment, truth_drive
from delta.body.expressions import ExpressionSpace
from delta.body.face_motion import driven_poses, face_joints
from delta.body.model import load_body_model
from delta.synthetic.generate import face_actions, generate, motion, splits
from delta.synthetic.spec import parse_subject, reenacted_raw

#: a long-haired talker and a short-haired one, ten frames each at 64² (the held-out part from frame 6)
OWN = dict(seed=5, framing="head", motion="face", expressions="talk", hair="long", resolution=64, turn_frames=6,
           novel_frames=4, test_view_every=3)  # fmt: skip
DRIVER = dict(OWN, seed=9, hair="short", phenotype={"weight": 0.8})
ANCHOR, REFERENCE = 2, 7


def frames(video):
    cap = cv2.VideoCapture(str(video))
    out = []
    while True:
        ok, img = cap.read()
        if not ok:
            return np.stack(out)
        out.append(img)


def test_a_driven_subject_is_validated():
    ok = parse_subject("a.follows.b", reenacted_raw(OWN, DRIVER, ANCHOR, REFERENCE))
    assert ok.num_frames == 10 and ok.driven.by.seed == 9 and (ok.driven.anchor, ok.driven.reference) == (2, 7)
    for raw, match in (
        (reenacted_raw(OWN, DRIVER, 10, 0), r"driven.anchor: a frame in \[0, 10\), got 10"),
        (reenacted_raw(OWN, dict(DRIVER, novel_frames=0), 0, 6), r"driven.reference: a frame in \[0, 6\), got 6"),
        (reenacted_raw(OWN, dict(DRIVER, expressions="none"), 0, 0), "both subjects need talking faces"),
        (reenacted_raw(OWN, reenacted_raw(DRIVER, OWN), 0, 0), "a driving subject has its own motion"),
        ({**OWN, "driven": {"by": DRIVER}}, "a mapping with 'by'"),
        (reenacted_raw(OWN, dict(DRIVER, hair="curly")), r"driven\.by\.hair: unknown value 'curly'"),
    ):
        with pytest.raises(DeltaError, match=match):
            parse_subject("a.follows.b", raw)


@pytest.mark.slow
def test_the_truth_holds_the_anchor_still_and_moves_its_face_as_the_driver(tmp_path, anny_files,
                                                                           anny_expressions_file):  # fmt: skip
    run = lambda name, raw: generate(
        parse_subject(name, raw),
        anny_files["body"],
        tmp_path / name,  # noqa: E731
        anny_files["shape_space"],
        anny_files["cache"],
        anny_expressions_file,
    )
    run("a", OWN)
    run("a.follows.a", reenacted_raw(OWN, OWN, ANCHOR, ANCHOR))
    run("a.follows.b", reenacted_raw(OWN, DRIVER, ANCHOR, REFERENCE))

    # driven by itself from its anchor, the anchor frame is the capture's own, pixel for pixel
    own, itself = frames(tmp_path / "a" / "a.mp4"), frames(tmp_path / "a.follows.a" / "a.follows.a.mp4")
    assert np.array_equal(itself[ANCHOR], own[ANCHOR]) and not np.array_equal(itself[ANCHOR + 1], own[ANCHOR + 1])

    body = load_body_model(anny_files["body"])
    names, actions = body.joint_names, ExpressionSpace.load(anny_expressions_file).names
    spec_a, spec_b = parse_subject("a", OWN), parse_subject("b", DRIVER)
    pose_a, poses_b = motion(spec_a, names)[0][ANCHOR], motion(spec_b, names)[0]
    truth = tmp_path / "a.follows.b" / "gt"
    with np.load(truth / "params.npz") as p:
        poses, expression = p["poses"], p["expression"]
        assert (int(p["drive_anchor"]), int(p["drive_reference"])) == (ANCHOR, REFERENCE)
    assert np.array_equal(expression, face_actions(spec_b, actions)), "the driver's facial actions, as they are"
    assert json.loads((truth / "splits.json").read_text()) == splits(spec_b), "the driver's splits"
    face = face_joints(names)
    rest = [j for j in range(len(names)) if j not in face]
    assert len(face) == 6 and np.allclose(poses[:, rest], pose_a[rest], atol=1e-12), "the body holds the anchor's pose"
    for f in range(len(poses)):
        for j in face:  # R(f) R(ref)ᵀ is the driver's, R(ref) the anchor's
            got = Rotation.from_rotvec(poses[f, j]) * Rotation.from_rotvec(poses[REFERENCE, j]).inv()
            want = Rotation.from_rotvec(poses_b[f, j]) * Rotation.from_rotvec(poses_b[REFERENCE, j]).inv()
            np.testing.assert_allclose(got.as_matrix(), want.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(Rotation.from_rotvec(poses[REFERENCE, face]).as_matrix(),
                               Rotation.from_rotvec(pose_a[face]).as_matrix(), atol=1e-9)  # fmt: skip
    with h5py.File(truth / "meshes.h5") as m:
        verts = m["body_vertices"][:]
    low = verts[0][:, 1] < np.median(verts[0][:, 1])  # the shoulders and chest: they never move
    assert np.abs(verts[:, low] - verts[0, low]).max() < 1e-6 and np.abs(verts - verts[0]).max() > 0.01

    # the true drive, put on the avatar subject's true anchor pose, is the truth's own motion
    target = SimpleNamespace(body=SimpleNamespace(joint_names=names, expression_names=actions),
                             poses=torch.zeros(1, dtype=torch.float64))  # fmt: skip
    ids = [0, 6, 9]
    drive = truth_drive(truth / "params.npz", ids, target)
    composed = driven_poses(torch.from_numpy(pose_a), drive.poses, drive.reference, names)
    np.testing.assert_allclose(composed.numpy(), poses[ids], atol=1e-9)
    np.testing.assert_array_equal(drive.expressions.numpy(), expression[ids])
    with pytest.raises(DeltaError, match="not the generated truth of a reenactment"):
        truth_drive(tmp_path / "a" / "gt" / "params.npz", ids, target)

    # a reenactment from another anchor or reference than the truth's is refused before anything renders
    trained = lambda: SimpleNamespace(data=SimpleNamespace(frame_ids=np.arange(10)))  # noqa: E731
    for anchor, reference, said in (
        (3, REFERENCE, "drives frame 3 relative to 7"),
        (ANCHOR, 0, "drives frame 2 relative to 0"),
    ):
        with pytest.raises(DeltaError, match=f"generated for the avatar's frame 2 .* frame 7; this reenactment {said}"):
            score_reenactment(trained(), trained(), anchor, reference, tmp_path / "a.follows.b", None, 2)
