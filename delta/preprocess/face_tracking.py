"""Faces in a video without a body model's help: MediaPipe's face detector and face mesh, tracked.

A head-and-shoulders close-up is no person to a body landmarker (too little of the body, too big a
face), so a head capture finds its face directly, as MediaPipe's face mesh pipeline does:

- ``face_detection_short_range.onnx`` (BlazeFace): a 128 x 128 letterboxed RGB frame in [-1, 1];
  896 anchors (16 x 16 x 2 at stride 8, 8 x 8 x 6 at stride 16) regress a box and six keypoints
  (right eye, left eye, nose tip, mouth, right ear, left ear) each, with a logit.
- ``face_landmark.onnx``: a 192 x 192 crop of the face, turned upright, in [0, 1]; 468 points (crop
  pixels) and a face-presence logit.

The crop of the first frame (or of a frame after the face was lost) comes from the detector: the box
1.5 times enlarged, turned so the eyes are level. Later crops come from the previous frame's points
(their box in the eyes-level frame, 1.5 times enlarged), which follows a moving head closer than
detection would.

Coordinates: continuous pixel coordinates (a pixel's centre at +0.5), (u, v) = (x right, y down).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np

from delta.preprocess.onnx_models import check_frame, open_session
from delta.preprocess.pose_landmarks import FACE_INPUT, PoseResult, _sigmoid

DETECT_INPUT = 128
#: outer eye corners of the 468-point face mesh (subject's right, left): the crop's level line
EYE_CORNERS = (33, 263)
#: a detection and a tracked face must be at least this likely to count
MIN_SCORE = 0.5
#: the face mesh's inner lip contours, corner to corner (MediaPipe's ``lipsUpperInner`` and
#: ``lipsLowerInner`` without the shared corners 78 and 308): where a closed mouth's lips meet, each on its
#: own lip (:func:`delta.synthetic.landmark_embedding.calibrate` places them so)
INNER_LIPS = {"upper": (191, 80, 81, 82, 13, 312, 311, 310, 415), "lower": (95, 88, 178, 87, 14, 317, 402, 318, 324)}
#: the inner lips' contour as a closed polygon: corner 78, the upper inner lip, corner 308, the lower one back
INNER_LIP_CONTOUR = (78, *INNER_LIPS["upper"], 308, *INNER_LIPS["lower"][::-1])
#: a face box is enlarged this much to make the landmark model's crop (MediaPipe's own factor)
CROP_SCALE = 1.5


def blazeface_anchors() -> np.ndarray:
    """(896, 2) anchor centres in [0, 1] of the short-range detector, in its output order."""
    rows = []
    for grid, per_cell in ((16, 2), (8, 6)):
        c = (np.arange(grid) + 0.5) / grid
        cy, cx = np.meshgrid(c, c, indexing="ij")
        cells = np.stack([cx.ravel(), cy.ravel()], 1)
        rows.append(np.repeat(cells, per_cell, axis=0))
    return np.concatenate(rows).astype(np.float32)


@dataclasses.dataclass
class Detection:
    box: np.ndarray
    """(4,) centre u, centre v, width, height in frame pixels."""
    keypoints: np.ndarray
    """(6, 2) right eye, left eye, nose tip, mouth, right ear, left ear in frame pixels."""
    score: float


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    lo = np.maximum(box[:2] - box[2:] / 2, boxes[:, :2] - boxes[:, 2:] / 2)
    hi = np.minimum(box[:2] + box[2:] / 2, boxes[:, :2] + boxes[:, 2:] / 2)
    inter = np.clip(hi - lo, 0, None).prod(1)
    return inter / (box[2:].prod() + boxes[:, 2:].prod(1) - inter + 1e-12)


def weighted_nms(boxes: np.ndarray, points: np.ndarray, scores: np.ndarray, iou: float = 0.3):
    """MediaPipe's blending suppression: each cluster of overlapping detections (IoU > ``iou`` with its
    best) becomes their score-weighted mean. Returns [(box (4,), points (P, 2), score)] best first."""
    order = np.argsort(-scores)
    boxes, points, scores = boxes[order], points[order], scores[order]
    left = np.ones(len(scores), bool)
    out = []
    for i in range(len(scores)):
        if not left[i]:
            continue
        group = left & (_iou(boxes[i], boxes) > iou)
        group[i] = True
        w = scores[group] / scores[group].sum()
        out.append(((boxes[group] * w[:, None]).sum(0), (points[group] * w[:, None, None]).sum(0), float(scores[i])))
        left &= ~group
    return out


class FaceDetector:
    """Faces in a frame, best first (BlazeFace short range: faces within about 2 m of the camera)."""

    def __init__(self, path: str | Path, threads: int = 1, config_key: str | None = None):
        self.path = Path(path)
        self.session = open_session(self.path, {"input": 4}, 2, threads, config_key)
        self.anchors = blazeface_anchors()

    def __call__(self, frame_rgb_uint8: np.ndarray) -> list[Detection]:
        frame = check_frame(frame_rgb_uint8, self.path)
        H, W = frame.shape[:2]
        scale = DETECT_INPUT / max(H, W)
        w, h = max(1, round(W * scale)), max(1, round(H * scale))
        pad_u, pad_v = (DETECT_INPUT - w) / 2, (DETECT_INPUT - h) / 2
        canvas = np.zeros((DETECT_INPUT, DETECT_INPUT, 3), np.float32)
        small = cv2.resize(frame, (w, h), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
        top, left = int(pad_v), int(pad_u)
        canvas[top : top + h, left : left + w] = small.astype(np.float32) / 127.5 - 1.0
        raw, logits = self.session.run(None, {"input": canvas[None]})
        raw, scores = np.asarray(raw)[0], _sigmoid(np.asarray(logits).reshape(-1))
        keep = scores > MIN_SCORE
        if not keep.any():
            return []
        raw, anchors, scores = raw[keep], self.anchors[keep], scores[keep]
        centre = raw[:, :2] / DETECT_INPUT + anchors
        size = raw[:, 2:4] / DETECT_INPUT
        points = raw[:, 4:16].reshape(-1, 6, 2) / DETECT_INPUT + anchors[:, None]
        to_frame = np.array([left, top], np.float32)

        def frame_px(q):  # [0, 1] of the canvas -> frame pixels
            return (q * DETECT_INPUT - to_frame) / scale

        found = weighted_nms(np.concatenate([centre, size], 1), points, scores)
        return [
            Detection(np.concatenate([frame_px(b[:2]), b[2:] * DETECT_INPUT / scale]), frame_px(p), s)
            for b, p, s in found
        ]


@dataclasses.dataclass
class Crop:
    """A square, turned region of a frame: its centre (u, v), side (pixels) and angle (radians, the
    angle of the subject's right-to-left eye line from the image's u axis)."""

    centre: np.ndarray
    side: float
    angle: float

    def affine(self, size: int) -> np.ndarray:
        """(2, 3) frame continuous coordinates -> crop continuous coordinates of a size x size crop."""
        s, c, sn = size / self.side, np.cos(self.angle), np.sin(self.angle)
        R = s * np.array([[c, sn], [-sn, c]])  # turns the eye line onto +u
        return np.concatenate([R, (size / 2 - R @ self.centre)[:, None]], 1)

    def cut(self, frame: np.ndarray, size: int) -> np.ndarray:
        A = self.affine(size)
        index = A.copy()  # pixel-index coordinates: p_i = p_c - 0.5 on both sides
        index[:, 2] += A[:, :2].sum(1) * 0.5 - 0.5
        return cv2.warpAffine(frame, index, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def to_frame(self, points: np.ndarray, size: int) -> np.ndarray:
        A = self.affine(size)
        return (points - A[:, 2]) @ np.linalg.inv(A[:, :2]).T


def eye_angle(right_eye: np.ndarray, left_eye: np.ndarray) -> float:
    d = left_eye - right_eye
    return float(np.arctan2(d[1], d[0]))


def crop_from_points(points: np.ndarray, angle: float, scale: float = CROP_SCALE) -> Crop:
    """The square crop around (P, 2) frame points in the frame turned by ``angle``, ``scale`` times their extent."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, s], [-s, c]])
    q = points @ R.T
    lo, hi = q.min(0), q.max(0)
    return Crop(R.T @ ((lo + hi) / 2), float((hi - lo).max() * scale), angle)


