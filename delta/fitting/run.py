"""The init-fitting step: frame record + body model -> results/{dataset}/{subject}/init/."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from delta.body.keypoints import KeypointMap, openpose18_map
from delta.body.lbs import batch_rodrigues, lbs, posed_joints
from delta.body.model import load_body_model
from delta.body.rotations import matrix_to_axis_angle, mean_rotation
from delta.body.upright import Upright, estimate_upright
from delta.cameras.models import OrthographicCamera, PinholeCamera, camera_vertical, check_camera
from delta.data.person import confident_keypoints, no_person_message
from delta.data.record import FrameRecord
from delta import DeltaError
from delta.body.face_points import FacePoints
from delta.fitting.balance import fit_balanced, legs_seen
from delta.fitting.face import FaceFit, FaceFitConfig, fit_face
from delta.fitting.fit import FitStart
from delta.fitting.hold import HEAD_CHAIN, hold_decision
from delta.fitting.settings import FitConfig
from delta.fitting.start import face_start
from delta.io import atomic_path, save_npz

log = logging.getLogger(__name__)
_KNEES = ("lowerleg01.L", "lowerleg01.R", "left_knee", "right_knee")
BODY_PARAMS = "body_params"
"""Optional record group: a dataset's per-frame body parameters (betas (S,), poses (N, J, 3), transl (N, 3))
with attr ``model``, the body model they belong to ("anny", "smplx", "smpl", ...)."""


def held_parts(model, hold: dict, frames: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What the fit's hold keeps near its mean (:func:`delta.fitting.hold.hold_decision`): the (J,) joints and
    the (F,) frames (None: the capture's own sequence). A held torso is the root and every joint but the
    neck's chain, in every frame; the limbs are every joint but the root."""
    if hold["holds"] == "torso":
        head = torch.stack([model.subtree(name) for name in HEAD_CHAIN]).any(0)
        return ~head, torch.ones(frames, dtype=torch.bool)
    return torch.arange(model.num_joints) > 0, None


def still_start(start: FitStart) -> FitStart:
    """A held torso's start from a close-up's face start, which gives each frame's turn of the head to the
    whole body: the root takes the frames' mean turn (the rotations' chordal mean) and place, the neck and
    head stay at rest, and the fit turns them to the face points. (Starting them turned instead, each frame's
    turn relative to the mean shared along the neck, left the talker's fit 58 px from its keypoints on
    average against 7 px from rest.)"""
    pose = start.pose.clone()
    pose[:, 0] = matrix_to_axis_angle(mean_rotation(batch_rodrigues(start.pose[:, 0])))
    transl = start.transl.mean(0, keepdim=True).expand_as(start.transl).clone()
    return dataclasses.replace(start, pose=pose, transl=transl)


def dataset_start(rec: FrameRecord, model) -> FitStart | None:
    """The record's body parameters when they are for ``model`` (same base name and joint count), else None."""
    if BODY_PARAMS not in rec.h5:
        return None
    group = rec.h5[BODY_PARAMS]
    owner = str(group.attrs.get("model", ""))
    if owner != model.name.split("_sub")[0]:
        log.info("%s: body parameters are for '%s', not '%s': fitting from scratch", rec.path, owner, model.name)
        return None
    for key in ("betas", "poses", "transl"):
        if key not in group:
            raise DeltaError(f"{rec.path}: '{BODY_PARAMS}/{key}' missing (the group has {sorted(group)})")
    betas, poses, transl = (torch.from_numpy(group[k][:]).double() for k in ("betas", "poses", "transl"))
    n = len(rec)
    if poses.shape != (n, model.num_joints, 3) or transl.shape != (n, 3):
        raise DeltaError(f"{rec.path}: '{BODY_PARAMS}' poses {tuple(poses.shape)} / transl {tuple(transl.shape)}, "
                         f"expected ({n}, {model.num_joints}, 3) / ({n}, 3) for '{model.name}'")  # fmt: skip
    if betas.shape[0] < model.num_shape:  # fewer coefficients than the model: the rest are 0
        betas = torch.cat([betas, betas.new_zeros(model.num_shape - betas.shape[0])])
    return FitStart(betas[: model.num_shape], poses, transl)


EXTERIOR = ("clothing", "hair")
"""Record masks whose pixels the fit's silhouette term weighs with ``exterior_fill``."""


