"""Entry point of ``delta export``: meshes, GLB, videos, side-by-side images and ``export.json`` of a trained avatar."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from delta import DeltaError
from delta.export import lineup
from delta.body.lbs import posed_joints
from delta.body.upright import Upright
from delta.export.animated import INFLUENCES, world_transform, write_animated_glb
from delta.export.meshes import (
    LAYER_MESH,
    MeshPart,
    body_mesh,
    edge_lengths,
    clothing_nerf_space,
    pose_clothing,
    rest_body,
    borrowed_weights,
    read_mesh,
    write_glb,
    write_mesh,
)
from delta.export.settings import PARTS, ExportSettings, part_settings
from delta.export.video import capture_upright, render_frames, side_by_side, turntable, write_video
from delta.geometry.raymesh import ray_mesh_hits
from delta.io import atomic_path, load_json, require_files, save_json
from delta.metrics import psnr
from delta.models.avatar import HybridAvatar
from delta.cameras.models import camera_vertical, metres_per_pixel
from delta.data.frames import load_full_frames
from delta.models.image import View, full_view, pixel_grid, render_image
from delta.progress import Progress
from delta.models.layer_support import confined_layers
from delta.training.run import Trained, load_trained

log = logging.getLogger(__name__)
#: Rendered masks are thresholded here (soft silhouette, NeRF opacity).
MASK_LEVEL = 0.5


def report_frames(split: np.ndarray, count: int) -> list[int]:
    """Up to ``count`` evenly spaced test frames (split 1 or 2), or training frames when there are none."""
    pool = np.flatnonzero(split != 0)
    pool = pool if len(pool) else np.arange(len(split))
    if count <= 0:
        return []
    return sorted({int(pool[i]) for i in np.linspace(0, len(pool) - 1, min(count, len(pool))).round().astype(int)})


def novel_pose_frames(split: np.ndarray, at_most: int = 0) -> list[int]:
    """The test-pose frames (split 2), or every frame when the capture has none; ``at_most`` > 0 keeps
    that many, evenly spaced."""
    pose = np.flatnonzero(split == 2)
    frames = pose if len(pose) else np.arange(len(split))
    if at_most and len(frames) > at_most:
        frames = frames[np.linspace(0, len(frames) - 1, at_most).round().astype(int)]
    return [int(i) for i in frames]


def silhouette(model: HybridAvatar, frame: int, parts: list[MeshPart]) -> np.ndarray:
    """Coverage (n, n) of meshes posed as ``frame`` through its camera."""
    n = model.resolution
    cam = model.camera(frame)
    mask = np.zeros((n, n), dtype=bool)
    for part in parts:
        if part.empty:
            continue
        with torch.no_grad():
            uv, depth = cam.project(torch.from_numpy(part.vertices).to(model.canonical_vertices))
        depth = depth if model.pinhole else torch.ones_like(depth)  # orthographic: nothing is behind the camera
        mask |= lineup.rasterize(uv.cpu().double().numpy(), depth.cpu().double().numpy(), part.faces, n, n)
    return mask


@torch.no_grad()
def rendered_hits(model: HybridAvatar, frame: int) -> np.ndarray:
    """(n, n) bool: the pixels whose rays hit the posed body mesh (the renderer's own ray casting)."""
    n = model.resolution
    pixels = pixel_grid(n).to(model.canonical_vertices)
    mesh = model.posed_mesh(frame)[0]
    origins, dirs = model.camera(frame).rays(pixels)
    return ray_mesh_hits(mesh.vertices, mesh.faces, origins, dirs).hit.reshape(n, n).cpu().numpy()


@torch.no_grad()
def write_capture_animation(model: HybridAvatar, frame_ids: np.ndarray, path: Path, fps: float,
                            clothing: MeshPart | None, upright: Upright) -> dict:  # fmt: skip
    """``avatar_animated.glb``: the avatar animated by every frame of the capture in order, at ``fps``
    frames a second (:func:`write_avatar_animation`)."""
    ids = np.asarray(frame_ids)
    order = np.unique(ids, return_index=True)[1]  # by frame, each once (a frame in two splits)
    rot, transl = (t.detach().cpu().double() for t in model.local_rotations())
    times = (ids[order] - ids[order][0]) / float(fps)
    return write_avatar_animation(model, rot[order], transl[order], times, path, clothing, upright)


@torch.no_grad()
def write_avatar_animation(model: HybridAvatar, rotations: torch.Tensor, transl: torch.Tensor, times: np.ndarray,
                           path: Path, clothing: MeshPart | None, upright: Upright) -> dict:  # fmt: skip
    """A skinned, animated GLB of the avatar: the body (and the clothing surface in the NeRF's space,
    skinned by its nearest body vertices' weights) bound in the rest pose, moved by (F, J, 3, 3) local
    rotations and (F, 3) translations in the capture's world at ``times`` (F,) seconds, standing on the
    capture's ``upright`` floor (:mod:`delta.export.animated`)."""
    body, rest_out = rest_body(model)
    weights = model.body.weights.detach().cpu().double().numpy()
    meshes = {"body": {"vertices": body.vertices, "faces": body.faces, "colors": body.colors, "weights": weights}}
    if clothing is not None and not clothing.empty:
        worn = pose_clothing(model, clothing, rest_out)
        meshes["clothing"] = {"vertices": worn.vertices, "faces": worn.faces, "colors": worn.colors,
                              "weights": borrowed_weights(body.vertices, weights, worn.vertices)}  # fmt: skip
    rotations, transl = rotations.detach().cpu().double(), transl.detach().cpu().double()
    cpu_body = model.body.to(dtype=torch.float64, device="cpu")
    start = posed_joints(cpu_body, model.betas.detach().cpu().double(), rotations[:1], transl[:1])[0, 0]
    rest_joints = rest_out.rest_joints[0].detach().cpu().double().numpy()
    sole = float(rest_joints[:, 1].min() - body.vertices[:, 1].min())  # canonical y is up
    world = world_transform(upright, start.numpy(), sole)
    if model.body.posedirs is not None:
        log.info("%s: the body model's pose correctives are not in the file (glTF has none)", path.name)
    write_animated_glb(path, meshes, rest_joints, model.body.parents.cpu().numpy(), model.body.joint_names,
                       rotations.numpy(), transl.numpy(), np.asarray(times, np.float64), world)  # fmt: skip
    return {"frames": int(len(times)), "meshes": sorted(meshes), "influences": INFLUENCES}


def check_frame(model: HybridAvatar, frame: int, clothing: MeshPart | None, img: dict) -> dict:
    """IoU of the projected exported posed meshes with the rendered masks of one frame.

    ``iou_body``: body mesh vs the rendered body (ray hits); ``iou_body_soft``: vs the soft training
    silhouette at 0.5; ``iou_avatar``: body + clothing meshes vs rendered body ∪ NeRF opacity > 0.5.
    """
    body, out = body_mesh(model, frame)
    body_sil = silhouette(model, frame, [body])
    hits = rendered_hits(model, frame)
    row = {"frame": frame, "iou_body": round(lineup.iou(body_sil, hits), 4),
           "iou_body_soft": round(lineup.iou(body_sil, img["silhouette"].numpy() > MASK_LEVEL), 4)}  # fmt: skip
    if clothing is not None:
        posed = pose_clothing(model, clothing, out)
        avatar_sil = body_sil | silhouette(model, frame, [posed])
        row["iou_avatar"] = round(lineup.iou(avatar_sil, hits | (img["nerf_mask"].numpy() > MASK_LEVEL)), 4)
    return row


@torch.no_grad()
def capture_pixel(model: HybridAvatar, frame: int, body: MeshPart, view: View | None) -> float:
    """The width (m) of one pixel of the capture's whole frame (of the model's crop without ``view``)
    at the posed body of ``frame``: the median over its vertices."""
    per_model_pixel = metres_per_pixel(model.camera(frame), torch.from_numpy(body.vertices))
    return float(per_model_pixel.median()) * (float(view.scale[0]) if view is not None else 1.0)


def edge_summary(part: MeshPart) -> dict:
    """Median and 95th-percentile edge length (mm) of a mesh."""
    edges = edge_lengths(part) * 1000
    return {"median_mm": round(float(np.median(edges)), 2), "p95_mm": round(float(np.percentile(edges, 95)), 2)}


def _load(model_path, record, body_path, device):
    require_files(model=model_path, record=record, body_model=body_path)
    return load_trained(model_path, record, body_path, device)  # names a record of other frames


#: The summary of the meshes part, read by the videos part and merged into ``export.json``.
MESHES_JSON = "meshes.json"


def export_avatar(model_path: str | Path, record: str | Path, body_path: str | Path, out_dir: str | Path,
                  settings: ExportSettings, device: str = "cpu", part: str = "all") -> dict:  # fmt: skip
    """Write the exports of a trained avatar into ``out_dir`` (``part``: meshes, videos or all); returns
    the part's summary (``meshes.json``; ``export.json`` for the videos and all)."""
    t_start = time.perf_counter()
    tr = _load(model_path, record, body_path, device)
    summary = export_trained(tr, out_dir, settings, {"model": str(model_path), "record": str(record)}, record, part)
    log.info("export %s (%.1f s, loading included) written to %s", part, time.perf_counter() - t_start, out_dir)
    return summary


def export_trained(tr: Trained, out_dir: str | Path, settings: ExportSettings, about: dict | None = None,
                   record: str | Path | None = None, part: str = "all") -> dict:  # fmt: skip
    """The exports of a loaded avatar (``about`` is copied into the summary): ``meshes`` writes the meshes,
    the GLBs and ``meshes.json``; ``videos`` the side-by-sides, line-up check and videos, reading the
    meshes part's output in ``out_dir``, and ``export.json`` (both summaries); ``all`` both.

    With the frame ``record``, the videos and side-by-sides show the capture's whole frame at its
    scoring size, whatever the avatar was trained at; without, the avatar's own crop.
    """
    if part not in PARTS:
        raise DeltaError(f"export: part '{part}' is not one of {', '.join(PARTS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if part in ("meshes", "all"):
        meshes = export_meshes(tr, out, settings, about, record)
        if part == "meshes":
            return meshes
    else:
        meshes = read_meshes_summary(out)
    return export_videos(tr, out, settings, meshes, record)


def read_meshes_summary(out: Path) -> dict:
    """The meshes part's summary in ``out``, or an error saying to export the meshes first."""
    path = out / MESHES_JSON
    if not path.is_file():
        raise DeltaError(f"{path}: missing; the videos part reads the meshes part's output "
                         f"(run `delta export --part meshes --out {out}` first)")  # fmt: skip
    return load_json(path)


def export_meshes(tr: Trained, out: Path, settings: ExportSettings, about: dict | None = None,
                  record: str | Path | None = None) -> dict:  # fmt: skip
    """Body and clothing/hair meshes (PLY), ``avatar.glb``, ``avatar_animated.glb`` and ``meshes.json``;
    the clothing's colours are read a pixel of the ``record``'s whole frame apart (of the model's crop
    without it)."""
    t_start = time.perf_counter()
    model, data = tr.model, tr.data
    posed_frame = report_frames(data.split, 1)[0]
    full = load_full_frames(record, [posed_frame], tr.settings.background) if record is not None else None
    view = full_view(full, model.resolution) if full is not None else None
    times: dict[str, float] = {}

    t = time.perf_counter()
    body_c, cano_out = body_mesh(model)
    body_p, posed_out = body_mesh(model, posed_frame)
    write_mesh(out / "body_canonical.ply", body_c)
    write_mesh(out / "body_posed.ply", body_p)
    parts = {"body": body_c}
    summary: dict = {**(about or {}), "stage": tr.stage, "preset": tr.preset,
                     "settings": part_settings(settings, "meshes"), "posed_frame": posed_frame,
                     "body": {"vertices": len(body_c.vertices), "faces": len(body_c.faces),
                              "watertight": bool(body_c.to_trimesh().is_watertight)}}  # fmt: skip
    times["body"] = time.perf_counter() - t

    pixel = capture_pixel(model, posed_frame, body_p, view)
    summary["colour_sampling"] = {"capture_pixel_mm": round(pixel * 1000, 2), "body_edges": edge_summary(body_c)}
    clothing = None
    if model.nerf is not None:
        t = time.perf_counter()
        # the NeRF's colour holds no detail finer than half its finest cell: no edge is split below that
        cell = model.nerf.color_cell()
        longest = max(settings.color_spacing * pixel, cell / 2) if settings.color_spacing > 0 else 0.0
        clothing = clothing_nerf_space(model, settings, longest)
        summary["colour_sampling"] |= {"nerf_colour_cell_mm": round(cell * 1000, 2),
                                       "clothing_longest_edge_mm": round(longest * 1000, 2)}  # fmt: skip
        if not clothing.empty:
            summary["colour_sampling"]["clothing_edges"] = edge_summary(clothing)
        parts["clothing"] = pose_clothing(model, clothing, cano_out)
        if not clothing.empty:  # (an empty mesh makes no PLY)
            write_mesh(out / "clothing_nerf_space.ply", clothing)  # the NeRF's own space (evaluation poses it)
            write_mesh(out / "clothing_canonical.ply", parts["clothing"])
            write_mesh(out / "clothing_posed.ply", pose_clothing(model, clothing, posed_out))
        tm = parts["clothing"].to_trimesh()
        summary["clothing"] = {"vertices": len(clothing.vertices), "faces": len(clothing.faces),
                               "components": len(tm.split(only_watertight=False)) if len(tm.faces) else 0}  # fmt: skip
        if clothing.empty:
            log.warning("the NeRF's density never reaches %.3g: the clothing mesh is empty", settings.threshold)
        layers = getattr(model.nerf, "names", ())
        if layers:  # each layer on its own as well (where its frames see it); the GLB holds them apart
            del parts["clothing"]
            as_trained = dict(model.nerf.layers)
            model.nerf.layers.update(confined_layers(model, data, layers))
        try:
            for name in layers:
                own = clothing_nerf_space(model, settings, longest, name)
                summary.setdefault("layers", {})[name] = {"vertices": len(own.vertices), "faces": len(own.faces)}
                if own.empty:
                    continue
                write_mesh(out / LAYER_MESH.format(layer=name, space="nerf_space"), own)
                parts[name] = pose_clothing(model, own, cano_out)
                write_mesh(out / LAYER_MESH.format(layer=name, space="canonical"), parts[name])
        finally:  # the videos render the avatar as trained
            if layers:
                model.nerf.layers.update(as_trained)
        times["clothing"] = time.perf_counter() - t
    write_glb(out / "avatar.glb", parts)
    t = time.perf_counter()
    upright = capture_upright(model)  # the animated GLB stands on it, the turntable turns about it
    summary["upright"] = upright.describe(camera_vertical(model.camera(0)))
    log.info("up axis from %d fitted frames: %s", upright.frames, summary["upright"])
    summary["animated"] = {**write_capture_animation(model, data.frame_ids, out / "avatar_animated.glb", settings.fps,
                                                     clothing, upright), "fps": settings.fps}  # fmt: skip
    times["animated"] = time.perf_counter() - t
    times["meshes"] = time.perf_counter() - t_start
    summary["seconds"] = {k: round(v, 2) for k, v in times.items()}
    save_json(out / MESHES_JSON, summary)
    log.info("meshes written in %.1f s", times["meshes"])
    return summary


def exported_clothing(model: HybridAvatar, out: Path, meshes: dict) -> MeshPart | None:
    """The clothing surface in the NeRF's space the meshes part wrote (empty where the NeRF's density
    never reached the threshold; None without a NeRF)."""
    if model.nerf is None:
        return None
    path = out / "clothing_nerf_space.ply"
    if not meshes.get("clothing", {}).get("faces"):
        return MeshPart(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3)))
    if not path.is_file():
        raise DeltaError(f"{path}: missing, but {out / MESHES_JSON} says the clothing mesh has "
                         f"{meshes['clothing']['faces']} faces; export the meshes again")  # fmt: skip
    return read_mesh(path)


