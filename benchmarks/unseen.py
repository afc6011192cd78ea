"""Where no training frame looked: the albedo's harmonic fill and the exterior's mirror against the fields' own.

A turning capture shows the whole body; a capture that never turns far from the camera (a talking head, a
dancer facing it) never shows the back. ``front`` writes a copy of a frame record whose training frames are only
those where the fitted body turns at most ``--turned`` degrees from the camera (the rest become held-out views),
so the same subject can be trained as such a capture. ``score`` scores a trained avatar's held-out views by the
workflow's evaluation (whole frames at the capture's size, unrefined, so that the pose cannot make up for the
colour) once a variant (:data:`VARIANTS`): the albedo's fill of the look from outside and the exterior's mirror
as training's end computes them (``training.unseen_albedo: outside``, ``training.unseen_exterior: mirror``),
the fill of the albedo alone with and without the mirror, neither. With
``--reference`` (the same subject trained on its whole turn) it also compares, on the vertices the front-only
capture never saw and the whole turn did, each variant's albedo with the reference's (RMSE on [0, 1] colours).
``views`` draws a turntable of each variant, a row each.

    PYTHONPATH=$PWD python3 benchmarks/unseen.py front --record results/synthetic/tight/frames.h5 \
        --init results/synthetic/tight/init/params.npz --turned 60 --out W/frames.h5
    delta train --stage 1 --record W/frames.h5 --body resources/body/anny_sub1.npz \
        --start results/synthetic/tight/init/params.npz --out W/stage1 \
        --settings "$(jq .settings results/synthetic/tight/stage1/settings.json)"
    PYTHONPATH=$PWD python3 benchmarks/unseen.py score --model W/stage1/model.pt --record W/frames.h5 \
        --body resources/body/anny_sub1.npz --subject tight --reference results/synthetic/tight/stage1/model.pt \
        --reference-record results/synthetic/tight/frames.h5 --max-frames 6 --csv benchmarks/unseen.csv
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pandas as pd
import torch

from delta.body.lbs import batch_rodrigues
from delta.eval.evaluate import evaluate
from delta.eval.settings import EvalSettings
from delta.export.video import turntable
from delta.models.unseen import seen_vertices, spread, unseen_albedo, unseen_parts
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import model_arguments, save_table  # noqa: E402


def facing_degrees(poses: np.ndarray, transl: np.ndarray, camera_center: np.ndarray | None) -> np.ndarray:
    """(N,) how far (degrees) each frame's body (root axis-angle ``poses`` (N, 3), ``transl`` (N, 3)) turns
    from the camera: the angle between the root's forward axis (the body's +z) and the way to the camera, both
    on the floor (the vertical left out). An orthographic camera looks along -z from +z."""
    forward = batch_rodrigues(torch.as_tensor(poses).double())[:, :, 2].numpy()
    to_camera = np.tile([0.0, 0.0, 1.0], (len(poses), 1)) if camera_center is None else camera_center - transl
    forward[:, 1] = to_camera[:, 1] = 0.0
    cos = (forward * to_camera).sum(1) / np.linalg.norm(forward, axis=1) / np.linalg.norm(to_camera, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def front(args) -> None:
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(args.record, out)
    with h5py.File(out, "r+") as h:
        center = None
        if "R" in h and "t" in h:
            center = -np.asarray(h["R"][:]).T @ np.asarray(h["t"][:])
        split = h["split"][:]
        with np.load(args.init, allow_pickle=False) as z:
            turned = facing_degrees(z["poses"][:, 0], z["transl"], center)
        moved = (split == 0) & (turned > args.turned)
        split[moved] = 1
        h["split"][...] = split
    print(f"{out}: {int((split == 0).sum())} training frames (turned at most {args.turned} degrees), "
          f"{int(moved.sum())} moved to held-out views")  # fmt: skip


VARIANTS = ("outside+mirror", "fill+mirror", "fill", "field")
"""What the avatar holds where no training frame looked: the fill of the seen surface as it looks from outside
(its exterior over its albedo) and the exterior's mirror (the workflow's default), the fill of the seen albedo
alone with the mirror, that fill alone, or neither (the fields' own extrapolation)."""


def unseen(model, frames) -> dict:
    """The albedo's fills and the exterior's mirror as training's end computes them from ``frames``."""
    (ids, values), mirror, evidence = unseen_parts(model, frames)
    seen = seen_vertices(model, spread(frames))
    _, albedo_values, _ = unseen_albedo(model, frames, seen, outside=False)
    return {"ids": ids, "values": values, "albedo_values": albedo_values, "mirror": mirror,
            "cells_mirrored": evidence.get("exterior", {}).get("mirrored", 0),
            "border_covered": evidence.get("albedo", {}).get("border_covered", 0)}  # fmt: skip


def set_variant(model, parts: dict, variant: str) -> None:
    fill = variant != "field"
    values = parts["values"] if variant.startswith("outside") else parts["albedo_values"]
    model.fill_albedo(parts["ids"] if fill else parts["ids"][:0], values if fill else values[:0])
    model.exterior_mirror = parts["mirror"] if variant.endswith("+mirror") else None


def albedo_rmse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(((a - b) ** 2).mean().sqrt())


def score(args) -> None:
    trained = load_trained(args.model, args.record, args.body)
    model, data = trained.model, trained.data
    parts = unseen(model, data.train)
    st = EvalSettings(splits=("test_view",), max_frames=args.max_frames, supersample=args.supersample,
                      refine_steps=0, worst=0)  # fmt: skip
    center = model.camera(0).center.detach().double().numpy() if model.pinhole else None
    turned = facing_degrees(model.poses[:, 0].detach(), model.transl.detach().double().numpy(), center)
    compare = {}
    if args.reference:
        ref = load_trained(args.reference, args.reference_record, args.body)
        only = seen_vertices(ref.model, ref.data.train) & ~seen_vertices(model, data.train)
        compare = {"only": only, "albedo": ref.model.albedo().detach()[only]}
    rows = []
    for variant in args.variants:
        set_variant(model, parts, variant)
        df = evaluate(trained, args.record, st, subject=args.subject)
        extra = {"variant": variant, "vertices_filled": len(parts["ids"]), "cells_mirrored": parts["cells_mirrored"],
                 "border_covered": parts["border_covered"], "training_frames": len(data.train)}  # fmt: skip
        if compare:
            got = model.albedo().detach()[compare["only"]]
            extra |= {"vertices_compared": int(compare["only"].sum()),
                      "albedo_rmse_vs_reference": albedo_rmse(got, compare["albedo"])}  # fmt: skip
        for _, r in df.iterrows():
            rows.append({"subject": args.subject, **extra, "frame_id": int(r["frame_id"]),
                         "turned_deg": float(turned[int(r["frame"])]), "psnr": r["psnr"], "psnr_body": r["psnr_body"],
                         "psnr_clothing": r.get("psnr_clothing", np.nan), "psnr_hair": r.get("psnr_hair", np.nan),
                         "ssim": r["ssim"],
                         "nerf_iou": r["nerf_iou"], "resolution": r["resolution"], "supersample": args.supersample})  # fmt: skip
    table = pd.DataFrame(rows).round(4)
    save_table(table, args.csv, append=args.append)
    print(table.to_string(index=False))
    print(
        table.groupby("variant")[["psnr", "psnr_body", "psnr_clothing", "psnr_hair", "nerf_iou"]]
        .mean()
        .round(3)
        .to_string()
    )


def views(args) -> None:
    """A PNG of turntable views of one frame, a row a variant (:data:`VARIANTS`, top to bottom)."""
    trained = load_trained(args.model, args.record, args.body)
    model = trained.model
    parts = unseen(model, trained.data.train)
    rows = []
    for variant in VARIANTS:
        set_variant(model, parts, variant)
        rows.append(np.concatenate(list(turntable(model, args.frame, args.count)), 1))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), np.concatenate(rows, 0))
    print(f"{args.out}: {args.count} turntable views of frame {args.frame}, a row each of {', '.join(VARIANTS)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    f = sub.add_parser("front", help="a copy of a record that trains only on frames turned towards the camera")
    f.add_argument("--record", required=True)
    f.add_argument("--init", required=True, help="the init fit's params.npz (the bodies' headings)")
    f.add_argument("--turned", type=float, default=60.0, help="degrees from the camera a training frame may turn")
    f.add_argument("--out", required=True)
    f.set_defaults(run=front)
    s = model_arguments(sub.add_parser("score", help="the held-out views with the fill and with the field"))
    s.add_argument("--reference", default="", help="the subject's avatar trained on its whole turn")
    s.add_argument("--reference-record", default="")
    s.add_argument("--max-frames", type=int, default=6)
    s.add_argument("--supersample", type=int, default=2)
    s.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    s.add_argument("--csv", required=True)
    s.add_argument("--append", action="store_true")
    s.set_defaults(run=score)
    v = sub.add_parser("views", help="turntable views with the fill and with the field, one PNG")
    v.add_argument("--model", required=True)
    v.add_argument("--record", required=True)
    v.add_argument("--body", required=True)
    v.add_argument("--frame", type=int, default=0)
    v.add_argument("--count", type=int, default=4)
    v.add_argument("--out", required=True)
    v.set_defaults(run=views)
    args = ap.parse_args()
    args.run(args)


if __name__ == "__main__":
    main()
