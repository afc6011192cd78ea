"""How consistently a trained avatar's deformation carries the true garment to its canonical space.

The exterior is one canonical NeRF: every training frame's clothing is mapped back to it by the kNN
skinning (``delta/deformers/knn.py``) and, in stage 2, moved by F_e. Where one point of the true garment
lands at different canonical points in different frames, the NeRF learns the average of what those
frames show there: a pattern is smeared by that spread, whatever the grid's cells. On a synthetic
subject the generator's garment meshes say where each garment vertex is in every frame, so the spread
is measured directly: each training frame's true garment vertices (brought into the avatar's frame by
the similarity that best aligns the true body to the avatar's posed body, same topology) are deformed
as the renderer deforms a sample, and each vertex's spread is its mean distance to its mean canonical
point over the frames.

The alignment is made per frame, so it also takes away that frame's error of the fitted body as a whole
(its root's turn and place): the ``fitted`` pass is a lower bound of the spread training sees, and that
error is measured apart (``pose_gap.py``'s root error). Two passes separate the causes: ``fitted`` (the
avatar's own poses: what training saw, less the whole body's error) and ``true``
(the generator's poses put in their place, as ``pose_gap.py`` does: what the deformation model itself
leaves). Rows: subject, poses, split, deformation (``knn``, ``knn+F_e`` with the frame's time, ``knn+F_e
(no time)`` as a novel pose gets it), garment layer, height band of the garment (quintiles of its
canonical height, ``all`` for the whole), and the spread's mean, median and 90th percentile in mm.

Held-out frames (``--held-out test_pose``): each vertex's distance, in those frames, from its mean
canonical point over the training frames: how far from what the NeRF learnt a novel pose looks it up.
Part of any spread is no deformation's: the generator moves garments and hair non-rigidly (a loose part
lags a turn and swings; a tight one ripples, ``delta.synthetic.garments.nonrigid_offsets``). With the
subject's synthetic spec (``--config``, the workflow's config files) the rows of deformation ``truth``
measure that motion itself the same way (each vertex's canonical point plus the frame's non-rigid
offset): the floor no skinning can go below.

    PYTHONPATH=$PWD python3 benchmarks/canonical_spread.py --model results/synthetic/gen6/stage2/model.pt \\
        --record results/synthetic/gen6/frames.h5 --body resources/body/anny_sub1.npz --subject gen6 \\
        --truth data/synthetic/gen6/gt --csv benchmarks/canonical_spread.csv
    PYTHONPATH=$PWD python3 benchmarks/canonical_spread.py --model results/synthetic/talker/stage2/model.pt \\
        --record results/synthetic/talker/frames.h5 --body resources/body/anny_sub1_face.npz --subject talker \\
        --truth data/synthetic/talker/gt --poses fitted --held-out test_view test_pose --diffused 0.015 --head-bound \\
        --config config/config.yaml config/heads.yaml --csv benchmarks/canonical_spread.csv --append
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import torch
import trimesh

from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.config import load_config
from delta.deformers import knn as deformer
from delta.eval.geometry import similarity_transform
from delta.geometry.nearest import PointIndex
from delta.synthetic.garments import build_layers, nonrigid_offsets
from delta.synthetic.generate import scene_motion
from delta.synthetic.spec import parse_subject
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pose_gap import put_true_poses  # noqa: E402
from table import model_arguments, save_table  # noqa: E402

BANDS = 5
#: the record's split codes (``delta.data.frames.FrameData.split``)
SPLITS = {"test_view": 1, "test_pose": 2}


def garment_layers(meshes: h5py.File) -> list[str]:
    """The generator's exterior layers (every ``{name}_vertices`` but the body's)."""
    return sorted(k[: -len("_vertices")] for k in meshes if k.endswith("_vertices") and k != "body_vertices")


@torch.no_grad()
def diffused(frame: deformer.SkinningFrame, points: torch.Tensor, cell: float, k: int = 48) -> torch.Tensor:
    """Canonical points (N, 3) by a weight field diffused from the body: the maps of a sparse subset of the
    vertices (one per ``cell`` voxel), blended by a Gaussian of the distance whose width is the point's
    own distance to the body (1.5 x, at least a centimetre): on the body its nearest vertex's map, farther
    out a blend of every part within that reach (a study; the renderer uses ``deformer.deform``)."""
    posed = frame.posed.detach()
    sparse = deformer.voxel_subset(posed, cell)
    dist, j = PointIndex(posed[sparse]).query(points, min(k, len(sparse)))
    width = (1.5 * frame.index.query(points, 1)[0][:, :1].to(points.dtype)).clamp_min(0.01)
    alpha = torch.softmax(-(dist.to(points.dtype) ** 2) / (2 * width**2), dim=-1)
    M = (alpha[..., None, None] * frame.to_canonical.detach()[sparse[j]]).sum(1)
    return (M[..., :3] @ points[..., None]).squeeze(-1) + M[..., 3]


@torch.no_grad()
def canonical_points(model, frames, meshes: h5py.File, frame_ids, layers,
                     diffuse_cell: float = 0.0) -> dict[tuple[str, str], np.ndarray]:  # fmt: skip
    """(deformation, layer) -> (F, V, 3) canonical points of the layer's true vertices in ``frames``."""
    rs = model.spec.render
    out: dict[tuple[str, str], list] = {}
    for f in frames:
        mesh, _, posed = model.posed_mesh(int(f))
        fid = int(frame_ids[f])
        scale, rot, shift = similarity_transform(meshes["body_vertices"][fid], posed.vertices[0].cpu().numpy())
        for layer in layers:
            true = meshes[f"{layer}_vertices"][fid].astype(np.float64)
            points = torch.as_tensor(scale * true @ rot.T + shift, dtype=torch.float32, device=model.poses.device)
            d = deformer.deform(mesh.skinning, points, rs.k, rs.sigma, float("inf"))
            passes = {"knn": d.canonical}
            if diffuse_cell > 0:
                passes["diffused"] = diffused(mesh.skinning, points, diffuse_cell)
            if mesh.skinning.head_index is not None:  # every layer as a hair layer bound to the head goes
                passes["head-bound"] = deformer.head_bound(mesh.skinning, points, d.canonical, d.distance)
            if model.deformation is not None:
                passes["knn+F_e"] = d.canonical + model.deformation(d.canonical, d.posed_ref, model.time_code(int(f)))
                passes["knn+F_e (no time)"] = d.canonical + model.deformation(d.canonical, d.posed_ref)
            for name, c in passes.items():
                out.setdefault((name, layer), []).append(c.cpu().numpy())
    return {k: np.stack(v) for k, v in out.items()}


