"""The CUDA path against the CPU path on a real subject: same batch, same losses and gradients; step time.

Builds the stage-1 avatar once on the CPU (float32), copies it to CUDA, renders the same rays with
the same sampling generator on both and compares every loss term and every parameter group's
gradient; then times training steps of the preset on each device. Writes one CSV row per check:

    python benchmarks/cuda_check.py --record results/synthetic/tight/frames.h5 \
        --body resources/body/anny_sub1.npz --init results/synthetic/tight/init/params.npz \
        --out benchmarks/cuda_check.csv --steps 30

``--tensor-paths`` needs no GPU: the same comparison with a GPU's code run on the CPU
(:func:`delta.devices.tensor_paths`: tensor searches, flat leaf tests, ``grid_sample``) in place of CUDA,
so a subject's whole step on a GPU's paths is checked before a GPU is at hand (the ``cuda`` column then
holds those values):

    python benchmarks/cuda_check.py --tensor-paths --settings results/synthetic/talker/stage1/settings.json \
        --record results/synthetic/talker/frames.h5 --body resources/body/anny_sub1_face.npz \
        --init results/synthetic/talker/init/params.npz --label talker --out benchmarks/device_paths_check.csv
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
import torch

from delta import losses as L
from delta.body.model import load_body_model
from delta.data.frames import sample_rays
from delta.devices import tensor_paths
from delta.training.presets import resolve
from delta.training.run import build_avatar, load_init, stage_frames
from delta.training.trainer import _to, loss_terms, train_stage

from delta.host_memory import hold_freed_memory

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402


def _terms_and_grads(model, batch, st, skin, seed):
    model.zero_grad(set_to_none=True)
    terms, _ = loss_terms(model, batch, st, skin, generator=torch.Generator().manual_seed(seed))
    L.total(terms, st.weights).backward()
    grads = {n: p.grad.detach().cpu().double() for n, p in model.named_parameters() if p.grad is not None}
    return {k: float(v.detach()) for k, v in terms.items()}, grads


def agreement(model, data, st, rays: int, seed: int = 0, paths_only: bool = False) -> list[dict]:
    """Loss terms and gradients on CPU and CUDA for one batch (``paths_only``: on the CPU with a GPU's code):
    relative differences."""
    batch = sample_rays(data, int(data.train[0]), rays, torch.Generator().manual_seed(seed))
    t_cpu, g_cpu = _terms_and_grads(copy.deepcopy(model), batch, st, data.skin_color, seed)
    if paths_only:
        with tensor_paths():
            t_gpu, g_gpu = _terms_and_grads(copy.deepcopy(model), batch, st, data.skin_color, seed)
    else:
        gpu = copy.deepcopy(model).to("cuda")
        t_gpu, g_gpu = _terms_and_grads(gpu, _to(batch, torch.device("cuda")), st, data.skin_color.cuda(), seed)
    rows = []
    for k in t_cpu:
        rows.append({"check": f"loss:{k}", "cpu": t_cpu[k], "cuda": t_gpu[k],
                     "rel_diff": abs(t_cpu[k] - t_gpu[k]) / max(abs(t_cpu[k]), 1e-12)})  # fmt: skip
    for n in g_cpu:
        a, b = g_cpu[n], g_gpu[n]
        rows.append({"check": f"grad:{n}", "cpu": float(a.norm()), "cuda": float(b.norm()),
                     "rel_diff": float((a - b).norm() / a.norm().clamp_min(1e-30))})  # fmt: skip
    return rows


def step_time(model, data, st, device: str, steps: int) -> dict:
    m = copy.deepcopy(model).to(device)
    st = copy.deepcopy(st)
    st.stage1.iterations, st.stage1.preview_every, st.stage1.checkpoint_every = steps, 0, 10**9
    with tempfile.TemporaryDirectory() as tmp:
        train_stage(1, m, data, st, Path(tmp), max_steps=3)  # warm-up (kernels, caches)
        (Path(tmp) / "checkpoint.pt").unlink(missing_ok=True)
        if device == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        res = train_stage(1, m, data, st, Path(tmp))
        if device == "cuda":
            torch.cuda.synchronize()
        sec = time.perf_counter() - t
    return {"check": f"step_seconds:{device}:{torch.get_num_threads()}threads", "cpu": float("nan"),
            "cuda": float("nan"), "rel_diff": float("nan"), "seconds_per_step": sec / steps,
            "train_psnr_last": float(res.losses.psnr.tail(5).mean())}  # fmt: skip


def render_time(model, device: str, size: int, supersample: int, frame: int) -> dict:
    """Seconds for one whole size×size image of a frame (supersample² rays a pixel), the scoring render."""
    from delta.models.image import View, render_image

    m = copy.deepcopy(model).to(device).eval()
    n = model.resolution
    view = View(size, size, (n / size, n / size))
    render_image(m, frame, view=view, supersample=1)  # warm-up
    if device == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    render_image(m, frame, view=view, supersample=supersample)
    if device == "cuda":
        torch.cuda.synchronize()
    return {"check": f"render_seconds:{device}:{size}x{size}x{supersample**2}", "cpu": float("nan"),
            "cuda": float("nan"), "rel_diff": float("nan"), "seconds_per_step": time.perf_counter() - t}  # fmt: skip


def main() -> None:
    hold_freed_memory()  # the host allocator as every delta command has it, so the clocks are the workflow's
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--record", required=True)
    p.add_argument("--body", required=True)
    p.add_argument("--init", required=True)
    p.add_argument("--preset", default="fast")
    p.add_argument(
        "--settings",
        default=None,
        help="a stage 1's settings.json (its preset, the subject's and the "
        "scene's settings) instead of the bare --preset: a head capture's expressions, layers and framing",
    )
    p.add_argument("--override", default="{}", help="JSON settings merged over the preset's or the run's")
    p.add_argument("--label", default="", help="the subject or variant, written in every row")
    p.add_argument("--out", default="benchmarks/cuda_check.csv")
    p.add_argument("--append", action="store_true", help="add the rows to an existing --out")
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--model", default=None, help="a trained stage's model.pt: also time a whole-image render")
    p.add_argument("--render-size", type=int, default=512)
    p.add_argument(
        "--cpu-threads", type=int, nargs="*", default=[2], help="CPU thread counts to time (none: CUDA only)"
    )
    p.add_argument("--tensor-paths", action="store_true", help="no GPU: a GPU's code on the CPU against the CPU's")
    a = p.parse_args()
    if not a.tensor_paths and not torch.cuda.is_available():
        raise SystemExit("cuda_check: torch sees no CUDA device")
    if a.settings:
        saved = json.loads(Path(a.settings).read_text())
        st = resolve(saved["preset"], saved["settings"], json.loads(a.override))
    else:
        st = resolve(a.preset, json.loads(a.override))
    data = stage_frames(a.record, st)
    body = load_body_model(a.body)
    torch.manual_seed(0)
    model = build_avatar(body, st, load_init(a.init, data), data, 1, torch.device("cpu"))
    rows = agreement(model, data, st, st.stage1.rays, paths_only=a.tensor_paths)
    if a.tensor_paths:
        _save(rows + [{"check": "device", "name": "cpu: its own paths against a GPU's (tensor_paths)"}], a)
        return
    rows.append(step_time(model, data, st, "cuda", a.steps))
    if a.model:
        from delta.training.run import load_trained

        trained = load_trained(a.model, a.record, a.body).model
        rows.append(render_time(trained, "cuda", a.render_size, 2, int(data.train[0])))
    for n in a.cpu_threads:
        torch.set_num_threads(n)
        rows.append(step_time(model, data, st, "cpu", a.steps))
    rows.append({"check": "device", "cpu": float("nan"), "cuda": float("nan"), "rel_diff": float("nan"),
                 "name": torch.cuda.get_device_name()})  # fmt: skip
    _save(rows, a)


def _save(rows: list[dict], a) -> None:
    df = pd.DataFrame(rows)
    df["label"] = a.label
    df = save_table(df, a.out, a.append)
    with pd.option_context("display.max_rows", 200, "display.width", 200):
        print(df.to_string(index=False))


if __name__ == "__main__":
    main()
