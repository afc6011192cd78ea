"""Faces found and tracked without a body: the detector's decoding, the turned crops, the tracker on a
real photo (against the body-guided face mesh), turned and lost faces, and the close-up's mask."""

import cv2
import numpy as np
import pytest
from skimage import data

from delta.preprocess.face_tracking import (
    BLAZEPOSE_FROM_FACE,
    Crop,
    FaceDetector,
    FaceTracker,
    HeadLandmarker,
    blazeface_anchors,
    blazepose_from_face,
    crop_from_points,
    head_mask,
    weighted_nms,
)


def test_anchors_are_the_two_grids_cell_centres():
    a = blazeface_anchors()
    assert a.shape == (896, 2)
    # 16 x 16 cells of 2 anchors, then 8 x 8 cells of 6, row by row
    np.testing.assert_allclose(a[0], [0.5 / 16, 0.5 / 16])
    np.testing.assert_allclose(a[1], a[0])
    np.testing.assert_allclose(a[2], [1.5 / 16, 0.5 / 16])
    np.testing.assert_allclose(a[2 * 16], [0.5 / 16, 1.5 / 16])
    np.testing.assert_allclose(a[512], [0.5 / 8, 0.5 / 8])
    np.testing.assert_allclose(a[512 + 6], [1.5 / 8, 0.5 / 8])
    np.testing.assert_allclose(a[-1], [7.5 / 8, 7.5 / 8])


def test_overlapping_detections_blend_by_score_and_apart_ones_stay():
    boxes = np.array([[0.5, 0.5, 0.2, 0.2], [0.52, 0.5, 0.2, 0.2], [0.1, 0.1, 0.1, 0.1]])
    points = np.stack([np.full((6, 2), 0.5), np.full((6, 2), 0.52), np.full((6, 2), 0.1)])
    scores = np.array([0.9, 0.6, 0.7])
    out = weighted_nms(boxes, points, scores)
    assert len(out) == 2
    box, pts, score = out[0]
    assert score == 0.9
    np.testing.assert_allclose(box[0], (0.9 * 0.5 + 0.6 * 0.52) / 1.5)
    np.testing.assert_allclose(pts[:, 0], (0.9 * 0.5 + 0.6 * 0.52) / 1.5)
    np.testing.assert_allclose(out[1][0], boxes[2])


@pytest.mark.parametrize("angle", [0.0, 0.4, -1.1])
def test_a_turned_crop_maps_frame_points_and_pixels_consistently(angle):
    crop = Crop(np.array([130.0, 90.0]), 80.0, angle)
    frame = np.zeros((200, 260, 3), np.uint8)
    p = np.array([150.5, 70.5])  # a pixel centre: pixel (150, 70)
    frame[70, 150] = 255
    A = crop.affine(64)
    q = A[:, :2] @ p + A[:, 2]
    cut = crop.cut(frame, 64).astype(float)[..., 0]
    peak = np.array(np.unravel_index(cut.argmax(), cut.shape))[::-1] + 0.5  # (u, v) centre
    assert np.linalg.norm(peak - q) < 0.75
    np.testing.assert_allclose(crop.to_frame(q[None], 64)[0], p, atol=1e-9)
    # the eye line along `angle` lies along the crop's u axis
    d = A[:, :2] @ np.array([np.cos(angle), np.sin(angle)])
    assert abs(d[1]) < 1e-9 and d[0] > 0


def test_the_crop_around_points_holds_them_with_the_margin():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-30, 30, (50, 2)) * [1.0, 0.5] + [200, 100]
    for angle in (0.0, 0.7):
        crop = crop_from_points(pts, angle, scale=1.5)
        A = crop.affine(100)
        q = pts @ A[:, :2].T + A[:, 2]
        assert q.min() >= 100 * (1 - 1 / 1.5) / 2 - 1e-6 and q.max() <= 100 - 100 * (1 - 1 / 1.5) / 2 + 1e-6
        assert np.isclose(np.ptp(q, 0).max(), 100 / 1.5)


def test_blazepose_points_are_the_named_face_points():
    face = np.zeros((468, 3), np.float32)
    face[:, 0], face[:, 1], face[:, 2] = np.arange(468), 2 * np.arange(468), 0.9
    lm = blazepose_from_face(face)
    assert lm[0, 0] == 1 and lm[2, 0] == (362 + 263) / 2 and lm[9, 0] == 291
    assert lm[7, 2] == pytest.approx(0.45) and lm[0, 2] == pytest.approx(0.9)
    assert (lm[[k for k in range(33) if k not in BLAZEPOSE_FROM_FACE], 2] == 0).all()  # shoulders, hands unseen


@pytest.fixture(scope="module")
def face_models(mediapipe_pose_model):
    return (
        mediapipe_pose_model.parent / "face_detection_short_range.onnx",
        mediapipe_pose_model.parent / "face_landmark.onnx",
    )