def exterior_masks(rec: FrameRecord) -> np.ndarray | None:
    """(N, H, W) uint8 union of the record's clothing and hair masks, or None when it has neither."""
    present = [rec.h5[k][:] for k in EXTERIOR if k in rec.h5]
    if not present:
        return None
    return np.maximum.reduce(present)


def check_record(rec: FrameRecord, detected: np.ndarray, masks: np.ndarray, frame_ids: np.ndarray,
                 cfg: FitConfig) -> None:  # fmt: skip
    """Raise a DeltaError before fitting a record that cannot give a body: a camera that cannot image
    (``check_camera``), or no frame the fit would use (every one with fewer than ``cfg.min_keypoints``
    confident keypoints or an empty person mask)."""
    if rec.h5.attrs["camera_model"] == "pinhole":
        check_camera(rec.camera(0), str(rec.path))
    elif "ortho_scale" in rec.h5:
        check_camera(rec.camera(), str(rec.path), frame_ids)
    counts = confident_keypoints(detected, cfg.conf_threshold)
    shown = masks.reshape(len(masks), -1).max(-1) > 0 if len(masks) else np.zeros(0, dtype=bool)
    if not ((counts >= cfg.min_keypoints) & shown).any():
        raise DeltaError(no_person_message(rec.path, len(frame_ids), counts, shown, "non-empty",
                                           min_keypoints=cfg.min_keypoints, threshold=cfg.conf_threshold))  # fmt: skip


def check_result(where, res, frame_ids: np.ndarray) -> None:
    """Raise a DeltaError naming the frames when the fit's parameters or a used frame's residual are not finite."""
    F = len(frame_ids)
    bad = {"shape": ~torch.isfinite(res.betas).all().expand(F),
           "pose": ~torch.isfinite(res.pose.reshape(F, -1)).all(-1),
           "translation": ~torch.isfinite(res.transl).all(-1),
           "reprojection residual": ~res.flagged & ~torch.isfinite(res.residual_px)}  # fmt: skip
    if isinstance(res.camera, OrthographicCamera):
        bad["camera"] = ~(torch.isfinite(res.camera.scale) & (res.camera.scale > 0)).reshape(-1).expand(F)
        bad["camera"] = bad["camera"] | ~torch.isfinite(res.camera.trans).reshape(-1, 2).all(-1).expand(F)
    names = [name for name, b in bad.items() if b.any()]
    if names:
        rows = torch.stack([bad[n] for n in names]).any(0).numpy()
        ids = frame_ids[rows].tolist()
        raise DeltaError(f"{where}: the fit gave a non-finite {', '.join(names)} at {len(ids)} of {F} frames "
                         f"{ids[:10]}{' ...' if len(ids) > 10 else ''}")  # fmt: skip


def face_points(rec: FrameRecord, model, body_path) -> FacePoints | None:
    """The record's face points on ``model`` (None when it has none), checked before any fitting."""
    points = rec.face_embedding()
    if points is None:
        return None
    if model.exprdirs is None:
        raise DeltaError(f"{rec.path} holds face points but the body model {body_path} has no expression "
                         "space: fit it with the face body model (the workflow picks it for a talking face)")  # fmt: skip
    if int(points.vertex_ids.max()) >= model.num_vertices:
        raise DeltaError(f"{rec.path}: its face points lie on a mesh of more than {model.num_vertices} vertices, "
                         f"not on {body_path}")  # fmt: skip
    return points


def with_face_points(kp_map: KeypointMap, detected: torch.Tensor, points: FacePoints | None,
                     face_seen: torch.Tensor | None) -> tuple[KeypointMap, torch.Tensor]:  # fmt: skip
    """The body fit's keypoints joined by the record's face points (``points`` on the mesh, ``face_seen``
    (F, K, 3) their detections; None: as they are). A close-up's body keypoints are the few a face shows;
    its hundreds of face points place, size and turn the head, which the silhouette alone leaves loose
    (the expressions come after, in the face fit)."""
    if points is None:
        return kp_map, detected
    K, V = points.num_points, kp_map.vertex_weights.shape[1]
    vw = torch.zeros(K, V, dtype=kp_map.vertex_weights.dtype)
    vw.scatter_add_(1, points.vertex_ids, points.bary.to(vw.dtype))
    joined = KeypointMap(tuple(kp_map.names) + tuple(f"face_{k}" for k in range(K)),
                         torch.cat([kp_map.joint_weights, kp_map.joint_weights.new_zeros(K, kp_map.joint_weights.shape[1])]),
                         torch.cat([kp_map.vertex_weights, vw]))  # fmt: skip
    return joined, torch.cat([detected, face_seen.to(detected.dtype)], 1)


