"""Procedural solid textures evaluated at canonical surface points.

Colours depend only on the canonical position of a surface point, so patterns
stay crisp at any mesh resolution and stick to the body and the cloth as they
move. All functions take (N, 3) points and return (N, 3) RGB in [0, 1].
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from delta.body.model import REGION
from delta.synthetic.spec import GarmentSpec


def _hash(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    h = (ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791) ^ (seed * 2654435761)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFFFF).astype(np.float64) / float(0xFFFFFF)


def value_noise(points: np.ndarray, frequency: float, seed: int) -> np.ndarray:
    """Smooth lattice noise in [0, 1] at (N, 3) points."""
    p = points * frequency
    base = np.floor(p).astype(np.int64)
    f = p - base
    f = f * f * (3 - 2 * f)
    out = np.zeros(len(points))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (
                    (f[:, 0] if dx else 1 - f[:, 0])
                    * (f[:, 1] if dy else 1 - f[:, 1])
                    * (f[:, 2] if dz else 1 - f[:, 2])
                )
                out += w * _hash(base[:, 0] + dx, base[:, 1] + dy, base[:, 2] + dz, seed)
    return out


def fractal_noise(points: np.ndarray, frequency: float, seed: int, octaves: int = 3) -> np.ndarray:
    total, amp, norm = np.zeros(len(points)), 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(points, frequency * 2**o, seed + o)
        norm += amp
        amp *= 0.5
    return total / norm


#: a face vertex within this of the mouth's inside (its cavity and tongue) is on a lip's inner rim (m)
LIP_RIM_GAP = 0.0025
#: the lips' red reaches this far from their inner rims (m): about 7 mm up the upper lip's front and
#: 10 mm down the lower lip's on Anny's mean face
LIP_REACH = 0.011


class FaceFeatures:
    """Where the eyes, brows and lips are, from the canonical body and its regions."""

    def __init__(self, vertices: np.ndarray, regions: np.ndarray):
        eyes = vertices[regions == REGION["eyes"]]
        face = vertices[regions == REGION["face"]]
        self.eye_centres = []
        for side in (1.0, -1.0):
            pts = eyes[eyes[:, 0] * side > 0] if len(eyes) else face[:1]
            self.eye_centres.append(pts.mean(0))
        self.eye_radius = max(0.008, float(np.ptp(eyes[:, 0]) / 4)) if len(eyes) else 0.012
        mouth = vertices[regions == REGION["mouth"]]
        eye_y = np.mean([c[1] for c in self.eye_centres])
        centre = mouth.mean(0) if len(mouth) else np.array([0.0, eye_y - 0.07, face[:, 2].max()])
        front = face[(np.abs(face[:, 0]) < 0.01) & (np.abs(face[:, 1] - centre[1]) < 0.01)]
        self.mouth = np.array([0.0, centre[1], front[:, 2].max() if len(front) else centre[2]])
        # the lips' inner rims: face vertices where the mouth's inside begins (None: no mouth region)
        self.lip_rim, self._rim_tree = None, None
        if len(mouth):
            near = cKDTree(mouth).query(face, distance_upper_bound=LIP_RIM_GAP)[0] < LIP_RIM_GAP
            if near.any():
                self.lip_rim = face[near]
                self._rim_tree = cKDTree(self.lip_rim)

    def lips(self, points: np.ndarray) -> np.ndarray:
        """(P,) bool: the points on the lips, within :data:`LIP_REACH` of their inner rims (less towards the
        corners); without a mouth region, an ellipse about the mouth's front."""
        if self.lip_rim is None:
            d = points - self.mouth
            return ((d[:, 0] / 0.026) ** 2 + (d[:, 1] / 0.009) ** 2 < 1.0) & (d[:, 2] > -0.02)
        distance = self._rim_tree.query(points)[0]
        corner = 1.15 * np.abs(self.lip_rim[:, 0]).max()
        reach = LIP_REACH * np.sqrt(np.clip(1 - (points[:, 0] / corner) ** 2, 0.12, 1))
        return distance < reach


