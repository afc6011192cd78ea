"""Where a training step's time goes: wall time per component of a stage-1 step, written as CSV.

Loads a trained stage (its occupancy grid is then active, as in all but a stage's first steps) or,
with ``--fresh``, the same model with every occupancy cell occupied (a stage's first steps), runs
``--steps`` timed training steps (forward, losses, backward; the parameters are not changed) and
times the parts by wrapping them: the kNN query of backward skinning, the skinning-weight distances,
the rest of backward skinning, the ray–mesh hits, the soft silhouette, the per-frame skinning setup
(distance grid, KD-tree), the early cull, the NeRF query and the backward pass. One row per component: seconds a
step and share of the step. Run it on a quiet machine.

    python benchmarks/step_profile.py --model results/synthetic/loose/stage1/model.pt \
        --record results/synthetic/loose/frames.h5 --out benchmarks/step_profile_loose.csv
    python benchmarks/step_profile.py ... --no-early-cull --append   # the same without the early cull

``--settings``/``--init`` start a fresh stage 1 instead of a trained one (as ``held_out_curve.py`` does,
with its ``--override``). ``--trace CSV`` also runs the steps under torch.profiler and writes, per
operator and per component (a component's row is its inclusive time), the calls, CPU and device
milliseconds a step: on a GPU, whether a part is launch-bound (CPU time >> device time) or compute-bound.

    python benchmarks/step_profile.py --settings .../stage1/settings.json --init .../init/params.npz \
        --override '{"resolution": 512}' --record ... --device cuda --out /tmp/p.csv --trace /tmp/ops.csv
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections import defaultdict
from pathlib import Path

import pandas as pd
import torch

from delta.host_memory import hold_freed_memory

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import device_name, save_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@contextlib.contextmanager
def patched(owners: list[tuple[object, str, str]], wrap):
    """Replace ``owner.name`` by ``wrap(fn, label)`` for every (owner, name, label) while inside."""
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in owners]
    for (owner, name, label), (_, _, fn) in zip(owners, saved):
        setattr(owner, name, wrap(fn, label))
    try:
        yield
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)


def timed(owners: list[tuple[object, str, str]], totals: dict, device: torch.device = torch.device("cpu")):
    """Each call of a wrapped part adds its wall time to totals[label] (on a GPU the device is
    synchronised before and after, so a part's queued kernels count as its own)."""

    def wrap(fn, label):
        def wrapper(*args, **kw):
            _sync(device)
            t = time.perf_counter()
            try:
                return fn(*args, **kw)
            finally:
                _sync(device)
                totals[label] += time.perf_counter() - t

        return wrapper

    return patched(owners, wrap)


def labelled(owners: list[tuple[object, str, str]]):
    """Each wrapped part runs in a torch.profiler ``record_function`` named by its label."""

    def wrap(fn, label):
        def wrapper(*args, **kw):
            with torch.profiler.record_function(label):
                return fn(*args, **kw)

        return wrapper

    return patched(owners, wrap)


def components(model) -> list[tuple[object, str, str]]:
    """(owner, function name, label) of the parts a step is split into."""
    from delta.deformers import knn as deformer
    from delta.geometry import distance_grid
    from delta.render import hybrid, silhouette

    return [
        (deformer, "knn", "knn query + distances"),
        (deformer, "weight_distance", "skinning-weight distances"),
        (deformer, "deform", "backward skinning (all)"),
        (deformer, "prepare", "per-frame skinning setup"),
        (distance_grid, "build", "distance grid (in the setup)"),
        (silhouette, "nearest_faces", "silhouette candidates (in the silhouette)"),
        (hybrid, "ray_mesh_hits", "ray-mesh hits"),
        (hybrid, "soft_silhouette", "soft silhouette"),
        (hybrid, "early_cull", "early cull (before the kNN)"),
        (model.nerf, "forward", "NeRF query"),
    ]


def step_fn(model, data, st, totals: dict, seed: int = 0):
    """One timed training step (forward, losses, backward; no parameter update) on a seeded frame."""
    from delta import losses as L
    from delta.data.frames import sample_rays
    from delta.training.trainer import _to, loss_terms

    g = torch.Generator().manual_seed(seed)
    dev = model.background.device

    def step():
        frame = int(data.train[torch.randint(len(data.train), (1,), generator=g)])
        batch = _to(sample_rays(data, frame, st.stage1.rays, g), dev)
        terms, r = loss_terms(model, batch, st, data.skin_color.to(dev), None, g)
        loss = L.total(terms, st.weights)
        model.zero_grad(set_to_none=True)
        _sync(dev)
        t = time.perf_counter()
        loss.backward()
        _sync(dev)
        totals["backward pass"] += time.perf_counter() - t
        return r.samples_evaluated

    return step


def profile(model, data, st, steps: int, seed: int = 0) -> tuple[pd.DataFrame, float]:
    totals: dict[str, float] = defaultdict(float)
    dev = model.background.device
    step = step_fn(model, data, st, totals, seed)
    samples = []
    for _ in range(2):  # warm up
        step()
    totals.clear()
    _sync(dev)
    t0 = time.perf_counter()
    with timed(components(model), totals, dev):
        for _ in range(steps):
            samples.append(step())
    _sync(dev)
    total = (time.perf_counter() - t0) / steps
    rows = [{"component": k, "seconds_per_step": v / steps, "share": v / steps / total} for k, v in totals.items()]
    rows.append({"component": "step", "seconds_per_step": total, "share": 1.0})
    return pd.DataFrame(rows), sum(samples) / len(samples)


def trace(model, data, st, steps: int, seed: int = 1) -> pd.DataFrame:
    """Operators and labelled components of ``steps`` steps under torch.profiler, per step."""
    from torch.profiler import ProfilerActivity

    dev = model.background.device
    step = step_fn(model, data, st, defaultdict(float), seed)
    for _ in range(2):
        step()
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with torch.profiler.profile(activities=acts) as prof, labelled(components(model)):
        for _ in range(steps):
            step()
        _sync(dev)
    labels = {label for _, _, label in components(model)}
    rows = []
    for e in prof.key_averages():
        comp = e.key in labels
        rows.append({
            "name": e.key,
            "kind": "component" if comp else "operator",
            "calls_per_step": e.count / steps,
            "cpu_ms_per_step": (e.cpu_time_total if comp else e.self_cpu_time_total) / 1e3 / steps,
            "device_ms_per_step": (e.device_time_total if comp else e.self_device_time_total) / 1e3 / steps,
        })  # fmt: skip
    # a labelled range is also listed once more as its span on the GPU's timeline (no CPU time): dropped
    table = pd.DataFrame(rows).sort_values(["kind", "cpu_ms_per_step"], ascending=[True, False])
    table = table.drop_duplicates(["name", "kind"])
    ops = table[table.kind == "operator"]
    launches = ops[ops.name.str.contains("LaunchKernel|cudaMemcpy|cudaMemset", regex=True)]
    total = {"name": "all operators", "kind": "total", "calls_per_step": ops.calls_per_step.sum(),
             "cpu_ms_per_step": ops.cpu_ms_per_step.sum(), "device_ms_per_step": ops.device_ms_per_step.sum()}  # fmt: skip
    launch = {"name": "kernel launches and copies", "kind": "total", "calls_per_step": launches.calls_per_step.sum(),
              "cpu_ms_per_step": launches.cpu_ms_per_step.sum(), "device_ms_per_step": 0.0}  # fmt: skip
    return pd.concat([pd.DataFrame([total, launch]), table], ignore_index=True)


def fresh_model(settings: str, override: str, record: str, body: str, init: str, device: str):
    """A stage-1 model from a run's settings.json (merged with ``override``), as at its first step."""
    import json
    from types import SimpleNamespace

    from delta.body.model import load_body_model
    from delta.training.presets import resolve
    from delta.training.run import build_avatar, load_init, pick_device, stage_frames

    saved = json.loads(Path(settings).read_text())
    st = resolve(saved["preset"], saved["settings"], json.loads(override))
    data = stage_frames(record, st)
    model = build_avatar(load_body_model(body), st, load_init(init, data), data, 1, pick_device(device))
    return SimpleNamespace(model=model, data=data, settings=st)


def main() -> None:
    hold_freed_memory()  # the host allocator as every delta command has it, so the clocks are the workflow's
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", help="a stage's model.pt (or --settings and --init)")
    ap.add_argument("--settings", help="a stage 1's settings.json: profile a fresh model from it")
    ap.add_argument("--init", help="with --settings: the subject's init/params.npz")
    ap.add_argument("--override", default="{}", help="with --settings: JSON settings merged over the run's")
    ap.add_argument("--record", required=True, help="the subject's frames.h5")
    ap.add_argument("--body", default=str(ROOT / "resources/body/anny_sub1.npz"))
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu", help="cpu or cuda (the model is moved there)")
    ap.add_argument("--fresh", action="store_true", help="every occupancy cell occupied (a stage's first steps)")
    ap.add_argument("--no-early-cull", action="store_true", help="every sample in a ray's span goes to the kNN query")
    ap.add_argument("--out", required=True, help="CSV to write")
    ap.add_argument("--append", action="store_true", help="add the rows to an existing --out")
    ap.add_argument("--trace", help="CSV of operators and components under torch.profiler")
    a = ap.parse_args()
    from delta.training.run import load_trained

    torch.set_num_threads(a.threads)
    if a.settings:
        tr = fresh_model(a.settings, a.override, a.record, a.body, a.init, a.device)
    elif a.model:
        tr = load_trained(a.model, a.record, a.body)
    else:
        ap.error("give --model, or --settings and --init")
    model = tr.model.to(a.device).train()
    if a.fresh and model.occupancy is not None:
        model.occupancy.reset()
    model.spec.render.early_cull = not a.no_early_cull
    table, samples = profile(model, tr.data, tr.settings, a.steps)
    table.insert(0, "model", a.model or f"fresh from {a.settings} {a.override}")
    table.insert(1, "occupancy", "all cells" if a.fresh else "trained")
    table.insert(2, "early_cull", model.spec.render.early_cull)
    table["nerf_samples_per_step"] = round(samples)
    table["threads"] = a.threads
    table["device"] = device_name(a.device, a.threads)
    print(save_table(table.round(4), a.out, a.append).to_string(index=False))
    if a.trace:
        ops = trace(model, tr.data, tr.settings, a.steps)
        ops["device"] = device_name(a.device, a.threads)
        print(save_table(ops.round(4), a.trace).head(40).to_string(index=False))


if __name__ == "__main__":
    main()