def crop_from_detection(det: Detection, scale: float = CROP_SCALE) -> Crop:
    return Crop(det.box[:2].astype(np.float64), float(det.box[2:].max() * scale), eye_angle(*det.keypoints[:2]))


class FaceTracker:
    """468 face-mesh points a frame, following one face through a video (frames in order)."""

    #: the inner lips' landmarks by lip (:data:`INNER_LIPS`)
    inner_lips = INNER_LIPS

    def __init__(self, detector: str | Path, landmarks: str | Path, threads: int = 1):
        self.detector = FaceDetector(detector, threads)
        self.path = Path(landmarks)
        self.session = open_session(self.path, {"input_1": 4}, 2, threads)
        self.crop: Crop | None = None

    def reset(self) -> None:
        self.crop = None

    def landmarks(self, frame: np.ndarray, crop: Crop) -> tuple[np.ndarray, float]:
        """(468, 2) frame points and the face-presence probability of the landmark model on ``crop``."""
        image = crop.cut(frame, FACE_INPUT).astype(np.float32) / 255.0
        points, flag = self.session.run(None, {"input_1": image[None]})
        points = np.asarray(points).reshape(468, 3)[:, :2]
        return crop.to_frame(points, FACE_INPUT), float(_sigmoid(np.asarray(flag).reshape(-1)[:1])[0])

    def __call__(self, frame_rgb_uint8: np.ndarray) -> np.ndarray:
        """(468, 3) (u, v, confidence) in frame pixels; all zero where no face is found."""
        frame = check_frame(frame_rgb_uint8, self.path)
        out = np.zeros((468, 3), np.float32)
        crop = self.crop
        if crop is None:
            found = self.detector(frame)
            if not found:
                return out
            crop = crop_from_detection(found[0])
        points, presence = self.landmarks(frame, crop)
        if presence < MIN_SCORE and self.crop is not None:  # lost while tracking: detect afresh
            self.crop = None
            return self(frame)
        if presence < MIN_SCORE:
            return out
        self.crop = crop_from_points(points, eye_angle(points[EYE_CORNERS[0]], points[EYE_CORNERS[1]]))
        out[:, :2], out[:, 2] = points, presence
        return out


