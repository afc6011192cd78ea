"""Score a trained avatar on a subject's test frames: ``results/{dataset}/{subject}/eval/``.

One row per (frame, refined) in ``metrics.csv``: PSNR / SSIM / L1 of the whole frame at the
capture's scoring size (People Snapshot 540×540, a synthetic capture its own; whatever size the
avatar was trained at) and per region, ST-LPIPS (alex), LPIPS-Alex when the user gave its weights, IoU of the NeRF
mask with the record's exterior mask and of the mesh silhouette with the person mask, and,
when ground truth is given (synthetic captures), the body vertex error. The convention
travels in every row: background colour, full image, resolution, whether the test frame's
pose and camera were refined (with the model frozen) before scoring.
"""

from __future__ import annotations

import math

import json
import logging
from pathlib import Path

import cv2
import h5py
import numpy as np
import pandas as pd
import torch
import trimesh

from delta import DeltaError
from delta import metrics as M
from delta.body.model import REGION
from delta.data.frames import load_full_frames
from delta.eval.expressions import AvatarExpressions
from delta.eval.geometry import (
    mesh_distance,
    point_to_surface,
    similarity_transform,
    vertex_error,
    vertex_errors,
)
from delta.eval.heldout import refine_frame
from delta.eval.settings import EvalSettings
from delta.geometry.sight import visible_vertices
from delta.export.video import side_by_side
from delta.geometry.raymesh import ray_mesh_hits
from delta.io import atomic_path
from delta.models.image import View, full_view, live_rays, pixel_grid, reach_box, render_image
from delta.progress import Progress
from delta.training.run import Trained
from delta.eval.settings import pick_frames

log = logging.getLogger(__name__)
FACE_REGIONS = (REGION["face"], REGION["eyes"], REGION["mouth"])


@torch.no_grad()
def face_pixels(model, frame: int, mesh_vertices: torch.Tensor, view: View) -> torch.Tensor:
    """(H, W) bool: pixel centres of the view whose ray first hits a face / eyes / mouth triangle of the body."""
    pixels = view.to_model(pixel_grid(view.height, device=mesh_vertices.device, width=view.width))
    live = torch.nonzero(live_rays(pixels, reach_box(model, frame, mesh_vertices))).squeeze(1)
    face = torch.zeros(len(pixels), dtype=torch.bool, device=pixels.device)
    origins, dirs = model.camera(frame).rays(pixels[live])
    hits = ray_mesh_hits(mesh_vertices, model.body.faces, origins, dirs)
    labels = model.body.regions[model.body.faces[hits.face.clamp_min(0), 0]]
    face[live] = hits.hit & torch.isin(labels, torch.tensor(FACE_REGIONS, device=labels.device))
    return face.reshape(view.height, view.width).cpu()


class Perceptual:
    """The perceptual distances asked for, on (H, W, 3) images in [0, 1]."""

    def __init__(self, st: EvalSettings, device):
        from delta.perceptual.stlpips import STLPIPS, lpips_alex

        self.nets = {}
        if st.perceptual_dir:
            self.nets["stlpips_alex"] = STLPIPS("alex", cache_dir=st.perceptual_dir).to(device)
        if st.lpips_alex:
            self.nets["lpips_alex"] = lpips_alex(*st.lpips_alex).to(device)

    @torch.no_grad()
    def __call__(self, a: torch.Tensor, b: torch.Tensor) -> dict[str, float]:
        x, y = (t.permute(2, 0, 1)[None].float() for t in (a, b))
        return {k: float(net(x.to(next(net.buffers()).device), y.to(next(net.buffers()).device)))
                for k, net in self.nets.items()}  # fmt: skip


