"""Clothing and hair as separate meshes skinned with the body.

Tight garments are shells offset from the skin along the normals of the body
regions they cover; a skirt (and a dress's lower part) is a flared surface of
revolution hanging from the hips, skinned to the pelvis only so that it does
not follow the legs; hair is a cap over the scalp plus, for long hair, a sheet
down the back. Each layer carries a per-vertex ``sway`` in [0, 1]: how much of
the non-rigid motion (see :func:`nonrigid_offsets`) it takes.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from delta.body.model import REGION, BodyModel
from delta.synthetic.spec import GarmentSpec

#: label of each layer in the ground-truth label maps (body regions take 1 + REGION index)
LAYER_LABELS = {"upper": 7, "lower": 8, "dress": 9, "hair": 10}
BODY_LABEL_OFFSET = 1

_TORSO = ("root", "spine", "pelvis", "clavicle", "shoulder")
_UPPER_ARM = ("upperarm",)
_LOWER_ARM = ("lowerarm",)
_LEGS_UPPER = ("upperleg",)
_LEGS_LOWER = ("lowerleg",)


@dataclasses.dataclass
class Layer:
    """A clothing or hair mesh in the canonical (zero-pose, shaped) space."""

    name: str
    label: int
    vertices: np.ndarray
    """(Vg, 3) canonical positions."""
    faces: np.ndarray
    """(Fg, 3) triangles."""
    weights: np.ndarray
    """(Vg, J) skinning weights."""
    sway: np.ndarray
    """(Vg,) share of the non-rigid motion."""
    centre: np.ndarray
    """(3,) the vertical axis the non-rigid motion turns about passes here."""
    garment: GarmentSpec | None = None


def _dominant(model: BodyModel, prefixes: tuple[str, ...]) -> np.ndarray:
    names = model.joint_names
    ids = [j for j, n in enumerate(names) if n.startswith(prefixes)]
    return np.isin(model.weights.numpy().argmax(1), ids)


def _joint(model: BodyModel, rest_joints: np.ndarray, name: str) -> np.ndarray:
    return rest_joints[model.joint_names.index(name)]


def _shell(model, verts, normals, mask, thickness, name, spec, sway) -> Layer:
    """Offset the body faces whose three vertices are all in ``mask``."""
    faces = model.faces.numpy()
    keep = mask[faces].all(1)
    used = np.unique(faces[keep])
    remap = -np.ones(len(verts), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return Layer(
        name=name,
        label=LAYER_LABELS[name],
        vertices=verts[used] + thickness * normals[used],
        faces=remap[faces[keep]],
        weights=model.weights.numpy()[used],
        sway=np.full(len(used), sway),
        centre=verts[used].mean(0),
        garment=spec,
    )


def _revolution(centre, y_top, y_bottom, radius_top, flare, theta_range, n_theta, n_h, closed):
    """Grid of a flared surface of revolution about the vertical axis through ``centre``."""
    thetas = np.linspace(theta_range[0], theta_range[1], n_theta, endpoint=not closed)
    heights = np.linspace(y_top, y_bottom, n_h)
    depth = y_top - heights
    r = radius_top(thetas)[None, :] + flare * depth[:, None]
    x = centre[0] + r * np.sin(thetas)[None, :]
    z = centre[2] + r * np.cos(thetas)[None, :]
    y = np.broadcast_to(heights[:, None], x.shape)
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    faces = []
    cols = n_theta if closed else n_theta - 1
    for i in range(n_h - 1):
        for j in range(cols):
            a, b = i * n_theta + j, i * n_theta + (j + 1) % n_theta
            c, d = a + n_theta, b + n_theta
            faces += [(a, c, b), (b, c, d)]
    sway = np.repeat((depth / max(depth[-1], 1e-6)) ** 2, n_theta)
    return verts, np.array(faces, dtype=np.int64), sway


def _radius_profile(verts, centre, y, band, margin):
    """Body radius around the vertical axis at height ``y`` as a function of angle (interpolated)."""
    sel = np.abs(verts[:, 1] - y) < band
    d = verts[sel][:, [0, 2]] - centre[[0, 2]]
    ang = np.arctan2(d[:, 0], d[:, 1])
    rad = np.linalg.norm(d, axis=1)
    bins = np.linspace(-np.pi, np.pi, 37)
    prof = np.array([rad[(ang >= lo) & (ang < hi)].max(initial=0.0) for lo, hi in zip(bins[:-1], bins[1:])])
    prof = np.maximum(prof, prof.max() * 0.6) + margin
    mids = (bins[:-1] + bins[1:]) / 2

    def radius(thetas):
        t = (np.asarray(thetas) + np.pi) % (2 * np.pi) - np.pi
        return np.interp(t, mids, prof, period=2 * np.pi)

    return radius


def _pelvis_weights(model: BodyModel, n: int) -> np.ndarray:
    w = np.zeros((n, model.num_joints))
    w[:, 0] = 1.0  # the root carries the skirt: it turns with the body, not with the legs
    return w


def build_layers(
    model: BodyModel, rest_vertices: np.ndarray, rest_joints: np.ndarray, garments, hair: str
) -> list[Layer]:
    """Clothing and hair layers for a shaped body at rest (canonical space)."""
    v = rest_vertices
    normals = trimesh.Trimesh(v, model.faces.numpy(), process=False).vertex_normals
    regions = model.regions.numpy()
    skin_ok = np.isin(regions, [REGION["body"]])
    hip_y = 0.5 * (_joint(model, rest_joints, "upperleg01.L")[1] + _joint(model, rest_joints, "upperleg01.R")[1])
    knee_y = _joint(model, rest_joints, "lowerleg01.L")[1]
    waist_y = hip_y + 0.10
    pelvis = rest_joints[0]
    layers = []
    for g in garments:
        if g.kind in ("tshirt", "longsleeve"):
            arms = _UPPER_ARM + (_LOWER_ARM if g.kind == "longsleeve" else ())
            mask = (_dominant(model, _TORSO) | _dominant(model, arms)) & skin_ok & (v[:, 1] > hip_y + 0.02)
            if g.kind == "tshirt":
                mask &= ~_dominant(model, ("upperarm02",))
            layers.append(_shell(model, v, normals, mask, g.thickness, "upper", g, 0.0))
        elif g.kind in ("trousers", "shorts"):
            legs = _LEGS_UPPER + (_LEGS_LOWER if g.kind == "trousers" else ())
            mask = (_dominant(model, legs) | (_dominant(model, _TORSO) & (v[:, 1] < waist_y))) & skin_ok
            if g.kind == "shorts":
                mask &= ~_dominant(model, ("upperleg02",))
            layers.append(_shell(model, v, normals, mask, g.thickness, "lower", g, 0.0))
        else:  # skirt or dress: a flared surface of revolution from the waist
            y_top = waist_y + (0.0 if g.kind == "skirt" else 0.04)
            y_hem = knee_y - (0.02 if g.kind == "skirt" else 0.18)
            trunk = _dominant(model, _TORSO + _LEGS_UPPER)  # not the hands hanging beside the hips
            radius = _radius_profile(v[trunk], pelvis, y_top, 0.03, g.thickness + 0.01)
            sv, sf, sway = _revolution(pelvis, y_top, y_hem, radius, 0.35, (-np.pi, np.pi), 96, 28, True)
            if g.kind == "dress":
                mask = _dominant(model, _TORSO) & skin_ok & (v[:, 1] > waist_y)
                top = _shell(model, v, normals, mask, g.thickness, "dress", g, 0.0)
                sf = np.concatenate([top.faces, sf + len(top.vertices)])
                sw = np.concatenate([top.weights, _pelvis_weights(model, len(sv))])
                sv, sway = np.concatenate([top.vertices, sv]), np.concatenate([top.sway, sway])
            else:
                sw = _pelvis_weights(model, len(sv))
            name = "dress" if g.kind == "dress" else "lower"
            layers.append(Layer(name, LAYER_LABELS[name], sv, sf, sw, sway, pelvis.copy(), g))
    if hair != "none":
        layers.append(_hair(model, v, normals, rest_joints, hair))
    return layers


def _hair(model, v, normals, rest_joints, hair) -> Layer:
    face = model.regions.numpy() == REGION["face"]
    fv = v[face]
    top_y = fv[:, 1].max()
    centre = np.array([0.0, top_y - 0.11, fv[:, 2].mean()])
    eye_y = centre[1] + 0.02
    scalp = face & (v[:, 1] > eye_y + 0.035)
    scalp |= face & (v[:, 2] < centre[2] - 0.02) & (v[:, 1] > eye_y - 0.06)
    cap = _shell(model, v, normals, scalp, 0.012, "hair", None, 0.0)
    head_idx = model.joint_names.index("head")
    cap.weights = np.zeros_like(cap.weights)
    cap.weights[:, head_idx] = 1.0
    if hair == "short":
        return cap
    radius = _radius_profile(v, centre, eye_y - 0.02, 0.02, 0.02)
    y_top, y_bottom = eye_y + 0.02, _joint(model, rest_joints, "neck01")[1] - 0.16
    sv, sf, sway = _revolution(centre, y_top, y_bottom, radius, 0.12, (np.pi * 0.42, np.pi * 1.58), 48, 20, False)
    w = np.zeros((len(sv), model.num_joints))
    t = np.clip((y_top - sv[:, 1]) / (y_top - y_bottom), 0, 1)
    lower = [j for j, n in enumerate(model.joint_names) if n.startswith("spine01")] or [0]
    w[:, head_idx] = 1 - t
    w[:, lower[0]] += t
    return Layer(
        name="hair",
        label=LAYER_LABELS["hair"],
        vertices=np.concatenate([cap.vertices, sv]),
        faces=np.concatenate([cap.faces, sf + len(cap.vertices)]),
        weights=np.concatenate([cap.weights, w]),
        sway=np.concatenate([cap.sway, sway]),
        centre=centre,
    )


def nonrigid_offsets(
    layer: Layer, normals: np.ndarray, frame_time: float, turn_rate: float, amplitude: float
) -> np.ndarray:
    """Canonical-space non-rigid displacement of a layer's vertices at one instant.

    Loose parts (``sway`` > 0) twist about the vertical axis against the turning
    direction, lagging more the faster the subject turns, and swing with a slow
    pendulum; the displacement grows with each vertex's ``sway``. Tight parts
    ripple a few millimetres along their ``normals`` (folds travelling up the cloth).
    """
    if amplitude == 0:
        return np.zeros_like(layer.vertices)
    t = frame_time
    if not layer.sway.any():
        if layer.garment is None:
            return np.zeros_like(layer.vertices)
        phase = 2 * np.pi * (layer.vertices[:, 1] / 0.12 + 0.8 * t)
        return amplitude * 0.003 * np.sin(phase)[:, None] * normals
    twist = amplitude * layer.sway * (-0.25 * np.tanh(turn_rate / 4) + 0.08 * np.sin(2 * np.pi * 0.7 * t))
    rel = layer.vertices - layer.centre
    c, s = np.cos(twist), np.sin(twist)
    x = c * rel[:, 0] + s * rel[:, 2]
    z = -s * rel[:, 0] + c * rel[:, 2]
    swing = amplitude * layer.sway * 0.03 * np.sin(2 * np.pi * 0.45 * t + 0.5)
    return np.stack([x - rel[:, 0] + swing, np.zeros_like(x), z - rel[:, 2]], -1)
