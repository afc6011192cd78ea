"""The init-fitting step: frame record + body model -> results/{dataset}/{subject}/init/."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from delta.body.keypoints import openpose18_map
from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.cameras.models import OrthographicCamera
from delta.data.record import FrameRecord
from delta.fitting.fit import FitConfig, fit
from delta.io import atomic_path, save_npz

log = logging.getLogger(__name__)
_KNEES = ("lowerleg01.L", "lowerleg01.R", "left_knee", "right_knee")


def run(record_path: str | Path, body_path: str | Path, out_dir: str | Path, overlays: int = 4) -> dict:
    """Fit and write ``params.npz``, ``report.csv`` (per-frame residuals and flags) and overlay PNGs."""
    out = Path(out_dir)
    model = load_body_model(body_path, dtype=torch.float64)
    kp_map = openpose18_map(model)
    with FrameRecord(record_path) as rec:
        detected = torch.from_numpy(rec.h5["keypoints"][:])
        camera = rec.camera(0) if rec.h5.attrs["camera_model"] == "pinhole" else OrthographicCamera(
            torch.tensor(1.0, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), rec.size, rec.size)
        frame_ids = rec.h5["frame_ids"][:]
        knees = [model.joint_names.index(n) for n in _KNEES if n in model.joint_names]
        res = fit(model, kp_map, detected, camera, FitConfig(), knees=knees)
        cam = {"camera_model": np.array(rec.h5.attrs["camera_model"])}
        if isinstance(res.camera, OrthographicCamera):
            cam.update(ortho_scale=res.camera.scale.numpy(), ortho_trans=res.camera.trans.numpy())
        save_npz(out / "params.npz", betas=res.betas.numpy(), poses=res.pose.numpy(), transl=res.transl.numpy(),
                 flagged=res.flagged.numpy(), frame_ids=frame_ids, joint_names=np.array(model.joint_names), **cam)  # fmt: skip
        report = pd.DataFrame({"frame": frame_ids, "flagged": res.flagged.numpy(),
                               "residual_px": res.residual_px.numpy(),
                               "confident_keypoints": (detected[..., 2] >= 0.3).sum(-1).numpy()})  # fmt: skip
        with atomic_path(out / "report.csv") as tmp:
            report.to_csv(tmp, index=False)
        picks = np.linspace(0, len(frame_ids) - 1, min(overlays, len(frame_ids))).round().astype(int)
        for k in picks:
            _overlay(rec, k, model, res, out / f"overlay_{int(frame_ids[k]):05d}.png")
    summary = {"frames": int(len(frame_ids)), "flagged": int(res.flagged.sum()),
               "residual_px_mean": float(np.nanmean(res.residual_px.numpy()))}  # fmt: skip
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
