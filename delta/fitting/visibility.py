"""Keypoints a fitted body hides: a keypoint the detector saw cannot lie behind the body's own surface.

A limb swung toward the camera and one swung away from it put their keypoints and silhouette in the same
pixels; what tells them apart is depth order. A forearm crossed in front of the chest is seen (the
detector's confidence is high), and the fit that swings that arm back behind the torso hides it: the ray
from the camera to the fitted wrist meets the torso first. Counting such keypoints lets the fit choose
between its candidate poses (``fit._limbs_by_visibility``).

Shapes: F frames, V vertices, T faces, K keypoints.
"""

from __future__ import annotations

import torch

from delta.cameras.models import PinholeCamera
from delta.geometry.raymesh import ray_mesh_hits

SEEN = 0.5
"""A detection at or above this confidence counts as seen (the synthetic captures write 1 for a seen
keypoint and 0.3 for a hidden one; detectors score hidden joints low)."""
JOINT_DEPTH = 0.15
"""A joint lies inside its limb: the surface in front of it may be this far (metres) nearer the camera and
the joint still counts as seen (the synthetic captures' own rule for joints)."""
LIMB_ENDS = ("right_elbow", "right_wrist", "left_elbow", "left_wrist", "right_knee", "right_ankle", "left_knee",
             "left_ankle")  # fmt: skip
"""The keypoints whose depth a limb's swing decides (the torso's and the face's stay where the root puts
them, and a torso joint seen at a turning body's side lies deep inside it)."""
_ORTHO_START = 10.0


def camera_rays(camera, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays (origins, unit directions, each (N, 3)) from the camera to points (N, 3), and each point's
    distance along its ray (N,). An orthographic camera looks along -z: its rays start 10 m in front."""
    if isinstance(camera, PinholeCamera):
        origins = camera.center.to(points.dtype).expand_as(points)
        dirs = points - origins
        dist = dirs.norm(dim=-1)
        return origins, dirs / dist.clamp_min(1e-12)[:, None], dist
    step = torch.tensor([0.0, 0.0, _ORTHO_START], dtype=points.dtype)
    dirs = torch.tensor([0.0, 0.0, -1.0], dtype=points.dtype).expand_as(points)
    return points + step, dirs, torch.full(points.shape[:1], _ORTHO_START, dtype=points.dtype)


@torch.no_grad()
def hidden_seen(vertices: torch.Tensor, faces: torch.Tensor, keypoints: torch.Tensor, seen: torch.Tensor,
                camera, depth: float = JOINT_DEPTH) -> torch.Tensor:  # fmt: skip
    """(F,) how many of each frame's seen keypoints the body hides: the ray from the camera to the
    keypoint meets the mesh (vertices (F, V, 3), faces (T, 3)) more than ``depth`` before it.
    keypoints (F, K, 3), seen (F, K) bool."""
    out = torch.zeros(len(keypoints), dtype=torch.int64)
    for f in range(len(keypoints)):
        pts = keypoints[f][seen[f]].detach()
        if not len(pts):
            continue
        origins, dirs, dist = camera_rays(camera, pts)
        hits = ray_mesh_hits(vertices[f].detach(), faces, origins, dirs)
        out[f] = int((hits.hit & (hits.t < dist - depth)).sum())
    return out
