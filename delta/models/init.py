"""The init fit's parameters (``init/params.npz``) as an avatar's starting point, checked against the frame record."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from delta import DeltaError
from delta.cameras.models import OrthographicCamera
from delta.data.frames import FrameData
from delta.models.avatar import InitParams


def load_init(path: str | Path, data: FrameData) -> InitParams:
    """The init fit's parameters, checked against the frame record."""
    with np.load(path, allow_pickle=False) as z:
        p = {k: z[k] for k in z.files}
    for key in ("betas", "poses", "transl", "frame_ids"):
        if key not in p:
            raise DeltaError(f"{path}: missing '{key}'; rerun the fit_init rule")
    if not np.array_equal(p["frame_ids"], data.frame_ids):
        raise DeltaError(f"{path}: its frames ({len(p['frame_ids'])}) differ from the frame record's "
                         f"({len(data.frame_ids)}); rerun fit_init")  # fmt: skip
    t = lambda k: torch.from_numpy(np.asarray(p[k], dtype=np.float32))  # noqa: E731
    camera = data.camera
    if str(p.get("camera_model", "pinhole")) == "orthographic":
        camera = OrthographicCamera(t("ortho_scale"), t("ortho_trans"), data.resolution, data.resolution)
    expression = t("expression") if "expression" in p else None
    if expression is not None and expression.shape[0] != len(data.frame_ids):
        raise DeltaError(f"{path}: 'expression' has {expression.shape[0]} rows for {len(data.frame_ids)} frames")
    return InitParams(t("betas"), t("poses"), t("transl"), camera, expression)