#: BlazePose landmark -> face-mesh points (averaged) for the points a face shows: nose, eyes (inner,
#: centre, outer), ears (the face outline at the ears' height: the tragus is hidden by hair or turned
#: away), mouth corners. Other BlazePose points are not seen by a face tracker (confidence 0).
BLAZEPOSE_FROM_FACE: dict[int, tuple[int, ...]] = {
    0: (1,), 1: (362,), 2: (362, 263), 3: (263,), 4: (133,), 5: (33, 133), 6: (33,),
    7: (454,), 8: (234,), 9: (291,), 10: (61,),
}  # fmt: skip
#: the ears are outline points, where the face's side is seen: half the confidence of the rest
OUTLINE_CONFIDENCE = 0.5
#: GrabCut works on frames at most this long (larger ones are cut at this size and the mask scaled back)
GRABCUT_SIZE = 512


def blazepose_from_face(face: np.ndarray) -> np.ndarray:
    """(33, 3) BlazePose landmarks (u, v, confidence) from (468, 3) face-mesh points."""
    out = np.zeros((33, 3), np.float32)
    for k, ids in BLAZEPOSE_FROM_FACE.items():
        out[k, :2] = face[list(ids), :2].mean(0)
        out[k, 2] = face[ids[0], 2] * (OUTLINE_CONFIDENCE if k in (7, 8) else 1.0)
    return out


def head_mask(frame_rgb: np.ndarray, face: np.ndarray, iterations: int = 4) -> np.ndarray:
    """(H, W) float32 0/1 head-and-shoulders mask by GrabCut, seeded by the face: the face's hull is
    the person, the region around the face and below the chin (neck, shoulders) probably the person,
    the top edge and the sides above the face the background, the rest probably background. A close-up
    on a plain background is what it is for; a busy background wants a matting model (RVM, MODNet)."""
    H, W = frame_rgb.shape[:2]
    scale = min(1.0, GRABCUT_SIZE / max(H, W))
    image = frame_rgb if scale == 1 else cv2.resize(frame_rgb, (round(W * scale), round(H * scale)),
                                                    interpolation=cv2.INTER_AREA)  # fmt: skip
    h, w = image.shape[:2]
    p = face[:, :2] * scale
    lo, hi = p.min(0), p.max(0)
    fw, fh = hi - lo
    seed = np.full((h, w), cv2.GC_PR_BGD, np.uint8)
    centre = (int((lo[0] + hi[0]) / 2), int((lo[1] + hi[1]) / 2 - 0.15 * fh))
    cv2.ellipse(seed, centre, (int(0.8 * fw), int(0.85 * fh)), 0, 0, 360, cv2.GC_PR_FGD, -1)
    cv2.rectangle(seed, (int(lo[0] - 0.6 * fw), int(hi[1])), (int(hi[0] + 0.6 * fw), h), cv2.GC_PR_FGD, -1)
    hull = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(p.astype(np.int32)), 1)
    seed[cv2.erode(hull, np.ones((9, 9), np.uint8)) > 0] = cv2.GC_FGD
    b, top = max(2, round(0.01 * max(h, w))), max(0, int(lo[1]))
    seed[:b] = cv2.GC_BGD
    seed[:top, :b] = seed[:top, -b:] = cv2.GC_BGD
    models = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(cv2.cvtColor(image, cv2.COLOR_RGB2BGR), seed, None, *models, iterations, cv2.GC_INIT_WITH_MASK)
    mask = ((seed == cv2.GC_FGD) | (seed == cv2.GC_PR_FGD)).astype(np.float32)
    return mask if scale == 1 else (cv2.resize(mask, (W, H), interpolation=cv2.INTER_LINEAR) > 0.5).astype(np.float32)


class HeadLandmarker:
    """A head-and-shoulders close-up's person mask and landmarks from its tracked face, in the body
    landmarker's form (:class:`PoseResult`), with the 468 face points kept in ``face``."""

    def __init__(self, detector: str | Path, landmarks: str | Path, threads: int = 1):
        self.tracker = FaceTracker(detector, landmarks, threads)
        self.face = np.zeros((468, 3), np.float32)

    def reset(self) -> None:
        self.tracker.reset()

    def __call__(self, frame_rgb_uint8: np.ndarray, mask: np.ndarray | None = None) -> PoseResult:
        """The tracked face's landmarks and head mask (``mask``: a given person mask, no GrabCut)."""
        self.face = self.tracker(frame_rgb_uint8)
        seen = self.face[0, 2] > 0
        if mask is None:
            mask = head_mask(frame_rgb_uint8, self.face) if seen else np.zeros(frame_rgb_uint8.shape[:2], np.float32)
        return PoseResult(mask=mask, landmarks=blazepose_from_face(self.face), presence=float(self.face[0, 2]))
