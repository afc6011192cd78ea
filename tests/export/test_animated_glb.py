"""The animated GLB, read back by a glTF reader and skinned by glTF's own rules written here: every key frame
reproduces the body model's posing (in the file's upright world), and trimesh opens the file."""

import dataclasses
import io
import json
import struct

import numpy as np
import pytest
import torch
import trimesh

from delta.body.lbs import batch_rodrigues, lbs
from delta.body.upright import Upright
from delta.export.animated import animated_glb, influences, world_transform
from tests.conftest import soft_tree_model, upsampled

D = torch.float64
COMPONENTS = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}
WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def read_glb(blob: bytes) -> tuple[dict, list[np.ndarray]]:
    magic, version, total = struct.unpack("<4sII", blob[:12])
    assert magic == b"glTF" and version == 2 and total == len(blob)
    n, kind = struct.unpack("<I4s", blob[12:20])
    assert kind == b"JSON"
    doc = json.loads(blob[20 : 20 + n])
    m, kind = struct.unpack("<I4s", blob[20 + n : 28 + n])
    assert kind == b"BIN\0"
    data = blob[28 + n : 28 + n + m]
    arrays = []
    for acc in doc["accessors"]:
        view = doc["bufferViews"][acc["bufferView"]]
        assert view["byteOffset"] % 4 == 0
        a = np.frombuffer(data, COMPONENTS[acc["componentType"]], acc["count"] * WIDTH[acc["type"]], view["byteOffset"])
        arrays.append(a.reshape(acc["count"], -1) if WIDTH[acc["type"]] > 1 else a)
    return doc, arrays


def quat_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])  # fmt: skip


def skinned(doc: dict, arrays: list[np.ndarray], key: int, mesh: int = 0, only_first_set: bool = False) -> np.ndarray:
    """The mesh's vertices at animation key ``key``, by glTF's node hierarchy and skinning rules."""
    nodes = [dict(n) for n in doc["nodes"]]
    for ch in doc["animations"][0]["channels"]:
        value = arrays[doc["animations"][0]["samplers"][ch["sampler"]]["output"]][key]
        nodes[ch["target"]["node"]][ch["target"]["path"]] = value
    local = []
    for n in nodes:
        if "matrix" in n:
            local.append(np.array(n["matrix"], np.float64).reshape(4, 4).T)
            continue
        M = np.eye(4)
        M[:3, :3] = quat_matrix(np.asarray(n.get("rotation", [0, 0, 0, 1]), np.float64))
        M[:3, 3] = n.get("translation", [0, 0, 0])
        local.append(M)
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}

    def glob(i):
        return glob(parent[i]) @ local[i] if i in parent else local[i]

    skin = doc["skins"][0]
    ibm = arrays[skin["inverseBindMatrices"]].reshape(-1, 4, 4).transpose(0, 2, 1)
    joint_M = np.stack([glob(j) @ b for j, b in zip(skin["joints"], ibm)])
    prim = doc["meshes"][mesh]["primitives"][0]["attributes"]
    sets = sorted(k[-1] for k in prim if k.startswith("JOINTS_"))
    v = arrays[prim["POSITION"]].astype(np.float64)
    joints = np.concatenate([arrays[prim[f"JOINTS_{s}"]] for s in sets], 1)
    w = np.concatenate([arrays[prim[f"WEIGHTS_{s}"]] for s in sets], 1).astype(np.float64)
    if only_first_set:  # what a viewer that reads one set of four does: renormalise it
        joints, w = joints[:, :4], w[:, :4] / w[:, :4].sum(1, keepdims=True)
    M = (w[:, :, None, None] * joint_M[joints.astype(int)]).sum(1)
    return np.einsum("vij,vj->vi", M[:, :3, :3], v) + M[:, :3, 3]


def test_each_key_frame_is_the_body_models_posing_in_the_upright_world():
    model = dataclasses.replace(soft_tree_model(D), posedirs=None)  # glTF has no pose correctives
    gen = torch.Generator().manual_seed(3)
    F = 4
    betas = torch.randn(1, 2, generator=gen, dtype=D)
    pose = 0.6 * torch.randn(F, model.num_joints, 3, generator=gen, dtype=D)
    transl = torch.randn(F, 3, generator=gen, dtype=D)
    out = lbs(model, betas.expand(F, -1), pose, transl=transl)
    rest = lbs(model, betas, torch.zeros(1, model.num_joints, 3, dtype=D))
    assert model.num_joints == 4  # blended weights over four joints: glTF's four influences hold them all
    up = torch.nn.functional.normalize(torch.tensor([0.3, -0.9, 0.2], dtype=D), dim=0)
    upright = Upright(up, -1.1, 0.0, F)
    world = world_transform(upright, out.joints[0, 0].numpy())
    mesh = {"vertices": rest.vertices[0].numpy(), "faces": model.faces.numpy(), "colors": np.full((model.num_vertices, 3), 0.5),
            "weights": model.weights.numpy()}  # fmt: skip
    blob = animated_glb({"body": mesh}, rest.rest_joints[0].numpy(), model.parents.numpy(), model.joint_names,
                        batch_rodrigues(pose).numpy(), transl.numpy(), np.arange(F) / 30.0, world)  # fmt: skip
    doc, arrays = read_glb(blob)
    for f in range(F):
        expected = out.vertices[f].numpy() @ world[:3, :3].T + world[:3, 3]
        np.testing.assert_allclose(skinned(doc, arrays, f), expected, atol=2e-5)
    # the world: the capture's up is +y, its floor y = 0, the first frame's root above the origin
    np.testing.assert_allclose(world[:3, :3] @ up.numpy(), [0, 1, 0], atol=1e-12)
    floor_point = -1.1 * up.numpy()  # a point of the floor (u·x = floor)
    assert (world[:3, :3] @ floor_point + world[:3, 3])[1] == pytest.approx(0.0, abs=1e-12)
    root0 = world[:3, :3] @ out.joints[0, 0].numpy() + world[:3, 3]
    assert root0[0] == pytest.approx(0.0, abs=1e-9) and root0[2] == pytest.approx(0.0, abs=1e-9)
    times = arrays[doc["animations"][0]["samplers"][0]["input"]]
    np.testing.assert_allclose(times, np.arange(F) / 30.0, rtol=1e-6)
    loaded = trimesh.load(io.BytesIO(blob), file_type="glb", force="scene")  # a third-party reader opens it
    assert sum(len(g.vertices) for g in loaded.geometry.values()) == model.num_vertices


