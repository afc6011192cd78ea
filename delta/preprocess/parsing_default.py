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


def seed_regions(shape, lm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face disc, hand discs (where the landmarks are visible) and the head box."""
    seeds = np.zeros(shape, bool)
    hands = np.zeros(shape, bool)
    head = np.zeros(shape, bool)
    face = lm[list(_FACE)]
    if (face[:, 2] > 0.5).sum() >= 3:
        ear_span = np.linalg.norm(lm[7, :2] - lm[8, :2])
        eye_mid = (lm[2, :2] + lm[5, :2]) / 2
        centre = (eye_mid + lm[0, :2]) / 2
        seeds |= _disc(shape, centre, 0.3 * ear_span)
        half = int(0.9 * ear_span)
        u, v = int(eye_mid[0]), int(eye_mid[1])
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
    if face_seed.sum() >= 20 and hand_seed.sum() >= 20:
        # seen from behind, the "face" disc lies on hair: trust the hands when the two disagree
        delta_e = np.linalg.norm(np.median(lab[face_seed.ravel()], 0) - np.median(lab[hand_seed.ravel()], 0))
        facing_away = delta_e > 45
    frontal = face_seed.sum() >= 50 and not facing_away
    if frontal:
        model = colour_model(lab[(face_seed | hand_seed).ravel()], (25.0, 4.0, 4.0))
    elif skin_model is not None:
        model = skin_model
    elif hand_seed.sum() >= 20:
        model = colour_model(lab[hand_seed.ravel()], (25.0, 4.0, 4.0))
    else:
        return {"skin": empty, "hair": empty, "clothing": person.astype(np.uint8)}, None, False
    skin = person & (_distance(lab, model).reshape(shape) < threshold)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    skin = cv2.morphologyEx(skin.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool) & person
    if head.any() and not facing_away:  # eyes, brows and lips belong to the face, not the hair
        ear_span = np.linalg.norm(lm[7, :2] - lm[8, :2])
        for k in (2, 5):
            skin |= person & _disc(shape, lm[k, :2] + [0, -0.05 * ear_span], 0.22 * ear_span)
        skin |= person & _disc(shape, lm[[9, 10], :2].mean(0), 0.25 * ear_span)
    hair = _hair(lab, shape, person & ~skin, head, lm, threshold, facing_away)
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
