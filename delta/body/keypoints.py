"""2D keypoint formats and their map onto body-model joints and vertices.

One array format everywhere: (N, K, 3) per frame with (u, v, confidence) in
pixels; confidence 0 means "not detected". ``OPENPOSE18`` is People Snapshot's
order. A ``KeypointMap`` places each keypoint on the body model as a weighted
sum of joints and vertices, so 3D keypoints follow any pose and shape.
"""

from __future__ import annotations

import dataclasses

import torch

from delta import DeltaError
from delta.body.model import REGION, BodyModel

OPENPOSE18: tuple[str, ...] = (
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow",
    "left_wrist", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle",
    "right_eye", "left_eye", "right_ear", "left_ear",
)  # fmt: skip

#: OpenPose-18 keypoints that sit on a joint of each model (the rest are placed on vertices).
_JOINTS = {
    "anny": {
        "neck": "neck01", "right_shoulder": "upperarm01.R", "right_elbow": "lowerarm01.R",
        "right_wrist": "wrist.R", "left_shoulder": "upperarm01.L", "left_elbow": "lowerarm01.L",
        "left_wrist": "wrist.L", "right_hip": "upperleg01.R", "right_knee": "lowerleg01.R",
        "right_ankle": "foot.R", "left_hip": "upperleg01.L", "left_knee": "lowerleg01.L", "left_ankle": "foot.L",
    },
    "smplx": {
        "neck": "neck", "right_shoulder": "right_shoulder", "right_elbow": "right_elbow",
        "right_wrist": "right_wrist", "left_shoulder": "left_shoulder", "left_elbow": "left_elbow",
        "left_wrist": "left_wrist", "right_hip": "right_hip", "right_knee": "right_knee",
        "right_ankle": "right_ankle", "left_hip": "left_hip", "left_knee": "left_knee", "left_ankle": "left_ankle",
    },
}  # fmt: skip


@dataclasses.dataclass
class KeypointMap:
    """Keypoints as weighted sums of model joints and vertices."""

    names: tuple[str, ...]
    joint_weights: torch.Tensor
    """(K, J) weights over joints."""
    vertex_weights: torch.Tensor
    """(K, V) weights over vertices (dense; few non-zeros)."""

    def __call__(self, joints: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
        """(B, J, 3) posed joints, (B, V, 3) posed vertices -> (B, K, 3) keypoints."""
        jw = self.joint_weights.to(joints.dtype)
        vw = self.vertex_weights.to(vertices.dtype)
        return torch.einsum("kj,bjc->bkc", jw, joints) + torch.einsum("kv,bvc->bkc", vw, vertices)


def _nearest(points: torch.Tensor, target: torch.Tensor, k: int) -> torch.Tensor:
    return (points - target).norm(dim=-1).topk(k, largest=False).indices


def openpose18_map(model: BodyModel) -> KeypointMap:
    """OpenPose-18 on a model: joints where the model has them, face points on head vertices.

    Nose, eyes and ears are found on the rest template from the face region:
    the eyes at the centre of each eye region (or of the face's upper front),
    the nose as the most forward face vertex between them, the ears as the
    outermost face vertices at eye height.
    """
    base = model.name.split("_sub")[0]
    if base not in _JOINTS:
        raise DeltaError(f"no OpenPose-18 map for body model '{model.name}' (known: {sorted(_JOINTS)})")
    names = OPENPOSE18
    J, V = model.num_joints, model.num_vertices
    jw = torch.zeros(len(names), J, dtype=model.v_template.dtype)
    vw = torch.zeros(len(names), V, dtype=model.v_template.dtype)
    for k, name in enumerate(names):
        joint = _JOINTS[base].get(name)
        if joint is not None:
            if joint not in model.joint_names:
                raise DeltaError(f"body model '{model.name}' has no joint '{joint}' for keypoint '{name}'")
            jw[k, model.joint_names.index(joint)] = 1.0
    v = model.v_template
    face = torch.nonzero(model.regions == REGION["face"]).squeeze(1)
    eyes = torch.nonzero(model.regions == REGION["eyes"]).squeeze(1)
    fv = v[face]
    for side, name, ear in ((1.0, "left_eye", "left_ear"), (-1.0, "right_eye", "right_ear")):
        if len(eyes):
            ids = eyes[(v[eyes, 0] * side) > 0]
            centre = v[ids].mean(0)
            # the eye keypoint sits on the front of the eye region (the visible eyeball)
            front = ids[v[ids, 2] > v[ids, 2].max() - 0.008]
            vw[names.index(name), front] = 1.0 / len(front)
        else:
            top = fv[:, 1].quantile(0.75)
            centre = fv[(fv[:, 1] > top - 0.06) & (fv[:, 1] < top) & (fv[:, 0] * side > 0.02)].mean(0)
            ids = face[_nearest(fv, centre, 8)]
            vw[names.index(name), ids] = 1.0 / len(ids)
        band = face[(fv[:, 1] - centre[1]).abs() < 0.02]
        outer = band[(v[band, 0] * side).topk(min(6, len(band))).indices]
        vw[names.index(ear), outer] = 1.0 / len(outer)
    eye_y = (vw[names.index("left_eye")] @ v + vw[names.index("right_eye")] @ v)[1] / 2
    below = face[(fv[:, 1] < eye_y - 0.015) & (fv[:, 1] > eye_y - 0.06) & (fv[:, 0].abs() < 0.01)]
    if not len(below):
        raise DeltaError(f"body model '{model.name}': found no nose vertices in the face region")
    nose = below[v[below, 2].topk(min(3, len(below))).indices]
    vw[names.index("nose"), nose] = 1.0 / len(nose)
    return KeypointMap(names=names, joint_weights=jw, vertex_weights=vw)