def truth_points(config: list[str], subject: str, body: str, truth: Path, splits: dict, layers) -> dict:
    """split -> (``truth``, layer) -> (F, V, 3): the generator's canonical vertices of each layer plus their
    non-rigid offsets in each split's frames (``splits``: name -> capture frame numbers), rebuilt once from the
    subject's spec and true shape."""
    raw = load_config(config, device=False)["datasets"]["synthetic"]["subjects"].get(subject)
    if raw is None:
        raise SystemExit(f"{subject}: not a synthetic subject of {' '.join(config)}")
    spec = parse_subject(subject, raw)
    model = load_body_model(body, dtype=torch.float64)
    params = np.load(truth / "params.npz")
    with torch.no_grad():
        zero = torch.zeros(1, model.num_joints, 3, dtype=torch.float64)
        rest = lbs(model, torch.from_numpy(params["betas"])[None], zero)
    built = {l.name: l for l in build_layers(model, rest.vertices[0].numpy(), rest.joints[0].numpy(), spec.garments,
                                             spec.hair)}  # fmt: skip
    _, rates, _, times = scene_motion(spec, model.joint_names, model.expression_names)
    normals = {n: trimesh.Trimesh(built[n].vertices, built[n].faces, process=False).vertex_normals for n in layers}

    def moved(name: str, frames) -> np.ndarray:
        layer = built[name]
        return np.stack([layer.vertices + nonrigid_offsets(layer, normals[name], times[f], rates[f], spec.sway)
                         for f in frames])  # fmt: skip

    return {split: {("truth", n): moved(n, frames) for n in layers} for split, frames in splits.items()}