def test_influences_keep_the_largest_weights_renormalised():
    w = np.array([[0.05, 0.4, 0.1, 0.3, 0.15, 0.0], [1.0, 0, 0, 0, 0, 0]])
    joints, weights = influences(w, 4)
    assert joints[0].tolist() == [1, 3, 4, 2] and joints[1, 0] == 0
    np.testing.assert_allclose(weights[0], np.array([0.4, 0.3, 0.15, 0.1]) / 0.95, rtol=1e-6)
    np.testing.assert_allclose(weights.sum(1), 1.0, rtol=1e-6)
    joints, weights = influences(w)  # eight of six joints: all kept, the rest weigh nothing
    assert joints.shape == (2, 8) and weights[0, 6:].tolist() == [0, 0]
    np.testing.assert_allclose(weights[0, :6], np.sort(w[0])[::-1], rtol=1e-6)


@pytest.mark.slow
def test_the_anny_body_keeps_its_posing_with_eight_influences(anny_files):
    """Anny's upsampled weights have up to ten influences a vertex: eight move no posed vertex by a
    millimetre; a viewer reading only the first four (renormalised) moves a few by centimetres."""
    model = upsampled(anny_files["body"], dtype=D)
    gen = torch.Generator().manual_seed(0)
    pose = 0.15 * torch.randn(2, model.num_joints, 3, generator=gen, dtype=D)
    betas = torch.zeros(2, model.num_shape, dtype=D)
    out = lbs(model, betas, pose)
    rest = lbs(model, betas[:1], torch.zeros(1, model.num_joints, 3, dtype=D))
    mesh = {"vertices": rest.vertices[0].numpy(), "faces": model.faces.numpy(), "colors": np.zeros((model.num_vertices, 3)),
            "weights": model.weights.numpy()}  # fmt: skip
    blob = animated_glb({"body": mesh}, rest.rest_joints[0].numpy(), model.parents.numpy(), model.joint_names,
                        batch_rodrigues(pose).numpy(), np.zeros((2, 3)), np.array([0.0, 0.04]), np.eye(4))  # fmt: skip
    doc, arrays = read_glb(blob)
    err = np.linalg.norm(skinned(doc, arrays, 1) - out.vertices[1].numpy(), axis=1)
    assert err.max() < 1e-3
    four = np.linalg.norm(skinned(doc, arrays, 1, only_first_set=True) - out.vertices[1].numpy(), axis=1)
    assert np.median(four) < 1e-5 and 1e-3 < np.percentile(four, 99) < 5e-3 and four.max() < 0.03


def test_a_one_frame_animation_and_a_mesh_without_faces():
    """A photograph's avatar (one frame) still makes a valid file; an empty clothing mesh is left out."""
    model = dataclasses.replace(soft_tree_model(D), posedirs=None)
    pose = torch.zeros(1, model.num_joints, 3, dtype=D)
    rest = lbs(model, torch.zeros(1, 2, dtype=D), pose)
    meshes = {"body": {"vertices": rest.vertices[0].numpy(), "faces": model.faces.numpy(),
                       "colors": np.zeros((model.num_vertices, 3)), "weights": model.weights.numpy()},
              "clothing": {"vertices": np.zeros((0, 3)), "faces": np.zeros((0, 3), np.int64), "colors": np.zeros((0, 3)),
                           "weights": np.zeros((0, model.num_joints))}}  # fmt: skip
    blob = animated_glb(meshes, rest.rest_joints[0].numpy(), model.parents.numpy(), model.joint_names,
                        batch_rodrigues(pose).numpy(), np.zeros((1, 3)), np.zeros(1), np.eye(4))  # fmt: skip
    doc, arrays = read_glb(blob)
    assert [m["name"] for m in doc["meshes"]] == ["body"]
    np.testing.assert_allclose(skinned(doc, arrays, 0), rest.vertices[0].numpy(), atol=1e-6)


def test_quaternion_keys_keep_one_sign_through_a_turn_past_a_half():
    """A joint turning steadily through 1.6 turns: consecutive keys are the nearer of q and -q (an
    interpolator would otherwise take the long way round), and each is still its rotation."""
    from delta.body.upright import axis_angle_matrix
    from delta.export.animated import quaternions

    axis = torch.tensor([0.2, 1.0, -0.3], dtype=D)
    angles = np.linspace(0, 3.2 * np.pi, 40)
    R = torch.stack([axis_angle_matrix(axis, float(a)) for a in angles])[:, None].numpy()
    q = quaternions(R)
    assert ((q[1:] * q[:-1]).sum(-1) > 0).all()
    back = np.stack([quat_matrix(k) for k in q[:, 0]])
    np.testing.assert_allclose(back, R[:, 0], atol=1e-9)
