"""An animated, skinned glTF binary (GLB) of the avatar's meshes: the body and its clothing bound to the
body model's skeleton in the rest pose, and one key a frame for every joint's rotation and the root's
translation, so that any glTF viewer (Blender, three.js, a phone) plays the capture's motion.

glTF skinning is linear blend skinning: a vertex is Σ_j w_j (G_j B_j) v with G_j the joint's global
transform (its node and its ancestors') and B_j its inverse bind matrix. The body model's rest joints
are world-aligned frames at J_j, so B_j = translate(-J_j) and G_j B_j is the LBS transform A_j of
:func:`delta.body.lbs.rigid_transforms`: the file reproduces the model's posing exactly, up to two
limits of the format kept in plain view: eight influences a vertex in two sets of four (the largest,
renormalised; the upsampled Anny body has up to ten: under 0.4 % of a vertex's weight is lost), and no
pose correctives. A viewer that reads only the first set (three.js) renormalises its four: a posed
vertex then moves by 2.4 mm at the 99th percentile, 13 mm at most, in random poses of 0.15 rad a joint.

The world is turned so that the capture's up (:mod:`delta.body.upright`) is glTF's +y and its floor (the
soles, by the median over frames) is y = 0, the first frame's root above the origin: the avatar stands
upright on any viewer's ground.
Shapes: V vertices, T triangles, J joints, F frames.
"""

from __future__ import annotations

import json
import os
import struct

import numpy as np
import torch

from delta.body.rotations import matrix_to_quaternion
from delta.body.upright import Upright, rotation_between
from delta.io import atomic_path

#: influences a vertex keeps, in sets of four (JOINTS_0 / WEIGHTS_0 the largest, JOINTS_1 / WEIGHTS_1 the next)
INFLUENCES = 8
_FLOAT, _USHORT, _UINT = 5126, 5123, 5125
_ARRAY, _ELEMENTS = 34962, 34963
_TYPES = {1: "SCALAR", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


def influences(weights: np.ndarray, count: int = INFLUENCES) -> tuple[np.ndarray, np.ndarray]:
    """(V, count) uint16 joint indices and float32 weights of the ``count`` largest of (V, J) skinning
    weights, renormalised to sum to 1."""
    weights = np.asarray(weights, dtype=np.float64)
    J = weights.shape[1]
    if J < count:  # fewer joints than influences: the rest weigh nothing (on joint 0)
        weights = np.concatenate([weights, np.zeros((len(weights), count - J))], 1)
    idx = np.argsort(-weights, axis=1, kind="stable")[:, :count]
    w = np.take_along_axis(weights, idx, 1)
    idx[idx >= J] = 0
    w = w / np.maximum(w.sum(1, keepdims=True), 1e-12)
    return idx.astype(np.uint16), w.astype(np.float32)


def world_transform(upright: Upright, root_start: np.ndarray, sole: float = 0.0) -> np.ndarray:
    """(4, 4) the capture's world -> glTF's: its up onto +y, its floor at y = 0, the first frame's root
    (3,) above the origin. The capture's floor is its lowest joint's; ``sole`` (m) lowers it to where
    the soles are (the rest body's lowest vertex below its lowest joint)."""
    U = rotation_between(upright.up.double(), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)).numpy()
    shift = -(U @ np.asarray(root_start, dtype=np.float64))
    shift[1] = -(upright.floor - sole)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = U, shift
    return M


def quaternions(rotations: np.ndarray) -> np.ndarray:
    """(F, J, 3, 3) rotations -> (F, J, 4) unit quaternions (x, y, z, w), each joint's sign kept continuous
    over the frames (a key and its negation are the same rotation, but not to an interpolator)."""
    q = matrix_to_quaternion(torch.from_numpy(np.ascontiguousarray(rotations, dtype=np.float64)))
    q = q.numpy()[..., [1, 2, 3, 0]]  # (w, x, y, z) -> glTF's (x, y, z, w)
    # each key takes the sign nearer the previous key's (as flipped): the running product of the signs
    steps = np.where((q[1:] * q[:-1]).sum(-1) < 0, -1.0, 1.0)
    signs = np.concatenate([np.ones((1,) + q.shape[1:-1]), np.cumprod(steps, 0)])
    return q * signs[..., None]


