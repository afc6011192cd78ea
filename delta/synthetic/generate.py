"""Generate one synthetic monocular capture with ground truth.

Writes ``{out}/{subject}.mp4`` (all that a real capture has) and ground truth
apart in ``{out}/gt/``: ``params.npz`` (body parameters, camera), ``frames.h5``
(masks, labels, depth, keypoints per frame), ``meshes.h5`` (canonical and posed
body and layer meshes), ``splits.json``, ``labels.json`` and canonical PLYs.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch
import trimesh

from delta import DeltaError
from delta.body.expressions import ExpressionSpace, with_expressions
from delta.body.face_motion import driven_poses
from delta.body.face_points import FacePoints, dense_face_points
from delta.body.keypoints import openpose18_map
from delta.body.lbs import lbs, skin
from delta.body.model import REGION_NAMES, BodyModel, load_body_model
from delta.cameras.models import OrthographicCamera, PinholeCamera, look_at
from delta.io import atomic_path, save_json, save_npz
from delta.synthetic import textures
from delta.synthetic.garments import BODY_LABEL_OFFSET, LAYER_LABELS, Layer, build_layers, nonrigid_offsets
from delta.synthetic.motion import face_sequence, novel_face_sequence, novel_sequence, turn_sequence
from delta.synthetic.talk import novel_expressions, talk_sequence
from delta.synthetic.raycast import SceneMesh, render
from delta.synthetic.spec import SubjectSpec

log = logging.getLogger(__name__)
FOURCC = {"ffv1": "FFV1", "mp4v": "mp4v"}


def label_names() -> dict[int, str]:
    names = {0: "background"}
    names.update({BODY_LABEL_OFFSET + i: f"body_{n}" for i, n in enumerate(REGION_NAMES)})
    names.update({v: k for k, v in LAYER_LABELS.items()})
    return names


#: share of the standing height an ``upper`` / ``head`` framing shows, from the top of the head down
UPPER_FRAMING = 0.35
HEAD_FRAMING = 0.2


def frame_span(spec: SubjectSpec, rest_y: np.ndarray) -> tuple[float, float]:
    """(height, centre) in metres of what the camera frames: the standing body (``full``) or its
    top ``UPPER_FRAMING`` (``upper``) or ``HEAD_FRAMING`` (``head``), with 5 cm of room above and below."""
    low, top = float(rest_y.min()), float(rest_y.max())
    share = {"upper": UPPER_FRAMING, "head": HEAD_FRAMING}.get(spec.framing)
    if share is not None:
        low = top - share * (top - low)
    return top - low + 0.1, (low + top) / 2


def make_camera(spec: SubjectSpec, height_m: float, centre_y: float):
    """A static camera framing ``height_m`` metres of a standing subject around height ``centre_y``."""
    H = W = spec.resolution
    fill = 0.86
    if spec.camera == "orthographic":
        s = 2 * fill / height_m
        return OrthographicCamera(torch.tensor(s, dtype=torch.float64),
                                  torch.tensor([0.0, -centre_y], dtype=torch.float64), W, H)  # fmt: skip
    distance = 3.2
    f = fill * H * distance / height_m
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=torch.float64)
    pitch = math.radians(spec.camera_pitch)
    target = torch.tensor([0.0, centre_y, 0.0], dtype=torch.float64)
    eye = target + distance * torch.tensor([0.0, math.sin(pitch), math.cos(pitch)], dtype=torch.float64)
    R, _ = look_at(eye, target, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    roll = math.radians(spec.camera_roll)  # about the optical axis: the subject appears turned clockwise
    Rz = torch.tensor([[math.cos(roll), -math.sin(roll), 0.0], [math.sin(roll), math.cos(roll), 0.0], [0.0, 0.0, 1.0]],
                      dtype=torch.float64)  # fmt: skip
    R = Rz @ R
    return PinholeCamera(K, R, -R @ eye, torch.tensor(spec.distortion, dtype=torch.float64), W, H)


def splits(spec: SubjectSpec) -> dict[str, list[int]]:
    if spec.driven is not None:  # one frame per driver frame
        return splits(spec.driven.by)
    turn = list(range(spec.turn_frames))
    test_view = turn[spec.test_view_every - 1 :: spec.test_view_every]
    held = set(test_view)
    return {
        "train": [f for f in turn if f not in held],
        "test_view": test_view,
        "test_pose": list(range(spec.turn_frames, spec.num_frames)),
    }


class _Albedo:
    """The subject's appearance: skin, garments and hair as solid textures."""

    def __init__(self, spec: SubjectSpec, layers: list[Layer], rest_vertices: np.ndarray, regions: np.ndarray):
        self.spec, self.layers = spec, layers
        self.features = textures.FaceFeatures(rest_vertices, regions)

    def __call__(self, objects: np.ndarray, points: np.ndarray, labels: np.ndarray) -> np.ndarray:
        out = np.zeros((len(points), 3))
        body = objects == 0
        if body.any():
            regions = labels[body].astype(np.int64) - BODY_LABEL_OFFSET
            out[body] = textures.skin_albedo(points[body], regions, self.spec.skin_color, self.features, self.spec.seed)
        for k, layer in enumerate(self.layers, start=1):
            sel = objects == k
            if not sel.any():
                continue
            if layer.garment is None:
                out[sel] = textures.hair_albedo(points[sel], self.spec.hair_color, self.spec.seed)
            else:
                out[sel] = textures.garment_albedo(points[sel], layer.garment, self.spec.seed + k)
        return out


