"""How well the init fit finds which way is up when the camera is not level.

A body turning in place (random small limb poses, the root yaw over a full turn) is filmed by the
synthetic generator's pinhole camera pitched and rolled by the given angles; its OpenPose-18
keypoints, with Gaussian pixel noise, are fitted in the camera's own frame, as a video is (the
camera's intrinsics, no extrinsics). The capture's up estimated from the fitted bodies
(:mod:`delta.body.upright`) is compared with the world's up seen from that camera, next to the
camera's own vertical (what a turntable turned about before the estimate): the bodies' estimate alone
(``bodies_up_error_deg``) and the workflow's, which takes the camera's vertical when the bodies agree
with it within ``LEVEL_SNAP_DEG`` (``estimated_up_error_deg``, ``took_camera``).

    python benchmarks/upright.py --body resources/body/anny_sub1.npz --out benchmarks/upright.csv
"""

from __future__ import annotations

import argparse
import math
import time

import pandas as pd
import torch

from delta.body.keypoints import openpose18_map
from delta.body.lbs import batch_rodrigues, posed_joints
from delta.body.model import load_body_model
from delta.body.upright import angle_deg, estimate_upright
from delta.cameras.models import PinholeCamera
from delta.fitting.fit import KeypointModel, fit
from delta.fitting.settings import FitConfig
from delta.synthetic.generate import frame_span, make_camera
from delta.synthetic.spec import parse_subject

D = torch.float64


def one(model, kp_map, pitch: float, roll: float, frames: int, noise_px: float, seed: int) -> dict:
    spec = parse_subject("tilted", {"camera_pitch": pitch, "camera_roll": roll, "resolution": 512})
    cam = make_camera(spec, *frame_span(spec, model.v_template[:, 1].double().numpy()))
    gen = torch.Generator().manual_seed(seed)
    pose = 0.08 * torch.randn(frames, model.num_joints, 3, generator=gen, dtype=D)
    pose[:, 0] = 0.0
    pose[:, 0, 1] = torch.linspace(0, 2 * math.pi, frames + 1, dtype=D)[:-1]
    transl = torch.zeros(frames, 3, dtype=D)
    uv, _ = cam.project(KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=D), pose, transl))
    uv = uv + noise_px * torch.randn(uv.shape, generator=gen, dtype=D)
    detected = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    video = PinholeCamera(cam.K, torch.eye(3, dtype=D), torch.zeros(3, dtype=D), cam.dist, cam.width, cam.height)
    t = time.perf_counter()
    res = fit(model, kp_map, detected, video, FitConfig(iterations=(80, 60, 0), sil_weight=0.0))
    rot = batch_rodrigues(res.pose)
    joints = posed_joints(model, res.betas, rot, res.transl)
    camera_up = torch.tensor([0.0, -1.0, 0.0], dtype=D)
    bodies = estimate_upright(rot[:, 0], joints)
    est = estimate_upright(rot[:, 0], joints, camera_up)
    truth = cam.R @ torch.tensor([0.0, 1.0, 0.0], dtype=D)
    return {"pitch_deg": pitch, "roll_deg": roll, "frames": frames, "noise_px": noise_px, "seed": seed,
            "camera_vertical_error_deg": round(angle_deg(camera_up, truth), 2),
            "bodies_up_error_deg": round(angle_deg(bodies.up, truth), 2),
            "estimated_up_error_deg": round(angle_deg(est.up, truth), 2), "took_camera": est.source != "bodies",
            "spread_deg": round(est.spread_deg, 2),
            "residual_px": round(float(res.residual_px.median()), 2),
            "fit_seconds": round(time.perf_counter() - t, 1)}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--body", required=True)
    p.add_argument("--pitch", type=float, nargs="+", default=[-15.0, 0.0, 15.0, 30.0])
    p.add_argument("--roll", type=float, nargs="+", default=[0.0, 15.0, 30.0])
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--noise-px", type=float, default=2.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    torch.set_num_threads(2)
    model = load_body_model(args.body, dtype=D)
    kp_map = openpose18_map(model)
    rows = []
    for pitch in args.pitch:
        for roll in args.roll:
            rows.append(one(model, kp_map, pitch, roll, args.frames, args.noise_px, args.seed))
            print(rows[-1], flush=True)
    pd.DataFrame(rows).to_csv(args.out, index=False)


if __name__ == "__main__":
    main()
