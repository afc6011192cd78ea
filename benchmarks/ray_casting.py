"""First-hit ray casting against a body mesh: Embree against the binned torch search, as CSV.

The rays are a camera's (pinhole: one origin; orthographic: one direction) through the body's box, the
mesh the workflow's upsampled body (``resources/body/anny_sub1.npz``, 110k faces). Each row is the median
wall time of ``--repeats`` calls: "fresh" moves the mesh before every call (a training step's posed mesh,
so Embree builds its scene every time), "built" casts again against the same mesh tensors (a whole image's
chunks: Embree's scene is kept). ``auto`` is what ``ray_mesh_hits`` chooses (``TORCH_RAYS``).

    python benchmarks/ray_casting.py --out benchmarks/ray_casting.csv
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import device_name, save_table  # noqa: E402

from delta.body.model import load_body_model  # noqa: E402
from delta.geometry import raymesh  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def camera_rays(lo: torch.Tensor, hi: torch.Tensor, n: int, camera: str, gen: torch.Generator):
    """(n, 3) origins and unit directions of a pinhole (one centre 3 m in front) or an orthographic camera
    (one direction), aimed at points spread over the box [lo, hi]."""
    target = lo + (hi - lo) * torch.rand(n, 3, generator=gen)
    if camera == "pinhole":
        origins = torch.tensor([0.0, float(lo[1] + hi[1]) / 2, 3.0]).expand(n, 3).clone()
        dirs = target - origins
    else:
        origins = torch.cat([target[:, :2], torch.full((n, 1), 3.0)], 1)
        dirs = torch.tensor([0.0, 0.0, -1.0]).expand(n, 3).clone()
    return origins, dirs / dirs.norm(dim=1, keepdim=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--body", default=str(ROOT / "resources/body/anny_sub1.npz"))
    ap.add_argument("--rays", type=int, nargs="+", default=[128, 1024, 4096, 8192, 16384, 32768])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    body = load_body_model(a.body)
    verts, faces = body.v_template.float(), body.faces
    lo, hi = verts.amin(0), verts.amax(0)
    gen = torch.Generator().manual_seed(0)
    rows = []
    for camera in ("pinhole", "orthographic"):
        for n in a.rays:
            origins, dirs = camera_rays(lo, hi, n, camera, gen)
            reference = raymesh.ray_mesh_hits(verts, faces, origins, dirs, backend="embree").face
            for mesh in ("fresh", "built"):
                for backend in ("embree", "torch", "auto"):
                    times = []
                    for r in range(a.repeats + 1):
                        v = verts + 1e-6 * (r + 1) if mesh == "fresh" else verts
                        start = time.perf_counter()
                        hits = raymesh.ray_mesh_hits(v, faces, origins, dirs, backend=backend)
                        times.append(time.perf_counter() - start)
                    seconds = sorted(times[1:])[len(times[1:]) // 2]  # the first call builds what "built" keeps
                    rows.append({"camera": camera, "rays": n, "mesh": mesh, "backend": backend,
                                 "seconds": round(seconds, 4), "faces": int(faces.shape[0]),
                                 "same_face_as_embree": float((hits.face == reference).float().mean()),
                                 "device": device_name("cpu", a.threads)})  # fmt: skip
                    print(rows[-1], flush=True)
    save_table(pd.DataFrame(rows), a.out, append=a.append)


if __name__ == "__main__":
    main()