def export_videos(tr: Trained, out: Path, settings: ExportSettings, meshes: dict,
                  record: str | Path | None = None) -> dict:  # fmt: skip
    """Side-by-sides, the line-up check of the exported meshes against the renders, ``turntable.mp4`` and
    ``novel_pose.mp4``; writes ``export.json``: the meshes part's summary with these added."""
    t_start = time.perf_counter()
    model, data = tr.model, tr.data
    frames = report_frames(data.split, max(settings.sidebyside, 1))
    full = load_full_frames(record, frames, tr.settings.background) if record is not None else None
    view = full_view(full, model.resolution) if full is not None else None
    clothing = exported_clothing(model, out, meshes)
    upright = capture_upright(model)
    summary = {**meshes, "settings": {**meshes.get("settings", {}), **part_settings(settings, "videos")}}
    times: dict[str, float] = dict(meshes.get("seconds", {}))

    t = time.perf_counter()
    rows = []
    (out / "sidebyside").mkdir(exist_ok=True)
    novel = novel_pose_frames(data.split, settings.novel_frames)
    size = f"{view.width}x{view.height}" if view else f"{model.resolution}x{model.resolution}"
    progress = Progress(f"export renders ({size})", len(frames) + settings.turntable_frames + len(novel))
    for k, f in enumerate(frames):
        img = render_image(model, f)  # the line-up check compares with the model's own crop
        if k < settings.sidebyside:  # (the line-up check uses at least one frame)
            shown = render_image(model, f, view=view, soft_silhouette=False) if full else img
            reference = full.images[k] if full else data.images[f]
            with atomic_path(out / "sidebyside" / f"frame_{int(data.frame_ids[f]):05d}.png") as tmp:
                cv2.imwrite(str(tmp), side_by_side(reference, shown["rgb"]))
        rows.append({**check_frame(model, f, clothing, img), "psnr": round(psnr(img["rgb"].clamp(0, 1), data.images[f]), 2),
                     "split": int(data.split[f])})  # fmt: skip
        progress.tick("line-up and side-by-side")
    summary["frames"] = rows
    keys = [k for k in ("iou_body", "iou_body_soft", "iou_avatar") if k in rows[0]]
    summary["lineup"] = {k: round(float(np.mean([r[k] for r in rows])), 4) for k in keys}
    times["sidebyside_and_lineup"] = time.perf_counter() - t

    t = time.perf_counter()
    turn_frame = int(data.train[0])
    turn = turntable(model, turn_frame, settings.turntable_frames, view, upright)
    summary["turntable"] = {
        "frame": turn_frame,
        "frames": write_video(out / "turntable.mp4", progress.counted(turn, "turntable"), settings.fps),
    }
    times["turntable"] = time.perf_counter() - t
    t = time.perf_counter()
    summary["novel_pose"] = {"frames": write_video(out / "novel_pose.mp4", progress.counted(render_frames(model, novel, view), "novel pose"), settings.fps),
                             "test_pose_frames": bool((data.split == 2).any())}  # fmt: skip
    times["novel_pose"] = time.perf_counter() - t
    times["videos"] = time.perf_counter() - t_start
    times["total"] = times["videos"] + times.get("meshes", 0.0)
    summary["seconds"] = {k: round(v, 2) for k, v in times.items()}
    summary["resolution"] = "{}x{}".format(*full.size) if full else f"{model.resolution}x{model.resolution}"
    summary["model_resolution"] = model.resolution
    save_json(out / "export.json", summary)
    log.info("line-up IoU %s, times %s", summary["lineup"], summary["seconds"])
    return summary
