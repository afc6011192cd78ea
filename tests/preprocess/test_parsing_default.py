"""The default parser's pieces on drawn images with known answers: the head's size when the head turns,
the torso's clothing sample, shaded skin told from clothing by which colour it is nearer."""

import cv2
import numpy as np

from delta.preprocess.parsing_default import (
    EAR_SPAN_PER_NECK,
    PELVIS,
    clothing_distance,
    clothing_seeds,
    head_span,
    shaded_skin,
)


def landmarks(ears: tuple[float, float], nose=(50.0, 40.0), shoulders=((30.0, 90.0), (70.0, 90.0))) -> np.ndarray:
    lm = np.zeros((33, 3))
    lm[:, 2] = 1.0
    lm[0, :2] = nose
    lm[7, :2], lm[8, :2] = (ears[0], 38.0), (ears[1], 38.0)
    lm[11, :2], lm[12, :2] = shoulders
    lm[23, :2], lm[24, :2] = (35.0, 170.0), (65.0, 170.0)
    return lm


def test_the_head_keeps_its_size_when_it_turns_to_profile():
    neck = np.linalg.norm(np.array([50.0, 40.0]) - [50.0, 90.0])  # nose to the shoulders' midpoint: 50 px
    frontal = landmarks((30.0, 70.0))
    assert head_span(frontal) == 40.0  # the ears' span, larger than 0.65 x 50
    profile = landmarks((49.0, 51.0))  # the ears 2 px apart
    assert head_span(profile) == EAR_SPAN_PER_NECK * neck
    hidden = profile.copy()
    hidden[11, 2] = 0.0  # a shoulder not seen: the ears are all there is
    assert head_span(hidden) == 2.0


def test_the_clothing_samples_lie_on_the_torso_and_the_pelvis():
    lm = landmarks((30.0, 70.0))
    torso, pelvis = clothing_seeds((200, 100), lm)
    quad = np.zeros((200, 100), np.uint8)
    cv2.fillConvexPoly(quad, np.round(lm[[11, 12, 24, 23], :2] - 0.5).astype(np.int32), 1)
    assert torso.any() and not (torso & ~quad.astype(bool)).any()
    assert 0.2 < torso.sum() / quad.sum() < 0.3  # shrunk by half towards the centre: a quarter of the area
    rows = np.nonzero(pelvis)[0]  # below the hips (v = 170), down the torso's axis by PELVIS of its 80 px
    assert rows.min() >= 170 and rows.max() <= 170 + PELVIS * 80 and not (pelvis & torso).any()
    lm[23, 2] = 0.0
    assert clothing_seeds((200, 100), lm) == []


def _lab(colours: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(colours.reshape(1, -1, 3).astype(np.uint8), cv2.COLOR_RGB2LAB).reshape(-1, 3).astype(float)


def test_clothing_of_several_colours_is_near_all_of_them():
    stripes = np.array([[20, 40, 160]] * 200 + [[235, 235, 225]] * 200)  # blue and white
    lab = _lab(np.concatenate([stripes, [[20, 40, 160], [235, 235, 225], [200, 150, 120]]]))
    seed = np.zeros(len(lab), bool)
    seed[:400] = True
    d = clothing_distance(lab, seed, np.arange(400, 403))
    assert d[0] < 3 and d[1] < 3 and d[2] > 10  # both stripes' colours, not skin


def test_shaded_skin_is_skin_where_it_is_nearer_skin_than_the_clothing():
    """A dress of one colour on the torso; legs in skin's colour in shade, beyond the strict threshold:
    they are skin. Trousers of a colour nearer skin than the shirt's, sampled at the pelvis: not skin.
    Where the torso itself is skin-coloured (no clothing to tell apart), nothing is added."""
    lab = _lab(
        np.array([[40, 160, 170]] * 300 + [[150, 105, 80]] * 100 + [[60, 200, 210]] * 50)
    )  # dress, leg, dress in light
    d_skin = np.concatenate([np.full(300, 20.0), np.full(100, 4.5), np.full(50, 18.0)])  # threshold 3: leg in 3..6
    candidates = np.ones(450, bool)
    torso = np.zeros(450, bool)
    torso[:300] = True
    out = shaded_skin(lab, d_skin.reshape(1, -1), candidates.reshape(1, -1), [torso.reshape(1, -1)], 3.0)[0]
    assert out[300:400].all() and not out[:300].any() and not out[400:].any()
    bare = shaded_skin(lab, np.full((1, 450), 4.0), candidates.reshape(1, -1), [torso.reshape(1, -1)], 3.0)
    assert not bare.any()  # a torso as near the skin's colour as the legs: not dressed, nothing decided
    khaki = _lab(np.array([[40, 160, 170]] * 300 + [[165, 140, 100]] * 150))  # shirt, khaki trousers
    d = np.concatenate([np.full(300, 20.0), np.full(150, 4.5)]).reshape(1, -1)
    pelvis = np.zeros((1, 450), bool)
    pelvis[0, 380:] = True
    assert shaded_skin(khaki, d, np.ones((1, 450), bool), [torso.reshape(1, -1)], 3.0)[0, 300:].all()  # unsampled
    assert not shaded_skin(khaki, d, np.ones((1, 450), bool), [torso.reshape(1, -1), pelvis], 3.0).any()


def test_a_back_view_with_the_hands_hidden_does_not_become_the_skin_model():
    """Frame 1 shows the face (skin-coloured face disc, hands in view); frame 2 the back of the head, the
    hands hidden: its "face" disc lies on dark hair and must not replace the skin model, so the
    shoulders' skin is still found."""
    from delta.preprocess.parsing_default import VideoParser
    from delta.preprocess.pose_landmarks import PoseResult

    skin, hair, shirt = (200, 150, 120), (40, 30, 25), (30, 60, 170)
    lm = landmarks((30.0, 70.0))
    lm[[2, 5], :2] = (42.0, 36.0), (58.0, 36.0)
    lm[[9, 10], :2] = (46.0, 48.0), (54.0, 48.0)
    for k, (u, v) in zip((15, 17, 19, 21, 16, 18, 20, 22), [(10.0, 150.0)] * 4 + [(90.0, 150.0)] * 4):
        lm[k, :2] = (u + (k % 3), v + (k % 5))
    mask = np.ones((200, 100), np.float32)

    def frame(face_colour, hands_seen):
        img = np.zeros((200, 100, 3), np.uint8)
        img[:] = shirt
        img[:95] = skin  # head and neck
        cv2.circle(img, (50, 40), 14, face_colour, -1)
        img[140:160, :18] = img[140:160, 82:] = skin  # the hands
        marks = lm.copy()
        marks[[15, 17, 19, 21, 16, 18, 20, 22], 2] = 1.0 if hands_seen else 0.0
        return img, PoseResult(mask, marks, 1.0)

    parser = VideoParser()
    parser(*(lambda img, pose: (img, mask, pose))(*frame(skin, True)))
    model = parser.skin_model
    assert model is not None
    img, pose = frame(hair, False)
    masks = parser(img, mask, pose)
    assert parser.skin_model is model
    assert masks["skin"][60:90].mean() > 0.5  # the neck and shoulders' skin, still told by the first frame's model