@pytest.mark.slow
def test_the_astronauts_face_is_found_and_meshed_as_the_body_guided_mesh_does(face_models, mediapipe_pose_model):
    from delta.preprocess.pose_landmarks import FaceLandmarker, PoseLandmarker

    img = data.astronaut()
    found = FaceDetector(face_models[0])(img)
    assert len(found) == 1 and found[0].score > 0.7
    u, v, w, h = found[0].box
    assert 180 < u < 290 and 70 < v < 200 and 50 < w < 160
    right_eye, left_eye, nose = found[0].keypoints[:3]
    assert right_eye[0] < nose[0] < left_eye[0]  # the subject's right eye is on the image's left
    tracked = FaceTracker(*face_models)(img)
    pose = PoseLandmarker(mediapipe_pose_model)(img)
    guided = FaceLandmarker(face_models[1])(img, pose)  # an independent crop: the pose model's face box
    assert (tracked[:, 2] > 0.9).all()
    gap = np.linalg.norm(tracked[:, :2] - guided[:, :2], axis=1)
    assert np.median(gap) < 3.0, np.median(gap)


@pytest.mark.slow
@pytest.mark.parametrize("degrees", [25, -35])
def test_a_tilted_face_is_meshed_as_the_upright_one_turned(face_models, degrees):
    img = data.astronaut()
    upright = FaceTracker(*face_models)(img)
    centre = upright[:, :2].mean(0)
    M = cv2.getRotationMatrix2D((float(centre[0] - 0.5), float(centre[1] - 0.5)), degrees, 1.0)
    turned = cv2.warpAffine(img, M, (512, 512), borderMode=cv2.BORDER_REFLECT)
    found = FaceTracker(*face_models)(turned)
    expected = (upright[:, :2] - 0.5) @ M[:, :2].T + M[:, 2] + 0.5
    gap = np.linalg.norm(found[:, :2] - expected, axis=1)
    assert np.median(gap) < 3.0, np.median(gap)


@pytest.mark.slow
def test_a_lost_face_is_found_again_and_no_face_gives_zeros(face_models):
    img = data.astronaut()
    tracker = FaceTracker(*face_models)
    first = tracker(img)
    blank = tracker(np.full_like(img, 128))
    assert (blank == 0).all() and tracker.crop is None
    shifted = np.roll(img, (40, -60), axis=(0, 1))  # the face elsewhere: detected afresh
    again = tracker(shifted)
    gap = np.linalg.norm(again[:, :2] - (first[:, :2] + [-60, 40]), axis=1)
    assert (again[:, 2] > 0.9).all() and np.median(gap) < 3.0


@pytest.mark.slow
def test_a_rendered_head_on_a_plain_background_is_masked(face_models, anny_files):
    import torch

    from delta.body.lbs import lbs
    from delta.body.model import REGION, load_body_model
    from delta.synthetic import textures
    from delta.synthetic.landmark_embedding import View, head_camera
    from delta.synthetic.raycast import SceneMesh, render
    import trimesh

    model = load_body_model(anny_files["body"], dtype=torch.float64)
    zero = torch.zeros(1, model.num_joints, 3, dtype=torch.float64)
    rest = lbs(model, torch.zeros(1, model.num_shape, dtype=torch.float64), zero).vertices[0].numpy()
    faces, regions = model.faces.numpy(), model.regions.numpy()
    face = regions == REGION["face"]
    # framed as a close-up: the head filling the upper half, the shoulders running off the bottom
    camera = head_camera(rest[face].mean(0) - [0, 0.08, 0], 0.3, View(torch.zeros(model.num_shape), 10, 0), 256)
    features = textures.FaceFeatures(rest, regions)
    scene = SceneMesh(rest, faces, np.zeros(len(faces), np.int64), rest,
                      trimesh.Trimesh(rest, faces, process=False).vertex_normals, regions.astype(np.uint8))  # fmt: skip
    frame = render(scene, camera, lambda o, p, lab: textures.skin_albedo(p, lab.astype(np.int64), (0.8, 0.6, 0.5),
                   features, 1), textures.shading, (0.35, 0.45, 0.6))  # fmt: skip
    rgb = np.round(frame.image * 255).astype(np.uint8)
    head = HeadLandmarker(*face_models)
    pose = head(rgb)
    assert pose.presence > 0.9 and (head.face[:, 2] > 0.9).all()
    truth = frame.alpha > 0.5
    mask = pose.mask > 0.5
    iou = (mask & truth).sum() / (mask | truth).sum()
    assert iou > 0.95, iou
    kp = pose.openpose18()
    assert (kp[[0, 14, 15], 2] > 0.9).all() and (kp[[16, 17], 2] > 0.4).all() and (kp[1:14, 2] == 0).all()
    assert head_mask(rgb, head.face).shape == rgb.shape[:2]
    none = head(np.full_like(rgb, 90))  # nothing found: an empty mask, no keypoints
    assert none.mask.max() == 0 and none.presence == 0 and (none.openpose18()[:, 2] == 0).all()


@pytest.mark.slow
def test_a_close_up_video_without_a_face_is_one_error(tmp_path, mediapipe_pose_model):
    from delta import DeltaError
    from delta.preprocess.steps import run_keypoints

    video = tmp_path / "wall.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 25, (96, 96))
    for k in range(6):
        writer.write(np.full((96, 96, 3), 120 + 10 * k, np.uint8))
    writer.release()
    out = tmp_path / "k.h5"
    with pytest.raises(DeltaError, match=r"wall\.mp4: no face found in any of the 6 frames analysed"):
        run_keypoints(video, None, "mediapipe", str(mediapipe_pose_model), out, framing="head")
    assert not out.exists()