def score_image(img: dict, gt: torch.Tensor, masks: dict[str, torch.Tensor], perceptual: Perceptual,
                perceptual_regions: tuple[str, ...] = (), background=(1.0, 1.0, 1.0)) -> dict:  # fmt: skip
    """Whole-image and per-region scores of one render (dict from render_image). The regions named in
    ``perceptual_regions`` are also scored perceptually, both images with everything outside the region
    set to the ``background`` colour (as NHA's protocol masks its face-hair-neck images)."""
    rgb = img["rgb"].clamp(0, 1)
    row = {"psnr": M.psnr(rgb, gt), "ssim": M.ssim(rgb, gt), "l1": M.l1(rgb, gt)}
    row |= perceptual(rgb, gt)
    for name, m in masks.items():
        row[f"psnr_{name}"] = M.psnr(rgb, gt, m)
        row[f"ssim_{name}"] = M.ssim(rgb, gt, m)
        row[f"l1_{name}"] = M.l1(rgb, gt, m)
        if name in perceptual_regions:
            inside = m[..., None].to(rgb.device)
            fill = torch.as_tensor(background, dtype=rgb.dtype, device=rgb.device)
            cut = lambda x: torch.where(inside, x, fill)  # noqa: E731
            row |= {f"{k}_{name}": v for k, v in perceptual(cut(rgb), cut(gt.to(rgb.device))).items()}
    return row


#: the outline band's half-width as a share of the scored image's longer side: 2 pixels at 512², where a
#: full body's pixel is 4 mm, so the band holds what a few millimetres of pose or shape error move
OUTLINE_SHARE = 1 / 256


def outline_width(size: tuple[int, int]) -> int:
    """The outline band's half-width in pixels for an image of ``size`` (W, H): at least one pixel."""
    return max(1, round(max(size) * OUTLINE_SHARE))