def _normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return trimesh.Trimesh(vertices, faces, process=False).vertex_normals.copy()


def _phenotype_betas(spec: SubjectSpec, shape_space: str | None, anny_cache: str | None, num_shape: int):
    if not spec.phenotype:
        return torch.zeros(num_shape, dtype=torch.float64)
    if shape_space is None:
        raise DeltaError(f"subject '{spec.name}': a phenotype needs the Anny shape-space file")
    from delta.body.anny_convert import ShapeSpace, build_anny, phenotype_betas

    return phenotype_betas(ShapeSpace.load(shape_space), build_anny(anny_cache), spec.phenotype)[:num_shape]


def motion(spec: SubjectSpec, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(F, J, 3) poses of the capture's frames (its motion, then the held-out segment) and the body's
    turn rate (rad/s) per frame, which sways the garments and hair."""
    if spec.motion == "face":
        poses = np.concatenate([face_sequence(names, spec.turn_frames, spec.fps, spec.seed),
                                novel_face_sequence(names, spec.novel_frames, spec.seed)])  # fmt: skip
        return poses, np.zeros(spec.num_frames)
    turn, rate = turn_sequence(names, spec.turn_frames, spec.turns, spec.fps, spec.seed)
    poses = np.concatenate([turn, novel_sequence(names, spec.novel_frames, spec.seed)])
    return poses, np.concatenate([rate, np.zeros(spec.novel_frames)])


def face_actions(spec: SubjectSpec, names: list[str]) -> np.ndarray | None:
    """(F, E) facial-action activations of the capture's frames, or None for a still face."""
    if spec.expressions == "none":
        return None
    return np.concatenate([talk_sequence(names, spec.turn_frames, spec.fps, spec.seed),
                           novel_expressions(names, spec.novel_frames, spec.seed)])  # fmt: skip


def scene_motion(spec: SubjectSpec, names: list[str], expression_names: list[str]):
    """(poses (F, J, 3), turn rates (F,), facial actions (F, E) or None, times (F,) in s) of the capture's
    frames: its own motion, or a driven subject's anchor frame moved by the driver's face
    (:class:`delta.synthetic.spec.DrivenSpec`; its garments and hair held as at the anchor's time)."""
    d = spec.driven
    if d is None:
        poses, rates = motion(spec, names)
        return poses, rates, face_actions(spec, expression_names), np.arange(len(poses)) / spec.fps
    own = torch.from_numpy(motion(dataclasses.replace(spec, driven=None), names)[0][d.anchor])
    theirs = torch.from_numpy(motion(d.by, names)[0])
    poses = driven_poses(own, theirs, theirs[d.reference], names).numpy()
    F = len(poses)
    return poses, np.zeros(F), face_actions(d.by, expression_names), np.full(F, d.anchor / spec.fps)


def generate(
    spec: SubjectSpec,
    body_model: str | os.PathLike,
    out_dir: str | os.PathLike,
    shape_space: str | None = None,
    anny_cache: str | None = None,
    expressions: str | os.PathLike | None = None,
) -> None:
    """Render the capture of ``spec`` into ``out_dir`` (see the module docstring); a talking face
    needs the ``expressions`` space file."""
    out = Path(out_dir)
    model: BodyModel = load_body_model(body_model, dtype=torch.float64)
    if not model.name.startswith("anny"):
        raise DeltaError(f"synthetic captures are built on the Anny body model, got '{model.name}'")
    if spec.expressions != "none":
        if expressions is None:
            raise DeltaError(f"subject '{spec.name}': expressions '{spec.expressions}' need the expression-space "
                             "file (delta anny-expressions)")  # fmt: skip
        model = with_expressions(model, ExpressionSpace.load(expressions), str(expressions))
    betas = _phenotype_betas(spec, shape_space, anny_cache, model.num_shape)[None]
    zero = torch.zeros(1, model.num_joints, 3, dtype=torch.float64)
    with torch.no_grad():
        rest = lbs(model, betas, zero)
    rest_v, rest_j = rest.vertices[0].numpy(), rest.joints[0].numpy()
    layers = build_layers(model, rest_v, rest_j, spec.garments, spec.hair)
    camera = make_camera(spec, *frame_span(spec, rest_v[:, 1]))
    poses, rates, actions, times = scene_motion(spec, model.joint_names, model.expression_names)
    face = dense_face_points(model) if actions is not None else None
    transl = np.zeros((len(poses), 3))
    kp_map = openpose18_map(model)
    on_joint = kp_map.joint_weights.sum(1).numpy() > 0
    albedo = _Albedo(spec, layers, rest_v, model.regions.numpy())
    body_faces = model.faces.numpy()
    canon_n = [_normals(rest_v, body_faces)] + [_normals(l.vertices, l.faces) for l in layers]
    labels_v = [model.regions.numpy() + BODY_LABEL_OFFSET] + [np.full(len(l.vertices), l.label) for l in layers]
    F, H, W = len(poses), spec.resolution, spec.resolution
    gt = out / "gt"
    gt.mkdir(parents=True, exist_ok=True)
    video = out / f"{spec.name}.mp4"
    with atomic_path(video) as tmp_video, atomic_path(gt / "frames.h5") as tmp_frames, \
            atomic_path(gt / "meshes.h5") as tmp_meshes:  # fmt: skip
        writer = cv2.VideoWriter(str(tmp_video), cv2.VideoWriter_fourcc(*FOURCC[spec.codec]), spec.fps, (W, H))
        if not writer.isOpened():
            raise DeltaError(f"OpenCV cannot write '{spec.codec}' video to {video}")
        with h5py.File(tmp_frames, "w", track_order=False) as fh, h5py.File(tmp_meshes, "w") as mh:
            dsets = _frame_datasets(fh, F, H, W, len(kp_map.names), face)
            mesh_dsets = _mesh_datasets(mh, model, rest_v, layers, F)
            # the scene's topology, texture coordinates and labels never change: build them once
            offsets = np.cumsum([0, len(rest_v)] + [len(l.vertices) for l in layers])
            static = dict(
                faces=np.concatenate([body_faces] + [l.faces + o for l, o in zip(layers, offsets[1:])]),
                face_object=np.concatenate([np.zeros(len(body_faces), int)]
                                           + [np.full(len(l.faces), k) for k, l in enumerate(layers, start=1)]),
                canonical=np.concatenate([rest_v] + [l.vertices for l in layers]),
                canonical_normals=np.concatenate(canon_n),
                vertex_label=np.concatenate(labels_v).astype(np.uint8),
            )  # fmt: skip
            weights = [torch.from_numpy(l.weights) for l in layers]
            for f in range(F):
                pose = torch.from_numpy(poses[f : f + 1])
                expression = None if actions is None else torch.from_numpy(actions[f : f + 1])
                with torch.no_grad():
                    posed = lbs(model, betas, pose, expression, transl=torch.from_numpy(transl[f : f + 1]))
                verts = [posed.vertices[0].numpy()]
                for k, layer in enumerate(layers, start=1):
                    moved = layer.vertices + nonrigid_offsets(layer, canon_n[k], times[f], rates[f], spec.sway)
                    lv, _ = skin(torch.from_numpy(moved)[None], weights[k - 1], posed.joint_transforms)
                    verts.append(lv[0].numpy())
                    mesh_dsets[layer.name][f] = verts[-1].astype(np.float32)
                mesh_dsets["body"][f] = verts[0].astype(np.float32)
                scene = SceneMesh(vertices=np.concatenate(verts), **static)
                frame = render(scene, camera, albedo, textures.shading, spec.background, spec.supersample)
                writer.write(cv2.cvtColor(np.round(frame.image * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
                kp3d = kp_map(posed.joints, posed.vertices)[0]
                _write_frame(dsets, f, frame, kp3d, camera, on_joint)
                if face is not None:
                    dsets["face_points"][f] = seen_points(face(posed.vertices)[0], camera, frame.depth)
            writer.release()
    save_npz(
        gt / "params.npz",
        betas=betas[0].numpy(),
        poses=poses,
        transl=transl,
        joint_names=np.array(model.joint_names),
        phenotype_labels=np.array(sorted(spec.phenotype)) if spec.phenotype else np.array([""]),
        phenotype_values=np.array([spec.phenotype[k] for k in sorted(spec.phenotype)])
        if spec.phenotype
        else np.zeros(1),
        fps=spec.fps,
        **_camera_arrays(camera, F),
        **({} if actions is None else {"expression": actions, "expression_names": np.array(model.expression_names)}),
        **(
            {}
            if spec.driven is None
            else {"drive_anchor": spec.driven.anchor, "drive_reference": spec.driven.reference}
        ),
    )
    save_json(gt / "splits.json", splits(spec))
    save_json(gt / "labels.json", {str(k): v for k, v in label_names().items()})
    _export_ply(gt / "canonical_body.ply", rest_v, body_faces)
    for layer in layers:
        _export_ply(gt / f"canonical_{layer.name}.ply", layer.vertices, layer.faces)


#: a face point is seen where it lies within this much (m) of the depth map's first surface
FACE_POINT_TOLERANCE = 0.004


def seen_points(points: torch.Tensor, camera, depth: np.ndarray) -> np.ndarray:
    """(K, 3) (u, v, confidence) of (K, 3) surface points: confidence 1 where the first surface along the
    pixel's ray is the point's own (within ``FACE_POINT_TOLERANCE``), 0 where hidden or outside the image."""
    uv, z = camera.project(points)
    uv_np, z_np = uv.numpy(), z.numpy()
    H, W = depth.shape
    i, j = np.floor(uv_np[:, 1]).astype(int), np.floor(uv_np[:, 0]).astype(int)
    inside = (i >= 0) & (i < H) & (j >= 0) & (j < W)
    conf = np.zeros(len(uv_np), np.float32)
    conf[inside] = z_np[inside] <= depth[i[inside], j[inside]] + FACE_POINT_TOLERANCE
    return np.concatenate([uv_np, conf[:, None]], 1).astype(np.float32)


def _frame_datasets(fh: h5py.File, F: int, H: int, W: int, K: int, face: FacePoints | None = None) -> dict:
    kw = dict(chunks=(1, H, W), compression="gzip", compression_opts=4, track_times=False)
    d = {name: fh.create_dataset(name, (F, H, W), dtype=np.uint8, **kw)
         for name in ("person", "clothing", "skin", "hair", "labels", "alpha")}  # fmt: skip
    d["depth"] = fh.create_dataset("depth", (F, H, W), dtype=np.float32, **kw)
    d["keypoints"] = fh.create_dataset("keypoints", (F, K, 3), dtype=np.float32, track_times=False)
    d["keypoints3d"] = fh.create_dataset("keypoints3d", (F, K, 3), dtype=np.float32, track_times=False)
    if face is not None:  # the dense face points and their embedding on the body mesh
        d["face_points"] = fh.create_dataset("face_points", (F, face.num_points, 3), np.float32, track_times=False)
        fh.create_dataset("face_point_vertices", data=face.vertex_ids.numpy(), track_times=False)
        fh.create_dataset("face_point_bary", data=face.bary.numpy(), track_times=False)
    return d


def _write_frame(d: dict, f: int, frame, kp3d: torch.Tensor, camera, on_joint: np.ndarray) -> None:
    """Masks, labels, depth and keypoints of one frame.

    A keypoint's confidence is 1 where it is seen and 0.3 where the surface hides
    it: surface keypoints (face) must lie within 3 cm of the depth map, joints
    (inside the body) within 15 cm.
    """
    lab = frame.label
    d["labels"][f] = lab
    d["person"][f] = (lab > 0).astype(np.uint8)
    d["skin"][f] = ((lab >= BODY_LABEL_OFFSET) & (lab < BODY_LABEL_OFFSET + len(REGION_NAMES))).astype(np.uint8)
    d["clothing"][f] = np.isin(lab, [LAYER_LABELS[n] for n in ("upper", "lower", "dress")]).astype(np.uint8)
    d["hair"][f] = (lab == LAYER_LABELS["hair"]).astype(np.uint8)
    d["alpha"][f] = np.round(frame.alpha * 255).astype(np.uint8)
    d["depth"][f] = frame.depth
    uv, z = camera.project(kp3d)
    uv_np, z_np = uv.numpy(), z.numpy()
    H, W = lab.shape
    conf = np.zeros(len(uv_np), np.float32)
    for k, ((u, v), zk) in enumerate(zip(uv_np, z_np)):
        i, j = int(np.floor(v)), int(np.floor(u))
        if 0 <= i < H and 0 <= j < W:
            tolerance = 0.15 if on_joint[k] else 0.03
            seen = zk <= frame.depth[i, j] + tolerance
            conf[k] = 1.0 if seen else 0.3
    d["keypoints"][f] = np.concatenate([uv_np, conf[:, None]], 1)
    d["keypoints3d"][f] = kp3d.numpy()


def _mesh_datasets(mh: h5py.File, model: BodyModel, rest_v: np.ndarray, layers: list[Layer], F: int) -> dict:
    kw = dict(track_times=False)
    mh.create_dataset("body_faces", data=model.faces.numpy().astype(np.int32), **kw)
    mh.create_dataset("body_canonical", data=rest_v.astype(np.float32), **kw)
    d = {"body": mh.create_dataset("body_vertices", (F, len(rest_v), 3), dtype=np.float32,
                                   chunks=(1, len(rest_v), 3), **kw)}  # fmt: skip
    for layer in layers:
        mh.create_dataset(f"{layer.name}_faces", data=layer.faces.astype(np.int32), **kw)
        mh.create_dataset(f"{layer.name}_canonical", data=layer.vertices.astype(np.float32), **kw)
        d[layer.name] = mh.create_dataset(f"{layer.name}_vertices", (F, len(layer.vertices), 3), dtype=np.float32,
                                          chunks=(1, len(layer.vertices), 3), **kw)  # fmt: skip
    mh.attrs["layers"] = json.dumps([l.name for l in layers])
    return d


def _camera_arrays(camera, F: int) -> dict:
    if isinstance(camera, OrthographicCamera):
        return dict(camera_model=np.array("orthographic"), width=camera.width, height=camera.height,
                    ortho_scale=np.full(F, float(camera.scale)), ortho_trans=np.tile(camera.trans.numpy(), (F, 1)))  # fmt: skip
    return dict(camera_model=np.array("pinhole"), width=camera.width, height=camera.height, K=camera.K.numpy(),
                R=camera.R.numpy(), t=camera.t.numpy(), dist=camera.dist.numpy())  # fmt: skip


def _export_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        trimesh.Trimesh(vertices, faces, process=False).export(tmp)


def write_peoplesnapshot(capture_dir: str | os.PathLike, subject: str, out_dir: str | os.PathLike) -> None:
    """The capture again in People Snapshot's layout (pinhole cameras only)."""
    from delta.data.peoplesnapshot import write_layout

    gt = Path(capture_dir) / "gt"
    with np.load(gt / "params.npz", allow_pickle=False) as p:
        if str(p["camera_model"]) != "pinhole":
            raise DeltaError(f"{gt / 'params.npz'}: People Snapshot's layout needs a pinhole camera")
        t = lambda k: torch.from_numpy(p[k])  # noqa: E731
        camera = PinholeCamera(t("K"), t("R"), t("t"), t("dist"), int(p["width"]), int(p["height"]))
    with h5py.File(gt / "frames.h5", "r") as f:
        keypoints = np.asarray(f["keypoints"])
        masks = (np.asarray(f["person"][i]) for i in range(f["person"].shape[0]))  # 0/1, as People Snapshot
        write_layout(out_dir, subject, Path(capture_dir) / f"{subject}.mp4", camera, masks, keypoints)
