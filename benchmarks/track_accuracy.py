"""How right the points tracked through a synthetic capture's training frames are (``delta.data.tracks``).

Each track's pixels in two frames should show the same point of the same garment. The generator's meshes say
which: a pixel's ray (the frame record's camera) meets the frame's true surfaces (body and every layer, one
mesh), and the point it meets is carried to the layer's canonical surface by its barycentric coordinates.
Each track is read from its first frame to each of its others: the error is the distance between the
two canonical points (mm), and whether they lie on the same layer. Rows: subject, the frames' gap in the
capture (in bins), the pairs read, the share on the same layer, the layers hit, and the error's median,
mean and 90th percentile over the pairs on one layer.

    PYTHONPATH=$PWD python3 benchmarks/track_accuracy.py --record results/synthetic/loose/frames.h5 \\
        --truth data/synthetic/loose/gt --subject loose --csv benchmarks/track_accuracy.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import torch
import trimesh

from delta.cameras.models import OrthographicCamera
from delta.data.frames import load_frames
from delta.data.tracks import frame_tracks

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

#: bins of the two ends' gap in capture frames
GAPS = [(1, 1), (2, 5), (6, 15), (16, 1000)]


def frame_camera(camera, row: int):
    """The record's camera of one frame (an orthographic camera holds one scale and shift a frame)."""
    if isinstance(camera, OrthographicCamera):
        return OrthographicCamera(camera.scale[row], camera.trans[row], camera.width, camera.height)
    return camera


class TrueSurfaces:
    """The generator's surfaces of a capture (the body and every layer) as one mesh a frame; the faces, their
    layer and the canonical vertices do not change from frame to frame and are read once."""

    def __init__(self, meshes: h5py.File, layers: list[str]):
        self.meshes, self.layers = meshes, layers
        faces = [meshes[f"{n}_faces"][:] for n in layers]
        start = np.cumsum([0] + [len(meshes[f"{n}_canonical"]) for n in layers])
        self.faces = np.concatenate([f + start[k] for k, f in enumerate(faces)])
        self.owner = np.concatenate([np.full(len(f), k) for k, f in enumerate(faces)])
        self.canonical = np.concatenate([meshes[f"{n}_canonical"][:] for n in layers]).astype(np.float64)

    def hits(self, fid: int, camera, pixels: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """(M, 3) canonical points and (M,) layer index (-1: no hit) where rays through ``pixels`` meet frame
        ``fid``'s surfaces."""
        V = np.concatenate([self.meshes[f"{n}_vertices"][fid] for n in self.layers]).astype(np.float64)
        origins, dirs = camera.rays(pixels.double())
        tri, ray, loc = trimesh.Trimesh(V, self.faces, process=False).ray.intersects_id(
            origins.numpy(), dirs.numpy(), multiple_hits=False, return_locations=True
        )
        points, layer = np.full((len(pixels), 3), np.nan), np.full(len(pixels), -1)
        corners = self.faces[tri]
        bary = trimesh.triangles.points_to_barycentric(V[corners], loc)
        points[ray] = np.einsum("nk,nkc->nc", bary, self.canonical[corners])
        layer[ray] = self.owner[tri]
        return points, layer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--record", required=True)
    ap.add_argument("--truth", required=True, help="the subject's gt folder (meshes.h5)")
    ap.add_argument("--subject", required=True)
    ap.add_argument("--resolution", type=int, default=512, help="the frames' size the tracks are made at")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    args = ap.parse_args()

    data = load_frames(args.record, args.resolution)
    tracks = frame_tracks(data.images, data.exterior, data.frame_ids, data.train)
    meshes = h5py.File(Path(args.truth) / "meshes.h5", "r")
    layers = ["body"] + sorted(
        k[: -len("_vertices")] for k in meshes if k.endswith("_vertices") and k != "body_vertices"
    )
    surfaces = TrueSurfaces(meshes, layers)
    seen = ~tracks.pixels[..., 0].isnan()  # (T, N)
    canon = np.full((*seen.shape, 3), np.nan)
    owner = np.full(seen.shape, -1)
    for f in data.train:  # each frame's tracks against its true surfaces at once
        rows_f = torch.nonzero(seen[:, int(f)]).squeeze(1)
        if len(rows_f):
            canon[rows_f, int(f)], owner[rows_f, int(f)] = surfaces.hits(
                int(data.frame_ids[f]), frame_camera(data.camera, int(f)), tracks.pixels[rows_f, int(f)]
            )
    rows = []
    for t in range(tracks.count):
        frames = torch.nonzero(seen[t]).squeeze(1).tolist()
        first = min(frames, key=lambda f: int(data.frame_ids[f]))
        for f in frames:
            if f == first:
                continue
            same = owner[t, first] >= 0 and owner[t, first] == owner[t, f]
            rows.append({"gap": abs(int(data.frame_ids[f]) - int(data.frame_ids[first])), "same": bool(same),
                         "layer": layers[owner[t, first]] if owner[t, first] >= 0 else "none",
                         "error_mm": float(np.linalg.norm(canon[t, first] - canon[t, f])) * 1000})  # fmt: skip
    every = pd.DataFrame(rows)
    out = []
    for lo, hi in GAPS:
        sel = every[(every.gap >= lo) & (every.gap <= hi)]
        if not len(sel):
            continue
        hit = sel[sel.same]
        out.append({"subject": args.subject, "gap_frames": f"{lo}-{hi}" if hi < 1000 else f"{lo}+", "pairs_read": len(sel),
                    "same_layer": round(float(sel.same.mean()), 4),
                    "layers": " ".join(f"{n}:{c}" for n, c in sel.layer.value_counts().items()),
                    "error_median_mm": round(float(hit.error_mm.median()), 2),
                    "error_mean_mm": round(float(hit.error_mm.mean()), 2),
                    "error_p90_mm": round(float(hit.error_mm.quantile(0.9)), 2),
                    "tracks": tracks.count, "resolution": args.resolution})  # fmt: skip
    table = save_table(pd.DataFrame(out), args.csv, args.append)
    print(table.to_string(index=False))


if __name__ == "__main__":
    main()
