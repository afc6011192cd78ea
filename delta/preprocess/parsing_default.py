"""The offline default parser: skin, hair and clothing from the person mask and body landmarks.

No package ships clothing or human-parsing weights, so the default is built
from what does ship: the face and hands are located by the pose landmarks, a
Gaussian skin-colour model (CIE Lab) is seeded from the pixels there, skin is
the person's pixels close to it; hair is what is neither skin nor below the
mouth inside the head's box; clothing is the person minus skin and hair.
Users with a U²-Net cloth or BiSeNet export get better parsing from those.
"""

from __future__ import annotations

import cv2
import numpy as np

from delta.preprocess.pose_landmarks import PoseResult

_FACE = (0, 2, 5, 7, 8, 9, 10)  # nose, eyes, ears, mouth corners
_HANDS = ((15, 17, 19, 21), (16, 18, 20, 22))  # wrist, pinky, index, thumb per hand


def _disc(shape, centre, radius) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    cv2.circle(m, (int(round(centre[0] - 0.5)), int(round(centre[1] - 0.5))), max(1, int(radius)), 1, -1)
    return m.astype(bool)


#: The ears' span is this share of the nose's distance to the shoulders' midpoint, seen from the front
#: (0.59–0.79 on the synthetic turns, median 0.65); that distance keeps its length as the head turns.
EAR_SPAN_PER_NECK = 0.65


def head_span(lm: np.ndarray) -> float:
    """The head's width (px): the ears' span, or, turned away from the camera where the ears' span
    collapses (1–5 px in profile), :data:`EAR_SPAN_PER_NECK` of the nose-to-shoulders distance."""
    span = float(np.linalg.norm(lm[7, :2] - lm[8, :2]))
    if (lm[[0, 11, 12], 2] > 0.5).all():
        span = max(span, EAR_SPAN_PER_NECK * float(np.linalg.norm(lm[0, :2] - lm[[11, 12], :2].mean(0))))
    return span