def spread_rows(points: np.ndarray, reference: np.ndarray | None = None) -> list[dict]:
    """Rows of one (F, V, 3) set: the spread (mean distance to the vertex's mean point, mm) over all the
    vertices and per height band (quintiles of the mean canonical height, lowest first). With a
    ``reference`` (F', V, 3) set the mean point and the bands are the reference's (the training frames')."""
    mean = (points if reference is None else reference).mean(0)
    spread = 1000 * np.linalg.norm(points - mean, axis=-1).mean(0)
    edges = np.quantile(mean[:, 1], np.linspace(0, 1, BANDS + 1))
    band = np.clip(np.searchsorted(edges, mean[:, 1], side="right") - 1, 0, BANDS - 1)
    rows = [("all", np.ones(len(spread), bool), edges[0], edges[-1])]
    rows += [(f"{b + 1} of {BANDS}", band == b, edges[b], edges[b + 1]) for b in range(BANDS)]
    return [{"band": name, "y_from_m": round(float(lo), 3), "y_to_m": round(float(hi), 3), "vertices": int(sel.sum()),
             "spread_mean_mm": float(spread[sel].mean()), "spread_median_mm": float(np.median(spread[sel])),
             "spread_p90_mm": float(np.percentile(spread[sel], 90))} for name, sel, lo, hi in rows]  # fmt: skip


def main(argv=None) -> None:
    ap = model_arguments(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument("--truth", required=True, help="the subject's gt folder (params.npz, meshes.h5)")
    ap.add_argument("--every", type=int, default=6, help="every how many training frames to use")
    ap.add_argument("--poses", nargs="+", default=["fitted", "true"], choices=["fitted", "true"])
    ap.add_argument(
        "--held-out",
        nargs="*",
        default=[],
        choices=["test_view", "test_pose"],
        help="also each held-out split's distance from the training frames' mean canonical points",
    )
    ap.add_argument("--config", nargs="+", help="the workflow's config files: rows of the truth's own motion")
    ap.add_argument(
        "--diffused",
        type=float,
        default=0.0,
        metavar="CELL",
        help="also rows of a weight field diffused from one vertex per CELL m (0: none)",
    )
    ap.add_argument("--head-bound", action="store_true", help="also rows of the carriage bound to the head")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    truth = np.load(Path(a.truth) / "params.npz")
    rows = []
    with h5py.File(Path(a.truth) / "meshes.h5", "r") as meshes:
        layers = garment_layers(meshes)
        for poses in a.poses:
            trained = load_trained(a.model, a.record, a.body)
            model, data = trained.model, trained.data
            ids, train = np.asarray(data.frame_ids), np.flatnonzero(np.asarray(data.train))
            if len(meshes["body_vertices"][0]) != model.body.num_vertices:
                raise SystemExit(f"{a.truth}: its body has {len(meshes['body_vertices'][0])} vertices, the avatar's "
                                 f"{model.body.num_vertices}: not the same body model")  # fmt: skip
            split = np.asarray(data.split)
            held = {name: np.flatnonzero(split == SPLITS[name])[:: max(1, a.every // 2)] for name in a.held_out}
            if a.head_bound:  # the frames carry the head's vertices: rows of the carriage bound to the head
                bound = dataclasses.replace(model.spec.render, hair_carriage="head")
                model.spec = dataclasses.replace(model.spec, render=bound, layers=tuple(model.spec.layers) or ("hair",))
            if poses == "true":
                put_true_poses(model, train, ids, train, truth)
                held = {}  # the true poses are put in for the training frames only
            frames = train[:: a.every]
            sets = {"train": canonical_points(model, frames, meshes, ids, layers, a.diffused)}
            sets |= {name: canonical_points(model, f, meshes, ids, layers, a.diffused) for name, f in held.items()}
            if a.config and poses == "fitted":
                splits = {name: ids[f] for name, f in {"train": frames, **held}.items()}
                for name, found in truth_points(a.config, a.subject, a.body, Path(a.truth), splits, layers).items():
                    sets[name] |= found
            for name, found in sets.items():
                for (deformation, layer), points in found.items():
                    reference = None if name == "train" else sets["train"][(deformation, layer)]
                    for r in spread_rows(points, reference):
                        rows.append({"subject": a.subject, "poses": poses, "split": name, "deformation": deformation,
                                     "layer": layer, "frames": len(points), **r, "model": a.model})  # fmt: skip
    table = pd.DataFrame(rows)
    print(table[table.band.isin(["all", f"1 of {BANDS}"])].drop(columns="model").round(1).to_string(index=False))
    save_table(table.round(2), a.csv, a.append)


if __name__ == "__main__":
    main()
