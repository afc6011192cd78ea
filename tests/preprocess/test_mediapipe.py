"""The offline default: MediaPipe's pose landmark model converted to ONNX, on a real photo and on
the synthetic captures."""

import h5py
import numpy as np
import pytest
from skimage import data

from delta.preprocess.pose_landmarks import OPENPOSE18_FROM_BLAZEPOSE, PoseLandmarker
from delta.body.keypoints import OPENPOSE18

pytestmark = pytest.mark.slow


def test_astronaut_mask_covers_the_person_and_face_points_land_on_the_face(mediapipe_pose_model):
    img = data.astronaut()  # a real person, 512 x 512
    result = PoseLandmarker(mediapipe_pose_model)(img)
    assert result.presence > 0.5
    mask = result.mask
    assert mask[90:160, 200:270].mean() > 0.9  # the face
    assert mask[300:420, 60:200].mean() > 0.8  # the suit's shoulder and chest
    assert mask[0:60, 440:512].mean() < 0.1  # the background above the shuttle
    kp = result.openpose18()
    face = {n: kp[OPENPOSE18.index(n)] for n in ("nose", "left_eye", "right_eye", "left_ear", "right_ear")}
    for name, (u, v, conf) in face.items():
        assert 170 < u < 300 and 60 < v < 200, f"{name} at ({u:.0f}, {v:.0f}) is off the face"
        assert conf > 0.5
    assert face["left_eye"][0] > face["nose"][0] > face["right_eye"][0]  # the subject's left is image right
    assert face["nose"][1] > face["left_eye"][1]


def test_keypoint_map_is_complete():
    assert len(OPENPOSE18_FROM_BLAZEPOSE) == len(OPENPOSE18) == 18


@pytest.mark.parametrize("subject", ["tight", "loose"])
def test_synthetic_masks_and_keypoints_match_ground_truth(mediapipe_pose_model, tiny_captures, subject):
    import cv2

    capture = tiny_captures / subject
    model = PoseLandmarker(mediapipe_pose_model)
    cap = cv2.VideoCapture(str(capture / f"{subject}.mp4"))
    ious, errors = [], []
    with h5py.File(capture / "gt" / "frames.h5") as gt:
        for i in range(gt["person"].shape[0]):
            ok, frame = cap.read()
            assert ok
            r = model(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
            pred, true = r.mask > 0.5, gt["person"][i] > 0
            ious.append((pred & true).sum() / (pred | true).sum())
            kp, gk = r.openpose18(), gt["keypoints"][i]
            body = [OPENPOSE18.index(n) for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip")]
            seen = [k for k in body if gk[k, 2] == 1 and kp[k, 2] > 0.5]
            if seen:
                errors.append(np.linalg.norm(kp[seen, :2] - gk[seen, :2], axis=1).mean())
    assert np.mean(ious) > 0.85, ious  # 128² captures: boundary pixels weigh a lot
    assert errors and np.median(errors) < 0.06 * 128  # within ~8 px at 128²


@pytest.mark.parametrize("subject", ["tight", "loose"])
def test_the_landmarkers_depths_tell_which_way_a_bone_runs(mediapipe_pose_model, tiny_captures, subject):
    """A bone's detected depth difference has the truth's sign where the truth's exceeds 0.1 m (the init fit
    takes from it only that side, ``fitting.terms.depth_term``)."""
    import cv2

    from delta.fitting.fit import DEPTH_BONES

    capture = tiny_captures / subject
    model = PoseLandmarker(mediapipe_pose_model)
    cap = cv2.VideoCapture(str(capture / f"{subject}.mp4"))
    p = np.load(capture / "gt" / "params.npz")
    bones = np.array(DEPTH_BONES)
    agree = []
    with h5py.File(capture / "gt" / "frames.h5") as gt:
        for i in range(gt["person"].shape[0]):
            ok, frame = cap.read()
            assert ok
            depth = model(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)).depth18()
            assert depth.shape == (18,) and np.isfinite(depth).all()
            kp3d = gt["keypoints3d"][i].astype(np.float64)
            true = (kp3d @ p["R"].T + p["t"])[:, 2] if str(p["camera_model"]) == "pinhole" else -kp3d[:, 2]
            dt, dd = true[bones[:, 1]] - true[bones[:, 0]], depth[bones[:, 1]] - depth[bones[:, 0]]
            agree += (np.sign(dt) == np.sign(dd))[np.abs(dt) > 0.1].tolist()
    assert len(agree) >= 5 and np.mean(agree) >= 0.8, agree


@pytest.mark.parametrize("subject", ["tight", "loose"])
def test_default_parser_partitions_the_person(mediapipe_pose_model, tiny_captures, subject):
    """Skin, hair and clothing partition the person; clothing overlaps the ground truth's."""
    import cv2

    from delta.preprocess.parsing_default import VideoParser

    capture = tiny_captures / subject
    landmarker, parser = PoseLandmarker(mediapipe_pose_model), VideoParser()
    cap = cv2.VideoCapture(str(capture / f"{subject}.mp4"))
    ious = []
    with h5py.File(capture / "gt" / "frames.h5") as gt:
        for i in range(gt["person"].shape[0]):
            rgb = cv2.cvtColor(cap.read()[1], cv2.COLOR_BGR2RGB)
            pose = landmarker(rgb)
            masks = parser(rgb, pose.mask, pose)
            total = masks["skin"].astype(int) + masks["hair"] + masks["clothing"]
            assert (total == (pose.mask > 0.5)).all()
            a, b = masks["clothing"] > 0, gt["clothing"][i] > 0
            ious.append((a & b).sum() / (a | b).sum())
    assert np.mean(ious) > 0.7, ious  # ~0.9 at 512² (benchmarks/preprocess_quality.py); 128² here


def test_face_mesh_lands_on_the_astronauts_face(mediapipe_pose_model):
    from delta.preprocess.pose_landmarks import FaceLandmarker

    img = data.astronaut()
    pose = PoseLandmarker(mediapipe_pose_model)(img)
    face = FaceLandmarker(mediapipe_pose_model.parent / "face_landmark.onnx")(img, pose)
    assert face.shape == (468, 3) and (face[:, 2] > 0.9).all()
    assert (face[:, 0] > 170).all() and (face[:, 0] < 290).all()
    assert (face[:, 1] > 60).all() and (face[:, 1] < 200).all()
    # MediaPipe's mesh: 1 is the nose tip, 13/14 the inner lips, 10 the top of the forehead
    assert face[10, 1] < face[1, 1] < face[13, 1]
    assert np.linalg.norm(face[1, :2] - pose.landmarks[0, :2]) < 25  # near the pose model's nose


def test_no_face_no_landmarks(mediapipe_pose_model):
    from delta.preprocess.pose_landmarks import FaceLandmarker

    blank = np.full((256, 256, 3), 200, np.uint8)
    pose = PoseLandmarker(mediapipe_pose_model)(blank)
    face = FaceLandmarker(mediapipe_pose_model.parent / "face_landmark.onnx")(blank, pose)
    assert pose.presence < 0.5 and (face[:, 2] == 0).all() and (pose.openpose18()[:, 2] == 0).all()