def track_face(model, res, points: FacePoints | None, face_seen: torch.Tensor | None,
               still: bool = False) -> FaceFit | None:  # fmt: skip
    """Per-frame expressions and head rotations from the record's face points (None when it has none); a
    ``still`` torso's place is corrected once for every frame (the head turns on the neck)."""
    if points is None:
        return None
    cfg = FaceFitConfig(one_place=still)
    return fit_face(model, points, face_seen.double(), res.camera, res.betas, res.pose, res.transl, cfg)


def fitted_upright(model, res) -> Upright:
    """The capture's up and floor from the fitted bodies of its frames (:mod:`delta.body.upright`)."""
    good = ~res.flagged if (~res.flagged).any() else torch.ones_like(res.flagged)
    rot = batch_rodrigues(res.pose[good])
    return estimate_upright(
        rot[:, 0], posed_joints(model, res.betas, rot, res.transl[good]), camera_vertical(res.camera)
    )


def run(record_path: str | Path, body_path: str | Path, out_dir: str | Path, overlays: int = 4,
        cfg: FitConfig = FitConfig()) -> dict:  # fmt: skip
    """Fit and write ``params.npz``, ``report.csv`` (per-frame residuals and flags) and overlay PNGs."""
    out = Path(out_dir)
    with FrameRecord(record_path) as rec:
        detected = torch.from_numpy(rec.h5["keypoints"][:])
        frame_ids = rec.h5["frame_ids"][:]
        masks = rec.h5["person"][:]
        check_record(rec, detected.numpy(), masks, frame_ids, cfg)
        model = load_body_model(body_path, dtype=torch.float64)
        kp_map = openpose18_map(model)
        points = face_points(rec, model, body_path)
        face_seen = torch.from_numpy(rec.h5["face_points"][:]).double() if points is not None else None
        start, started_from = dataset_start(rec, model), "dataset"
        if rec.h5.attrs["camera_model"] == "pinhole":
            camera = rec.camera(0)
        elif start is not None:  # the dataset's cameras go with its parameters
            camera = rec.camera()
        else:
            camera = OrthographicCamera(torch.tensor(1.0, dtype=torch.float64), torch.zeros(2, dtype=torch.float64),
                                        rec.size, rec.size)  # fmt: skip
        if start is None and points is not None and isinstance(camera, PinholeCamera):  # a close-up: from its face
            start, started_from = face_start(model, points, face_seen, camera), "face"
        started_from = started_from if start is not None else "mean_pose"
        knees = [model.joint_names.index(n) for n in _KNEES if n in model.joint_names]
        exterior = exterior_masks(rec)
        # a novel-pose sequence (split 2) is not the training sequence's continuation
        sequence = torch.from_numpy((rec.h5["split"][:] == 2).astype(np.int64))
        hold = hold_decision(detected.numpy(), sequence.numpy() == 0, cfg.static_spread, cfg.static_weight,
                             cfg.conf_threshold, face=points is not None, still=cfg.still_torso)  # fmt: skip
        log.info("holding the pose near its mean: %s", hold["why"])
        fit_cfg = cfg if hold["hold"] else dataclasses.replace(cfg, static_weight=0.0)
        held_joints, held_frames = held_parts(model, hold, len(frame_ids))
        if hold["holds"] == "torso" and started_from == "face":
            start = still_start(start)
        fit_map, fit_detected = with_face_points(kp_map, detected, points, face_seen)
        depth = torch.from_numpy(rec.h5["keypoint_depth"][:]) if "keypoint_depth" in rec.h5 else None
        res, balance = fit_balanced(model, fit_map, fit_detected, camera, fit_cfg, side=rec.size,
                                    close_up=points is not None, legs=legs_seen(detected, cfg.conf_threshold),
                                    knees=knees, masks=masks, start=start,
                                    exterior=exterior, sequence=sequence, depth=depth, held_joints=held_joints,
                                    held_frames=held_frames, tied=hold["holds"] == "torso")  # fmt: skip
        check_result(rec.path, res, frame_ids)
        face, face_arrays = track_face(model, res, points, face_seen, still=hold["holds"] == "torso"), {}
        if face is not None:
            res.pose, res.betas, res.transl = face.poses, face.betas, face.transl
            face_arrays = dict(expression=face.expression.numpy(), expression_names=np.array(model.expression_names),
                               face_flags=np.array(face.flags), face_residual_px=face.residual_px.numpy())  # fmt: skip
        upright = fitted_upright(model, res)
        cam = {"camera_model": np.array(rec.h5.attrs["camera_model"])}
        if isinstance(res.camera, OrthographicCamera):
            cam.update(ortho_scale=res.camera.scale.numpy(), ortho_trans=res.camera.trans.numpy())
        save_npz(out / "params.npz", betas=res.betas.numpy(), poses=res.pose.numpy(), transl=res.transl.numpy(),
                 flagged=res.flagged.numpy(), few_keypoints=res.few_keypoints.numpy(),
                 empty_mask=res.empty_mask.numpy(), started_from=np.array(started_from),
                 frame_ids=frame_ids, joint_names=np.array(model.joint_names), up=upright.up.numpy(),
                 floor=np.array(upright.floor), **cam, **face_arrays)  # fmt: skip
        confident = confident_keypoints(detected.numpy(), cfg.conf_threshold)
        report = pd.DataFrame({"frame": frame_ids, "flagged": res.flagged.numpy(),
                               "few_keypoints": res.few_keypoints.numpy(), "empty_mask": res.empty_mask.numpy(),
                               "residual_px": res.residual_px.numpy(),
                               "confident_keypoints": confident})  # fmt: skip
        if face is not None:
            report["face_flag"], report["face_residual_px"] = face.flags, face.residual_px.numpy()
        with atomic_path(out / "report.csv") as tmp:
            report.to_csv(tmp, index=False)
        picks = np.linspace(0, len(frame_ids) - 1, min(overlays, len(frame_ids))).round().astype(int)
        for k in picks:
            _overlay(rec, k, model, res, out / f"overlay_{int(frame_ids[k]):05d}.png")
    flagged = frame_ids[res.flagged.numpy()].tolist()
    if flagged:
        log.warning("%s: %d of %d frames flagged (too few keypoints or an empty mask; their parameters are "
                    "interpolated): %s", record_path, len(flagged), len(frame_ids), flagged)  # fmt: skip
    summary = {"frames": int(len(frame_ids)), "flagged": int(res.flagged.sum()), "flagged_frames": flagged,
               "started_from": started_from,
               "residual_px_mean": float(np.nanmean(res.residual_px.numpy())),
               "upright": upright.describe(camera_vertical(res.camera)), "static_hold": hold,
               "silhouette_balance": balance,
               "neighbour_starts": {"reach": fit_cfg.neighbour_reach,
                                    "refitted": [int(frame_ids[f]) for f in res.neighbour_refits],
                                    "frames_from": [[int(frame_ids[f]), int(frame_ids[s])]
                                                    for f, s in res.neighbour_starts]}}  # fmt: skip
    log.info("init fit: %s", summary)
    return summary


def _overlay(rec: FrameRecord, k: int, model, res, path: Path) -> None:
    """The fitted mesh's vertices drawn over the frame (a quick visual check)."""
    image = cv2.cvtColor(rec.h5["images"][k], cv2.COLOR_RGB2BGR)
    out = lbs(model, res.betas[None], res.pose[k : k + 1], transl=res.transl[k : k + 1])
    cam = res.camera
    if isinstance(cam, OrthographicCamera):
        cam = OrthographicCamera(cam.scale[k], cam.trans[k], cam.width, cam.height)
    uv = cam.project(out.vertices[0, ::7])[0].numpy()
    shade = image.copy()
    for u, v in uv:
        if 0 <= u < image.shape[1] and 0 <= v < image.shape[0]:
            shade[int(v), int(u)] = (60, 220, 60)
    with atomic_path(path) as tmp:
        cv2.imwrite(str(tmp), cv2.addWeighted(image, 0.4, shade, 0.6, 0))