def skin_albedo(points, regions, base_color, features: FaceFeatures, seed: int) -> np.ndarray:
    """Skin with mottling and pores, whitish eyes with dark irises, brows and lips."""
    base = np.asarray(base_color)
    mottle = fractal_noise(points, 12.0, seed)
    pores = value_noise(points, 160.0, seed + 7)
    col = base[None] * (0.86 + 0.22 * mottle[:, None]) * (0.96 + 0.06 * pores[:, None])
    freckle = value_noise(points, 55.0, seed + 3) > 0.86
    col[freckle] *= np.array([0.85, 0.75, 0.7])
    eye = regions == REGION["eyes"]
    if eye.any():
        sclera = np.array([0.93, 0.92, 0.9])
        col[eye] = sclera
        for c in features.eye_centres:
            d = points[eye] - c
            front = d[:, 2] / (np.linalg.norm(d, axis=1) + 1e-9)
            iris = front > 0.8
            idx = np.flatnonzero(eye)
            col[idx[iris]] = np.array([0.25, 0.16, 0.1])
            col[idx[front > 0.95]] = np.array([0.03, 0.03, 0.03])
    face = regions == REGION["face"]
    for c in features.eye_centres:  # brows: a dark band above each eye
        d = points - c
        brow = face & (d[:, 1] > 0.012) & (d[:, 1] < 0.022) & (np.abs(d[:, 0]) < 0.026) & (d[:, 2] > -0.012)
        col[brow] = np.array([0.2, 0.13, 0.08])
    lips = face & features.lips(points)
    col[lips] = base * np.array([0.95, 0.55, 0.55])
    col[regions == REGION["mouth"]] = np.array([0.35, 0.08, 0.1])
    return np.clip(col, 0, 1)


def garment_albedo(points: np.ndarray, spec: GarmentSpec, seed: int) -> np.ndarray:
    """Two-colour patterns with a little fabric noise."""
    a, b = np.asarray(spec.colors[0]), np.asarray(spec.colors[1])
    x, y, z = points.T
    if spec.pattern == "stripes":
        t = (np.sin(2 * np.pi * y / 0.06) > 0).astype(float)
    elif spec.pattern == "checker":
        t = ((np.floor(x / 0.05) + np.floor(y / 0.05) + np.floor(z / 0.05)) % 2).astype(float)
    elif spec.pattern == "dots":
        cell = 0.045
        q = np.stack([x, y, z], 1) / cell
        t = (np.linalg.norm(q - np.round(q), axis=1) < 0.28).astype(float)
    elif spec.pattern == "plaid":
        t = 0.5 * ((np.sin(2 * np.pi * x / 0.08) > 0.3) + (np.sin(2 * np.pi * y / 0.08) > 0.3))
    else:
        t = np.zeros(len(points))
    col = a[None] * (1 - t[:, None]) + b[None] * t[:, None]
    weave = value_noise(points, 300.0, seed + 11)
    return np.clip(col * (0.92 + 0.12 * weave[:, None]), 0, 1)


def hair_albedo(points: np.ndarray, color, seed: int) -> np.ndarray:
    """Dark hair with strands running downwards (noise stretched along y)."""
    stretched = points * np.array([1.0, 0.08, 1.0])
    strands = fractal_noise(stretched, 220.0, seed + 21, octaves=2)
    return np.clip(np.asarray(color)[None] * (0.7 + 0.6 * strands[:, None]), 0, 1)


def shading(normals: np.ndarray) -> np.ndarray:
    """Baked Lambert lighting in the canonical frame: ambient plus one key light, (N,) factors.

    Two-sided: the normals of open cloth and hair sheets may point either way.
    """
    light = np.array([0.35, 0.55, 0.76])
    light = light / np.linalg.norm(light)
    n = normals / (np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12)
    return 0.62 + 0.38 * np.abs(n @ light)