def head_region(person: torch.Tensor, clothing: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: a head-and-shoulders capture's face, hair and neck: the person less its clothing (the
    region DELTA and NHA score head avatars on, which leaves out the torso's clothes)."""
    return (person > 0.5) & ~(clothing > 0)


def exterior_leaks(nerf_mask: torch.Tensor, person: torch.Tensor, interior: torch.Tensor,
                   face: torch.Tensor) -> dict[str, float]:  # fmt: skip
    """Where the exterior's opacity should not be, from one render's NeRF opacity (H, W) and the capture's
    person alpha, visible-body (skin) alpha and the body mesh's face pixels (H, W):

    - ``nerf_on_skin``: mean opacity over the pixels the capture shows as skin (interior > 0.5);
    - ``nerf_on_face``: the same over those of them on the face;
    - ``nerf_off_person``: opacity summed outside the person (alpha < 0.5), as a share of the capture's
      exterior area (person − skin): what floats free of the body, relative to the clothing and hair.

    NaN where a region is empty."""
    skin = interior > 0.5
    face_skin = skin & face
    outside = person < 0.5
    area = float((person - interior).clamp_min(0).sum())
    mean = lambda m: float(nerf_mask[m].mean()) if bool(m.any()) else math.nan  # noqa: E731
    return {"nerf_on_skin": mean(skin), "nerf_on_face": mean(face_skin),
            "nerf_off_person": float(nerf_mask[outside].sum()) / area if area > 0 else math.nan}  # fmt: skip


def gt_body_vertices(meshes_h5: str | Path, frame_ids) -> dict[int, np.ndarray]:
    with h5py.File(meshes_h5, "r") as f:
        if "body_vertices" not in f:
            raise DeltaError(f"{meshes_h5}: no 'body_vertices'; not a synthetic capture's gt/meshes.h5")
        return {int(i): f["body_vertices"][int(i)] for i in frame_ids}


def body_errors(mesh, ref: np.ndarray, keep: np.ndarray, camera) -> dict:
    """Body vertex error (mm) against the true vertices over the modelled ones (``keep``), and apart over
    those the frame's camera sees and those it does not (hidden behind the body or outside the image:
    a view says nothing of them), all under the one centroid alignment of the modelled vertices."""
    v = mesh.vertices.detach().cpu().numpy()
    if ref.shape != v.shape:
        return {"body_err_mm": np.nan, "body_err_visible_mm": np.nan, "body_err_hidden_mm": np.nan,
                "body_err_pa_mm": np.nan}  # fmt: skip
    err = 1000 * vertex_errors(v[keep], ref[keep])
    seen = visible_vertices(mesh.vertices, mesh.faces, camera).numpy()[keep]
    part = lambda m: float(err[m].mean()) if m.any() else np.nan  # noqa: E731
    return {"body_err_mm": float(err.mean()), "body_err_visible_mm": part(seen), "body_err_hidden_mm": part(~seen),
            "body_err_pa_mm": 1000 * vertex_error(v[keep], ref[keep], align="similarity")}  # fmt: skip


def evaluate(trained: Trained, record: str | Path, st: EvalSettings, gt_meshes: str | Path | None = None,
             subject: str = "", worst_dir: str | Path | None = None) -> pd.DataFrame:  # fmt: skip
    """One row per scored (frame, refined); with ``worst_dir``, the ``st.worst`` lowest-PSNR frames of each
    split as side-by-side PNGs there (``{split}_frame_{id}.png``)."""
    model, data = trained.model, trained.data
    frames = pick_frames(data.split, st.splits, st.max_frames)
    if not frames:
        raise DeltaError(f"{record}: no frames of the splits {list(st.splits)} to evaluate")
    dev = model.background.device
    perceptual = Perceptual(st, dev)
    full = load_full_frames(record, [f for f, _ in frames], trained.settings.background)
    view = full_view(full, model.resolution)
    gt = gt_body_vertices(gt_meshes, data.frame_ids[[f for f, _ in frames]]) if gt_meshes else {}
    face = None
    if gt_meshes:  # a talking capture's truth: the tracked face's expressions are scored too
        ids = [int(data.frame_ids[f]) for f, _ in frames]
        face = AvatarExpressions.of(model, Path(gt_meshes).parent / "params.npz", ids)
    passes = [False, True] if st.refine_steps and st.report_unrefined else [bool(st.refine_steps)]
    bg = "white" if tuple(trained.settings.background) == (1.0, 1.0, 1.0) else str(tuple(trained.settings.background))
    keep = model.modelled.cpu().numpy()
    rows = []
    worst = WorstFrames(st.worst)
    progress = Progress(f"evaluate ({view.width}x{view.height})", len(frames))
    for k, (f, split) in enumerate(frames):
        for refined in passes:
            fit = None
            if refined:
                fit = refine_frame(model, data, f, st.refine_steps, rays=st.refine_rays, lr=st.refine_lr, seed=f,
                                   tol=st.refine_tol, lr_end=st.refine_lr_end, check=st.refine_check,
                                   sides=st.refine_sides, confirm=st.refine_confirm)  # fmt: skip
            with torch.no_grad():
                mesh, offsets, out = model.posed_mesh(f)
            img = render_image(model, f, supersample=st.supersample, view=view, soft_silhouette=False)
            body = full.interior[k] > 0.5
            masks = {"body": body, "face": face_pixels(model, f, mesh.vertices, view) & body}
            masks |= {name: m[k] for name, m in full.parts.items()}
            masks["outline"] = M.outline_band(full.person[k] > 0.5, outline_width(full.size))
            if model.spec.capture == "upper" and "clothing" in full.parts:
                masks["head"] = head_region(full.person[k], full.parts["clothing"][k])
            row = {"subject": subject, "frame": f, "frame_id": int(data.frame_ids[f]), "split": split,
                   "refined": refined, "refine_steps": fit.steps if fit else 0, "stage": trained.stage,
                   "preset": trained.preset, "background": bg, "image": "full",
                   "resolution": "{}x{}".format(*full.size), "train_resolution": trained.settings.resolution,
                   "supersample": st.supersample}  # fmt: skip
            if fit:  # the refinement's residual: its loss on one fixed probe draw of rays before and after
                row |= {"refine_loss_start": fit.loss_start, "refine_loss_end": fit.loss_end,
                        "refine_converged": fit.converged, "refine_kept_step": fit.kept,
                        "refine_overruled": fit.overruled,
                        "refine_sides": " ".join(fit.sides)}  # fmt: skip
            row |= score_image(img, full.images[k], masks, perceptual, ("head",), trained.settings.background)
            row["outline_error_share"] = M.error_share(img["rgb"].clamp(0, 1), full.images[k], masks["outline"])
            row["nerf_iou"] = (
                M.iou(img["nerf_mask"] > 0.5, full.exterior[k] > 0.5) if model.nerf is not None else np.nan
            )
            if model.nerf is not None:
                row |= exterior_leaks(img["nerf_mask"], full.person[k], full.interior[k], masks["face"])
            row["mesh_iou"] = M.iou(img["silhouette"] > 0.5, full.person[k] > 0.5)
            for name in getattr(model.nerf, "names", ()):  # an exterior in layers: each against its own mask
                if name in full.parts:
                    row[f"{name}_layer_iou"] = M.iou(img[f"layer_{name}"] > 0.5, full.parts[name][k])
            if refined == passes[-1]:
                worst.offer(split, row["psnr"], int(data.frame_ids[f]), img["rgb"], full.images[k])
            if gt:
                row |= body_errors(mesh, gt[int(data.frame_ids[f])], keep, model.camera(f))
            if face is not None:
                row |= face(f, int(data.frame_ids[f]))
            rows.append(row)
        scores = " ".join(f"{k} {v:.3f}" for k, v in rows[-1].items() if k in ("psnr", "ssim", "stlpips_alex"))
        progress.report(k + 1, f"frame {f} ({split}) {scores}")
    if worst_dir is not None:
        worst.write(worst_dir)
    return pd.DataFrame(rows)


class WorstFrames:
    """The ``count`` lowest-PSNR renders of each split, kept while the frames are scored."""

    def __init__(self, count: int):
        self.count, self.kept = count, {}

    def offer(self, split: str, psnr: float, frame_id: int, render: torch.Tensor, reference: torch.Tensor) -> None:
        if self.count <= 0:
            return
        kept = self.kept.setdefault(split, [])
        kept.append((psnr, frame_id, render.clamp(0, 1), reference))
        kept.sort(key=lambda item: item[0])
        del kept[self.count :]

    def write(self, out_dir: str | Path) -> list[Path]:
        """The kept frames as side-by-side PNGs (the folder is made even when there are none)."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        written = []
        for split, kept in sorted(self.kept.items()):
            for psnr, frame_id, render, reference in kept:
                path = out / f"{split}_frame_{frame_id:05d}.png"
                with atomic_path(path) as tmp:
                    cv2.imwrite(str(tmp), side_by_side(reference, render))
                written.append(path)
            log.info("lowest PSNR (%s): %s", split, ", ".join(f"frame {i} {p:.2f} dB" for p, i, _, _ in kept))
        return written


def write_csv(df: pd.DataFrame, path: str | Path) -> None:
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False)


def train_body_errors_mm(trained: Trained, gt_meshes: str | Path, every: int = 10) -> dict[str, float]:
    """Body vertex error (mm) over every ``every``-th training frame, centroid-aligned
    (``train_body_err_mm``) and Procrustes-aligned (``train_body_err_pa_mm``; :func:`vertex_errors`): the
    body under the clothing as training left it (the modelled vertices: an ``upper`` capture has no legs)."""
    model, data = trained.model, trained.data
    frames = data.train[::every]
    gt = gt_body_vertices(gt_meshes, data.frame_ids[frames])
    keep = model.modelled.cpu().numpy()
    errs = {"centroid": [], "similarity": []}
    with torch.no_grad():
        offsets = model.offsets()
        for f in frames:
            v = model.pose_body(int(f), offsets).vertices[0].cpu().numpy()
            ref = gt[int(data.frame_ids[f])]
            if ref.shape != v.shape:
                return {"train_body_err_mm": float("nan"), "train_body_err_pa_mm": float("nan")}
            for align, out in errs.items():
                out.append(vertex_error(v[keep], ref[keep], align))
    return {"train_body_err_mm": 1000 * float(np.mean(errs["centroid"])),
            "train_body_err_pa_mm": 1000 * float(np.mean(errs["similarity"]))}  # fmt: skip


def gt_exterior(meshes_h5: str | Path, frame_id: int) -> trimesh.Trimesh | None:
    """The GT clothing and hair layers of one frame as one mesh (None when the capture has none)."""
    with h5py.File(meshes_h5, "r") as f:
        layers = json.loads(f.attrs.get("layers", "[]"))
        parts = [trimesh.Trimesh(f[f"{n}_vertices"][int(frame_id)], f[f"{n}_faces"][:], process=False) for n in layers]
    return trimesh.util.concatenate(parts) if parts else None


def moved_like_body(part, body: np.ndarray, true_body: np.ndarray, keep: np.ndarray) -> trimesh.Trimesh:
    """A posed surface ``part`` (a MeshPart) moved by the similarity that aligns the posed ``body`` (V, 3) with
    the ``true_body`` over the ``keep`` vertices: the surface with the body's size, rotation and place left out."""
    scale, rot, move = similarity_transform(body[keep], true_body[keep])
    return trimesh.Trimesh(scale * part.vertices @ rot.T + move, part.faces, process=False)


def clothing_distance(trained: Trained, nerf_space_mesh: str | Path, gt_meshes: str | Path, frames: list[int],
                      samples: int = 20000) -> dict:  # fmt: skip
    """Chamfer distance (mm, sample to sample), point-to-surface distance (mm, samples to the other
    mesh's triangles, exact) and normal consistency of the exported clothing surface, posed as each
    frame by forward skinning, against the GT clothing and hair of that frame. Both are moved by the
    offset that aligns the fitted body's centroid with the GT body's (as the body error is).

    ``clothing_p2s_pa_*``: the same point-to-surface distance with the clothing moved instead by the
    similarity that aligns the fitted body with the GT body (its rotation, scale and translation over
    the modelled vertices, as ``body_err_pa_mm`` is taken): the clothing's error with the body's size,
    which one camera cannot observe, left out (docs/evaluation.md)."""
    from delta.export.meshes import pose_clothing, read_mesh

    model, data = trained.model, trained.data
    part = read_mesh(nerf_space_mesh)
    if part.empty:
        return {}
    gt_body = gt_body_vertices(gt_meshes, data.frame_ids[frames])
    keep = model.modelled.cpu().numpy()
    rows, exact, exact_pa = [], [], []
    with torch.no_grad():
        offsets = model.offsets()
        for f in frames:
            fid = int(data.frame_ids[f])
            ref = gt_exterior(gt_meshes, fid)
            if ref is None:
                return {}
            out = model.pose_body(int(f), offsets)
            posed = pose_clothing(model, part, out)
            body = out.vertices[0].cpu().numpy()
            shift = gt_body[fid].mean(0) - body.mean(0)
            pred = trimesh.Trimesh(posed.vertices + shift, posed.faces, process=False)
            rows.append(mesh_distance(pred, ref, samples, seed=f))
            exact.append(point_to_surface(pred, ref, samples, seed=f))
            exact_pa.append(point_to_surface(moved_like_body(posed, body, gt_body[fid], keep), ref, samples, seed=f))
    return {"clothing_chamfer_mm": 1000 * float(np.mean([r.chamfer for r in rows])),
            "clothing_accuracy_mm": 1000 * float(np.mean([r.accuracy for r in rows])),
            "clothing_completeness_mm": 1000 * float(np.mean([r.completeness for r in rows])),
            "clothing_normal_consistency": float(np.mean([r.normal_consistency for r in rows])),
            "clothing_p2s_mm": 1000 * float(np.mean([r.mean for r in exact])),
            "clothing_p2s_accuracy_mm": 1000 * float(np.mean([r.accuracy for r in exact])),
            "clothing_p2s_completeness_mm": 1000 * float(np.mean([r.completeness for r in exact])),
            "clothing_p2s_pa_mm": 1000 * float(np.mean([r.mean for r in exact_pa])),
            "clothing_p2s_pa_accuracy_mm": 1000 * float(np.mean([r.accuracy for r in exact_pa])),
            "clothing_p2s_pa_completeness_mm": 1000 * float(np.mean([r.completeness for r in exact_pa])),
            "clothing_frames": len(rows)}  # fmt: skip


def convention(df: pd.DataFrame, st: EvalSettings) -> dict:
    """How the scores were taken, as the columns of ``metrics.csv`` carry it."""
    first = df.iloc[0]
    return {"background": str(first["background"]), "image": str(first["image"]), "resolution": str(first["resolution"]),
            "train_resolution": int(first["train_resolution"]), "supersample": st.supersample, "data_range": 1,
            "perceptual": "+".join(c for c in ("stlpips_alex", "lpips_alex") if c in df) or "none",
            "refinement": f"pose and camera, model frozen, {st.refine_steps} steps" if st.refine_steps else "none"}  # fmt: skip


def summarize(df: pd.DataFrame) -> dict:
    """Mean of every score per (split, refined), e.g. ``{"test_view": {"refined": {...}, "unrefined": {...}}}``."""
    scores = [c for c in df.columns if df[c].dtype.kind == "f" or c == "refine_steps"]  # steps: taken, on average
    out: dict = {}
    for (split, refined), g in df.groupby(["split", "refined"]):
        out.setdefault(split, {})["refined" if refined else "unrefined"] = {
            c: (None if np.isnan(v) else round(float(v), 5)) for c, v in g[scores].mean().items()
        } | {"frames": int(len(g))}
    return out