def seed_regions(shape, lm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face disc, hand discs (where the landmarks are visible) and the head box (centred between the eyes
    and the ears: in profile the head reaches from the eye back past the ear)."""
    seeds = np.zeros(shape, bool)
    hands = np.zeros(shape, bool)
    head = np.zeros(shape, bool)
    face = lm[list(_FACE)]
    if (face[:, 2] > 0.5).sum() >= 3:
        span = head_span(lm)
        eye_mid = (lm[2, :2] + lm[5, :2]) / 2
        centre = (eye_mid + lm[0, :2]) / 2
        seeds |= _disc(shape, centre, 0.3 * np.linalg.norm(lm[7, :2] - lm[8, :2]))
        half = int(0.9 * span)
        u, v = int((eye_mid[0] + lm[[7, 8], 0].mean()) / 2), int(eye_mid[1])
        head[max(0, v - int(1.4 * half)) : max(0, v + half), max(0, u - half) : max(0, u + half)] = True
    for hand in _HANDS:
        pts = lm[list(hand)]
        if (pts[:, 2] > 0.5).all():
            centre = pts[1:, :2].mean(0)
            size = np.linalg.norm(pts[1:, :2] - pts[0, :2], axis=1).max()
            hands |= _disc(shape, centre, 0.5 * size)
    return seeds, hands, head


def colour_model(samples: np.ndarray, floor: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """A robust Gaussian (mean, inverse covariance) over Lab ``samples``."""
    med = np.median(samples, 0)
    spread = np.median(np.abs(samples - med), 0) * 1.4826 + 1e-6
    kept = samples[(np.abs(samples - med) / spread < 2.5).all(1)]  # drop eyes, brows, lips, shadows
    kept = kept if len(kept) >= 10 else samples
    cov = np.cov(kept.T) + np.diag(floor)  # regularised: lighting varies more than hue
    return kept.mean(0), np.linalg.inv(cov)


def _distance(lab: np.ndarray, model: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    d = lab - model[0]
    return np.sqrt(np.einsum("ni,ij,nj->n", d, model[1], d))


def _colour_distance(lab: np.ndarray, samples: np.ndarray, floor: tuple[float, float, float]) -> np.ndarray:
    """Mahalanobis distance of every pixel to a robust Gaussian fitted to ``samples`` (Lab)."""
    return _distance(lab, colour_model(samples, floor))


#: How much farther than the threshold from the skin's colour a pixel may be and still be skin, where the
#: clothing's colour is farther still.
LOOSE_SKIN = 2.0
_BODY = (11, 12, 24, 23)  # shoulders and hips, round the torso
PELVIS = 0.35
"""The pelvis's clothing sample reaches below the hips by this share of the shoulders-to-hips length."""


def _quad(shape, pts: np.ndarray, shrink: float) -> np.ndarray:
    """The quadrilateral ``pts`` (4, 2) shrunk towards its centre by ``shrink``, as a mask."""
    m = np.zeros(shape, np.uint8)
    corners = pts.mean(0) + (1 - shrink) * (pts - pts.mean(0))
    cv2.fillConvexPoly(m, np.round(corners - 0.5).astype(np.int32), 1)
    return m.astype(bool)


def clothing_seeds(shape, lm: np.ndarray, shrink: float = 0.5) -> list[np.ndarray]:
    """Where a dressed person's clothing is, each region's colours to be sampled on their own: the torso's
    quadrilateral (shoulders, hips) shrunk towards its centre by ``shrink``, and the pelvis below the hips
    (down the torso's axis by :data:`PELVIS` of its length: trousers, shorts or a skirt, whatever the legs
    wear). None where a corner is not visible."""
    pts = lm[list(_BODY)]
    if not (pts[:, 2] > 0.5).all():
        return []
    down = PELVIS * (pts[2:, :2].mean(0) - pts[:2, :2].mean(0))
    hips = pts[2:, :2]  # right, left
    return [_quad(shape, pts[:, :2], shrink), _quad(shape, np.concatenate([hips, hips[::-1] + down]), shrink)]


def clothing_distance(lab: np.ndarray, seed: np.ndarray, at: np.ndarray, clusters: int = 3) -> np.ndarray:
    """The Mahalanobis distance of the pixels ``at`` (flat indices) to the nearest of ``clusters`` robust
    Gaussians fitted to the ``seed`` pixels' Lab colours (a print or stripes has several colours)."""
    samples = lab[seed].astype(np.float32)
    k = min(clusters, max(1, len(samples) // 30))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.5)
    _, labels, _ = cv2.kmeans(samples, k, None, criteria, 2, cv2.KMEANS_PP_CENTERS)
    pixels, out = lab[at], np.full(len(at), np.inf)
    for c in range(k):
        members = samples[labels.ravel() == c].astype(np.float64)
        if len(members) >= 10:
            out = np.minimum(out, _colour_distance(pixels, members, (9.0, 4.0, 4.0)))
    return out


def shaded_skin(lab: np.ndarray, d_skin: np.ndarray, candidates: np.ndarray, seeds: list[np.ndarray],
                threshold: float) -> np.ndarray:  # fmt: skip
    """Skin in shade or light (legs, forearms), farther from the face's colour than ``threshold``: up to
    :data:`LOOSE_SKIN` times it, the ``candidates`` nearer the skin's colour than to any clothing colour
    sampled in the ``seeds`` (:func:`clothing_seeds`). Nothing where the torso is not dressed (its colour
    as near the skin's as that) or not seen."""
    dressed = [seed & candidates for seed in seeds]
    dressed = [d for d in dressed if d.sum() >= 50]
    if not dressed or np.median(d_skin[dressed[0]]) <= LOOSE_SKIN * threshold:
        return np.zeros_like(candidates)
    near = candidates & (d_skin < LOOSE_SKIN * threshold)
    out = np.zeros_like(candidates)
    idx = np.flatnonzero(near)
    if len(idx):
        d_clothing = np.min([clothing_distance(lab, d.ravel(), idx) for d in dressed], axis=0)
        out.ravel()[idx] = d_skin.ravel()[idx] < d_clothing
    return out


class VideoParser:
    """Parses a video's frames in order, remembering the skin colour seen on a frontal face
    for the frames where the face is turned away or too small to sample."""

    def __init__(self, threshold: float = 3.0):
        self.threshold = threshold
        self.skin_model: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self, rgb: np.ndarray, alpha: np.ndarray, pose: PoseResult) -> dict[str, np.ndarray]:
        masks, model, frontal = _parse(rgb, alpha, pose, self.threshold, self.skin_model)
        if frontal:
            self.skin_model = model
        return masks


def parse(rgb: np.ndarray, alpha: np.ndarray, pose: PoseResult, threshold: float = 3.0,
          skin_model: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, np.ndarray]:  # fmt: skip
    """(H, W) uint8 0/1 masks 'skin', 'hair', 'clothing' that partition the person (alpha > 0.5).

    ``skin_model`` (from an earlier frontal frame) is used when this frame shows no usable face.
    """
    return _parse(rgb, alpha, pose, threshold, skin_model)[0]


def _parse(rgb, alpha, pose, threshold, skin_model):
    """The masks, the skin model used, and whether it was sampled from a frontal face here."""
    person = alpha > 0.5
    shape = person.shape
    empty = np.zeros(shape, np.uint8)
    lm = pose.landmarks
    face_seed, hand_seed, head = seed_regions(shape, lm)
    face_seed &= person
    hand_seed &= person
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB).reshape(-1, 3).astype(np.float64)
    facing_away = False
    # seen from behind, the "face" disc lies on hair: trust the hands when the two disagree, or, with the
    # hands hidden, the skin seen on an earlier frontal face (a back view must not become the skin model)
    reference = np.median(lab[hand_seed.ravel()], 0) if hand_seed.sum() >= 20 else None
    if reference is None and skin_model is not None:
        reference = skin_model[0]
    if face_seed.sum() >= 20 and reference is not None:
        facing_away = np.linalg.norm(np.median(lab[face_seed.ravel()], 0) - reference) > 45
    frontal = face_seed.sum() >= 50 and not facing_away
    if frontal:
        model = colour_model(lab[(face_seed | hand_seed).ravel()], (25.0, 4.0, 4.0))
    elif skin_model is not None:
        model = skin_model
    elif hand_seed.sum() >= 20:
        model = colour_model(lab[hand_seed.ravel()], (25.0, 4.0, 4.0))
    else:
        return {"skin": empty, "hair": empty, "clothing": person.astype(np.uint8)}, None, False
    d_skin = _distance(lab, model).reshape(shape)
    skin = person & (d_skin < threshold)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    skin = cv2.morphologyEx(skin.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool) & person
    if head.any() and not facing_away:  # eyes, brows and lips belong to the face, not the hair
        ear_span = head_span(lm)
        for k in (2, 5):
            skin |= person & _disc(shape, lm[k, :2] + [0, -0.05 * ear_span], 0.22 * ear_span)
        skin |= person & _disc(shape, lm[[9, 10], :2].mean(0), 0.25 * ear_span)
    hair = _hair(lab, shape, person & ~skin, head, lm, threshold, facing_away)
    skin |= shaded_skin(lab, d_skin, person & ~skin & ~hair, clothing_seeds(shape, lm), threshold)
    clothing = person & ~skin & ~hair
    masks = {k: m.astype(np.uint8) for k, m in (("skin", skin), ("hair", hair), ("clothing", clothing))}
    return masks, model, frontal


def _hair(lab, shape, candidates, head, lm, threshold, facing_away) -> np.ndarray:
    """Hair colour seeded above the eyes (the whole head seen from behind); hair may hang beside
    the neck down to the shoulders."""
    rows = np.arange(shape[0])[:, None]
    eye_v = lm[[2, 5], 1].mean()
    top = candidates & head & (rows < (lm[[9, 10], 1].mean() if facing_away else eye_v))
    if top.sum() < 20:
        return candidates & head & (rows < lm[[9, 10], 1].mean())
    near = _colour_distance(lab, lab[top.ravel()], (9.0, 4.0, 4.0)).reshape(shape) < threshold
    cols = np.nonzero(head.any(0))[0]
    reach = np.zeros(shape, bool)
    width = cols.max() - cols.min()
    lo, hi = max(0, int(cols.min() - 0.3 * width)), int(cols.max() + 0.3 * width)
    shoulder_v = lm[[11, 12], 1].mean() if (lm[[11, 12], 2] > 0.5).all() else eye_v + 2 * width
    reach[: max(0, int(shoulder_v + 0.15 * width)), lo:hi] = True
    return candidates & near & reach | (candidates & head & (rows < eye_v))
