"""The offline default for person masks and body keypoints: MediaPipe's pose landmark model in ONNX.

``pose_landmark_full.onnx`` (converted by :mod:`delta.preprocess.mediapipe_convert`)
takes a 256 x 256 RGB crop in [0, 1] (NHWC) and returns 39 landmarks (x, y, z,
visibility and presence logits; the first 33 are BlazePose's body points, in crop
pixels), a pose-presence score, 256 x 256 segmentation logits and the landmarks in
metres about the hips' centre, along the camera's axes (``Identity_4``; their depths
tell a limb swung toward the camera from one swung away, which project alike). The person is
tracked: each frame's crop is the square around the previous frame's landmarks
(the whole frame at the start or when the person is lost).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np

from delta.preprocess.onnx_models import check_frame, open_session

INPUT = 256
#: OpenPose-18 keypoint -> BlazePose-33 landmark(s) (averaged)
OPENPOSE18_FROM_BLAZEPOSE: tuple[tuple[int, ...], ...] = (
    (0,), (11, 12), (12,), (14,), (16,), (11,), (13,), (15,), (24,), (26,), (28,), (23,), (25,), (27,),
    (5,), (2,), (8,), (7,),
)  # fmt: skip


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -60, 60)))


@dataclasses.dataclass
class PoseResult:
    mask: np.ndarray
    """(H, W) float32 person probability."""
    landmarks: np.ndarray
    """(33, 3) BlazePose landmarks (u, v, visibility) in frame pixel coordinates (centres at +0.5)."""
    presence: float
    """Probability that a person is in the crop."""
    metric: np.ndarray | None = None
    """(33, 3) the landmarks in metres about the hips' centre, x right, y down, z away from the camera."""

    def openpose18(self) -> np.ndarray:
        """(18, 3) keypoints (u, v, confidence); confidence 0 when no person was found."""
        return openpose18(self.landmarks, self.presence)

    def depth18(self) -> np.ndarray:
        """(18,) the OpenPose keypoints' depths (metres, about the hips' centre, away from the camera); NaN
        when no person was found."""
        if self.metric is None or self.presence <= 0.5:
            return np.full(18, np.nan, np.float32)
        return np.array([self.metric[list(ids), 2].mean() for ids in OPENPOSE18_FROM_BLAZEPOSE], np.float32)


def openpose18(landmarks: np.ndarray, presence: float) -> np.ndarray:
    """(18, 3) OpenPose keypoints (u, v, confidence) of (33, 3) BlazePose landmarks; confidence 0 unless
    ``presence`` > 0.5."""
    out = np.zeros((18, 3), np.float32)
    for k, ids in enumerate(OPENPOSE18_FROM_BLAZEPOSE):
        out[k, :2] = landmarks[list(ids), :2].mean(0)
        out[k, 2] = landmarks[list(ids), 2].min() * (presence > 0.5)
    return out