class _Buffer:
    """The binary chunk and the accessors over it."""

    def __init__(self):
        self.data, self.views, self.accessors = bytearray(), [], []

    def add(self, array: np.ndarray, component: int, target: int | None = None, bounds: bool = False) -> int:
        array = np.ascontiguousarray(array)
        while len(self.data) % 4:
            self.data.append(0)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": array.nbytes}
        if target is not None:
            view["target"] = target
        self.data += array.tobytes()
        self.views.append(view)
        width = 1 if array.ndim == 1 else int(np.prod(array.shape[1:]))
        acc = {"bufferView": len(self.views) - 1, "componentType": component, "count": int(array.shape[0]),
               "type": _TYPES[width]}  # fmt: skip
        if bounds:
            flat = array.reshape(len(array), -1)
            acc["min"], acc["max"] = flat.min(0).tolist(), flat.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def animated_glb(meshes: dict[str, dict], rest_joints: np.ndarray, parents: np.ndarray, joint_names: list[str],
                 rotations: np.ndarray, root_translation: np.ndarray, times: np.ndarray,
                 world: np.ndarray) -> bytes:  # fmt: skip
    """The GLB bytes of skinned ``meshes`` ({name: {"vertices" (V, 3) in the rest pose, "faces" (T, 3),
    "colors" (V, 3) in [0, 1], "weights" (V, J)}}) animated by (F, J, 3, 3) local joint ``rotations`` and
    the (F, 3) body translation at ``times`` (F,) seconds, the whole under the (4, 4) ``world``."""
    rest_joints, parents = np.asarray(rest_joints, np.float64), np.asarray(parents)
    J = len(parents)
    buf = _Buffer()
    # nodes: 0 the avatar (the world transform), 1..J the joints, then one node a mesh
    children: dict[int, list[int]] = {j: [] for j in range(J)}
    roots = []
    for j, p in enumerate(parents):
        (roots if p < 0 else children[int(p)]).append(j)
    nodes = [{"name": "avatar", "matrix": world.T.reshape(-1).tolist(), "children": [1 + r for r in roots]}]
    for j in range(J):
        p = int(parents[j])
        local = rest_joints[j] - (rest_joints[p] if p >= 0 else 0.0)
        node = {"name": joint_names[j], "translation": local.tolist()}
        if children[j]:
            node["children"] = [1 + c for c in children[j]]
        nodes.append(node)
    ibm = np.tile(np.eye(4, dtype=np.float32), (J, 1, 1))
    ibm[:, :3, 3] = -rest_joints
    skin = {"joints": list(range(1, J + 1)), "inverseBindMatrices": buf.add(ibm.transpose(0, 2, 1).reshape(J, 16), _FLOAT),
            "skeleton": 0}  # fmt: skip
    gl_meshes = []
    for name, m in meshes.items():
        if len(m["faces"]) == 0:
            continue
        joints, weights = influences(m["weights"])
        attributes = {"POSITION": buf.add(np.asarray(m["vertices"], np.float32), _FLOAT, _ARRAY, bounds=True),
                      "COLOR_0": buf.add(np.clip(np.asarray(m["colors"], np.float32), 0, 1), _FLOAT, _ARRAY)}  # fmt: skip
        for k in range(0, INFLUENCES, 4):
            attributes[f"JOINTS_{k // 4}"] = buf.add(joints[:, k : k + 4], _USHORT, _ARRAY)
            attributes[f"WEIGHTS_{k // 4}"] = buf.add(weights[:, k : k + 4], _FLOAT, _ARRAY)
        indices = buf.add(np.asarray(m["faces"], np.uint32).reshape(-1), _UINT, _ELEMENTS)
        gl_meshes.append({"name": name, "primitives": [{"attributes": attributes, "indices": indices, "material": 0}]})
        nodes.append({"name": name, "mesh": len(gl_meshes) - 1, "skin": 0})
    # animation: every joint's rotation, the root joints' translation, one key a frame (linear)
    t = buf.add(np.asarray(times, np.float32), _FLOAT, bounds=True)
    q = quaternions(rotations).astype(np.float32)
    samplers, channels = [], []
    for j in range(J):
        samplers.append({"input": t, "output": buf.add(q[:, j], _FLOAT), "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": 1 + j, "path": "rotation"}})
    for r in roots:
        moved = (rest_joints[r] + np.asarray(root_translation, np.float64)).astype(np.float32)
        samplers.append({"input": t, "output": buf.add(moved, _FLOAT), "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": 1 + r, "path": "translation"}})
    doc = {
        "asset": {"version": "2.0", "generator": "delta (DELTA avatars)"},
        "scene": 0,
        "scenes": [{"nodes": [0] + [1 + J + k for k in range(len(gl_meshes))]}],
        "nodes": nodes,
        "meshes": gl_meshes,
        "skins": [skin],
        "materials": [
            {
                "name": "albedo",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [1, 1, 1, 1],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 1.0,
                },
            }
        ],  # fmt: skip
        "animations": [{"name": "capture", "samplers": samplers, "channels": channels}],
        "buffers": [{"byteLength": len(buf.data)}],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
    }
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    data = bytes(buf.data) + b"\0" * (-len(buf.data) % 4)
    total = 12 + 8 + len(text) + 8 + len(data)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(text), b"JSON") + text
            + struct.pack("<I4s", len(data), b"BIN\0") + data)  # fmt: skip


def write_animated_glb(path: str | os.PathLike, *args, **kwargs) -> None:
    """:func:`animated_glb` written atomically to ``path``."""
    blob = animated_glb(*args, **kwargs)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(blob)