class PoseLandmarker:
    """Person mask and body landmarks per frame, tracking the person across frames."""

    def __init__(self, path: str | Path, threads: int = 1, config_key: str | None = None, margin: float = 1.35):
        self.path = Path(path)
        self.session = open_session(self.path, {"input_1": 4}, 5, threads, config_key)
        self.margin = margin
        self.roi: tuple[float, float, float] | None = None  # centre u, centre v, side

    def reset(self) -> None:
        self.roi = None

    def _crop(self, frame: np.ndarray, roi) -> tuple[np.ndarray, float, float, float]:
        cu, cv, side = roi
        scale = INPUT / side
        # affine map frame pixel-index coords -> crop pixel-index coords (pixel centres aligned)
        tx = INPUT / 2 - cu * scale - 0.5 + 0.5 * scale
        ty = INPUT / 2 - cv * scale - 0.5 + 0.5 * scale
        M = np.array([[scale, 0, tx], [0, scale, ty]], dtype=np.float64)
        crop = cv2.warpAffine(frame, M, (INPUT, INPUT), flags=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT)  # fmt: skip
        return crop, scale, tx, ty

    def __call__(self, frame_rgb_uint8: np.ndarray, mask: np.ndarray | None = None) -> PoseResult:
        """The frame's landmarks and person mask (``mask``: a given person mask taken instead of the model's)."""
        frame = check_frame(frame_rgb_uint8, self.path)
        H, W = frame.shape[:2]
        roi = self.roi or (W / 2, H / 2, float(max(H, W)))
        crop, scale, tx, ty = self._crop(frame, roi)
        out = self.session.run(None, {"input_1": crop[None].astype(np.float32) / 255.0})
        raw = out[0].reshape(-1, 5)[:33]
        presence = float(np.asarray(out[1]).reshape(-1)[0])
        # crop coords (continuous, centres at +0.5) -> frame continuous coords
        u = (raw[:, 0] - 0.5 - tx) / scale + 0.5
        v = (raw[:, 1] - 0.5 - ty) / scale + 0.5
        vis = _sigmoid(raw[:, 3])
        Minv = cv2.invertAffineTransform(np.array([[scale, 0, tx], [0, scale, ty]]))
        if mask is None:
            seg = _sigmoid(np.asarray(out[2])[0, :, :, 0]).astype(np.float32)
            mask = cv2.warpAffine(seg, Minv, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        metric = np.asarray(out[4], np.float32).reshape(-1, 3)[:33] if len(out) > 4 else None
        result = PoseResult(mask=mask, landmarks=np.stack([u, v, vis], 1).astype(np.float32), presence=presence,
                            metric=metric)  # fmt: skip
        self._track(result)
        return result

    def _track(self, result: PoseResult) -> None:
        seen = result.landmarks[:, 2] > 0.5
        if result.presence < 0.5 or seen.sum() < 4:
            self.roi = None
            return
        pts = result.landmarks[seen, :2]
        lo, hi = pts.min(0), pts.max(0)
        centre = (lo + hi) / 2
        self.roi = (float(centre[0]), float(centre[1]), float((hi - lo).max() * self.margin + 16))


FACE_INPUT = 192


class FaceLandmarker:
    """MediaPipe's face mesh (468 landmarks) in ONNX, on the face box the pose landmarks give.

    ``face_landmark.onnx``: input ``input_1`` (1, 192, 192, 3) RGB in [0, 1]; outputs the
    468 x (x, y, z) landmarks in crop pixels and a face-presence logit.
    """

    def __init__(self, path: str | Path, threads: int = 1, config_key: str | None = None, scale: float = 2.2):
        self.path = Path(path)
        self.session = open_session(self.path, {"input_1": 4}, 2, threads, config_key)
        self.scale = scale

    def __call__(self, frame_rgb_uint8: np.ndarray, pose: PoseResult) -> np.ndarray:
        """(468, 3) landmarks (u, v, confidence) in frame pixels; confidence 0 without a face."""
        frame = check_frame(frame_rgb_uint8, self.path)
        lm = pose.landmarks
        out = np.zeros((468, 3), np.float32)
        face = lm[[0, 2, 5, 7, 8, 9, 10]]
        if pose.presence < 0.5 or (face[:3, 2] < 0.5).any():
            return out
        centre = face[:, :2].mean(0)
        side = self.scale * max(np.linalg.norm(lm[7, :2] - lm[8, :2]), np.linalg.norm(lm[2, :2] - lm[5, :2]) * 2)
        s = FACE_INPUT / side
        tx, ty = FACE_INPUT / 2 - centre[0] * s - 0.5 + 0.5 * s, FACE_INPUT / 2 - centre[1] * s - 0.5 + 0.5 * s
        crop = cv2.warpAffine(frame, np.array([[s, 0, tx], [0, s, ty]]), (FACE_INPUT, FACE_INPUT),
                              flags=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)  # fmt: skip
        points, flag = self.session.run(None, {"input_1": crop[None].astype(np.float32) / 255.0})
        points = np.asarray(points).reshape(468, 3)
        out[:, 0] = (points[:, 0] - 0.5 - tx) / s + 0.5
        out[:, 1] = (points[:, 1] - 0.5 - ty) / s + 0.5
        out[:, 2] = _sigmoid(np.asarray(flag).reshape(-1)[:1])[0]
        return out
