"""``results/{dataset}/tradeoff.csv`` and ``tradeoff.png``: what each preset and knob buys and costs.

One row per (subject, variant): the knobs (preset, resolution, rays, samples, field backend,
iterations, culling), wall time and peak memory of each stage (the rules' benchmark files; a stage
resumed from a checkpoint is timed by the trainer's clock, which runs on across invocations),
held-out scores (the variant's evaluation), throughput (NeRF samples/s and counted FLOP/s of
a training step against the machine's measured matrix-multiply peak), whether the variant is
on the Pareto front of (total training time, held-out PSNR) for its subject, and — against the
reference variant (the paper's settings, no culling) — the speed-up to the same PSNR:

    speedup = T_reference(P) / T_variant(P),  P = the reference's final training-ray PSNR,

with T(P) the wall time at which a stage-1 run's smoothed training-ray PSNR first reaches P
(from the ``seconds`` column of its losses.csv). No ratio where it would measure step times, not
learning: a reference that gained less than ``MIN_GAIN_DB``, or a variant whose first
``PSNR_WINDOW`` steps already average P or more (a short reference run's P). Training-ray PSNR
is the proxy because held-out PSNR is only measured at the end; the held-out PSNR of both is in
the row.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from delta.eval.aggregate import benchmark_row
from delta.eval.plots import smooth
from delta.geometry.distance_grid import GRID_REACH
from delta.io import atomic_path, load_json

#: training-ray PSNR is noisy (one frame a step); this many steps are averaged
PSNR_WINDOW = 25


def hybrid_rows(losses: pd.DataFrame) -> pd.DataFrame:
    """The rows of the hybrid objective: a NeRF-only warm-up's rows (``warmup`` 1) score another render."""
    return losses[losses["warmup"] != 1] if "warmup" in losses.columns else losses


def time_to_psnr(losses: pd.DataFrame, target: float, window: int = PSNR_WINDOW) -> float:
    """Seconds until the moving-average training-ray PSNR first reaches ``target`` (nan: never);
    the clock runs from the stage's start, warm-up included, the PSNR is the hybrid render's."""
    losses = hybrid_rows(losses)
    if losses.empty or "seconds" not in losses.columns:
        return math.nan
    psnr = smooth(losses["psnr"].to_numpy(), window)
    idx = np.flatnonzero(psnr >= target)
    return float(losses["seconds"].iloc[idx[0]]) if len(idx) else math.nan


#: the reference must have climbed at least this far (dB) above its first ``PSNR_WINDOW`` steps for
#: a speed-up to mean anything: a flat curve is "reached" at every run's first step
MIN_GAIN_DB = 0.5


def start_psnr(losses: pd.DataFrame, window: int = PSNR_WINDOW) -> float:
    """Mean training-ray PSNR of the first ``window`` steps (after any warm-up)."""
    losses = hybrid_rows(losses)
    return float(losses["psnr"].iloc[:window].mean()) if not losses.empty else math.nan


def psnr_gain(losses: pd.DataFrame, window: int = PSNR_WINDOW) -> float:
    """Final smoothed training-ray PSNR minus the mean of the first ``window`` steps (after any warm-up)."""
    return final_psnr(losses, window) - start_psnr(losses, window)


def final_psnr(losses: pd.DataFrame, window: int = PSNR_WINDOW) -> float:
    losses = hybrid_rows(losses)
    return float(smooth(losses["psnr"].to_numpy(), window)[-1]) if not losses.empty else math.nan


def pareto_front(cost: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """True where no other point is at least as cheap and as good, and strictly better in one."""
    cost, gain = np.asarray(cost, float), np.asarray(gain, float)
    ok = np.isfinite(cost) & np.isfinite(gain)
    out = np.zeros(len(cost), bool)
    for i in np.flatnonzero(ok):
        dominated = ok & (cost <= cost[i]) & (gain >= gain[i]) & ((cost < cost[i]) | (gain > gain[i]))
        out[i] = not dominated.any()
    return out


def curve_time_to(seconds: np.ndarray, psnr: np.ndarray, target: float) -> float:
    """Seconds at which a held-out curve (scores of a run's snapshots, in the order trained) first reaches
    ``target``, linear between the snapshots around the crossing (nan: never). A first snapshot already at
    or above it gives that snapshot's seconds: the crossing lies before it, where nothing was scored."""
    seconds, psnr = np.asarray(seconds, float), np.asarray(psnr, float)
    hit = np.flatnonzero(psnr >= target)
    if not len(hit):
        return math.nan
    i = int(hit[0])
    if i == 0:
        return float(seconds[0])
    t0, t1, p0, p1 = seconds[i - 1], seconds[i], psnr[i - 1], psnr[i]
    return float(t0 + (t1 - t0) * (target - p0) / (p1 - p0))


def front_at(seconds: np.ndarray, psnr: np.ndarray, t: float) -> float:
    """The measured front at time ``t``: the best PSNR of any point trained for at most ``t`` seconds
    (nan: none)."""
    seconds, psnr = np.asarray(seconds, float), np.asarray(psnr, float)
    ok = np.isfinite(psnr) & (seconds <= t)
    return float(psnr[ok].max()) if ok.any() else math.nan


def knobs(settings: dict) -> dict:
    """The knobs of a trained variant, from its profile.json (preset and merged settings)."""
    raw = settings.get("settings", {})
    render = raw.get("render", {})
    return {"preset": settings.get("preset"), "resolution": raw.get("resolution"),
            "rays": raw.get("stage1", {}).get("rays"), "samples": render.get("samples"),
            "nerf_backend": raw.get("nerf", {}).get("encoding"),
            "iterations": raw.get("stage1", {}).get("iterations"),
            "max_dist": render.get("max_dist"),
            "occupancy": bool(render.get("occupancy", {}).get("enabled", False)),
            # the early cull reads the distance grid, built only when max_dist is within its reach
            "early_cull": bool(render.get("early_cull", True)) and float(render.get("max_dist", 0.0)) <= GRID_REACH}  # fmt: skip


def training_clock(losses: pd.DataFrame) -> float:
    """The trainer's clock at a stage's last step (0: none): it continues across resumes."""
    return float(losses["seconds"].iloc[-1]) if "seconds" in losses.columns and not losses.empty else 0.0


def stage_seconds(bench_s: float, clock_s: float) -> float:
    """A stage's wall time: the rule's benchmark, unless the job resumed from a checkpoint — the benchmark
    then timed only the last invocation, and the trainer's clock (every invocation's steps) is longer."""
    return round(max(bench_s, clock_s), 1)


def variant_row(subject: str, variant: str, files: dict, peak: float) -> dict:
    """``files``: summary, profile, losses1 [, losses2], bench1 [, bench2]."""
    prof = load_json(files["profile"])
    row = {"subject": subject, "variant": variant} | knobs(prof)
    total = 0.0
    curves = {k: pd.read_csv(files[f"losses{k}"]) for k in (1, 2) if f"losses{k}" in files}
    for stage in (1, 2):
        if f"bench{stage}" in files:
            b = benchmark_row(files[f"bench{stage}"])
            clock = training_clock(curves[stage])
            row[f"stage{stage}_s"], row[f"stage{stage}_max_rss_mb"] = stage_seconds(b["s"], clock), b["max_rss_mb"]
            row[f"stage{stage}_resumed"] = clock > b["s"]
            total += row[f"stage{stage}_s"]
    row["train_s"] = total
    row["stages"] = 2 if "bench2" in files else 1
    summary = load_json(files["summary"])
    scored = summary.get("convention", {}).get("resolution") or summary.get("settings", {}).get("resolution")
    row["eval_resolution"] = scored or row["resolution"]
    scores = summary.get("scores", {})
    for split, passes in scores.items():
        for name, vals in passes.items():
            tag = "_refined" if name == "refined" else ""
            for k in ("psnr", "ssim", "l1", "stlpips_alex", "nerf_iou", "body_err_mm"):
                if k in vals:
                    row[f"{split}_{k}{tag}"] = math.nan if vals[k] is None else vals[k]
    row |= {"step_s": prof["seconds"], "samples_per_step": prof["samples"], "samples_per_s": prof["samples"] / prof["seconds"],
            "flop_per_step": prof["flops"], "flop_per_s": prof["flops"] / prof["seconds"], "matmul_peak_flop_per_s": peak,
            "peak_fraction": prof["flops"] / prof["seconds"] / peak}  # fmt: skip
    row["train_psnr_start"], row["train_psnr_final"] = start_psnr(curves[1]), final_psnr(curves[1])
    row["_curve1"] = curves[1]  # for the speed-ups, once every row (and so the reference's) is known
    return row


def held_out_psnr(row: dict) -> float:
    for key in ("test_view_psnr", "test_pose_psnr", "train_psnr"):
        if key in row and not math.isnan(row[key]):
            return row[key]
    return math.nan


def tradeoff(
    manifest: dict, peak_json: str | Path, reference: str, out_csv: str | Path, out_png: str | Path
) -> pd.DataFrame:
    """``manifest``: {subject: {variant: files}} (see :func:`variant_row`)."""
    peak = float(load_json(peak_json)["flop_per_s"])
    rows = [variant_row(s, v, files, peak) for s, variants in manifest.items() for v, files in variants.items()]
    df = pd.DataFrame(rows)
    df["held_out_psnr"] = [held_out_psnr(r) for r in rows]
    df["pareto"] = False
    df["reference_psnr"] = math.nan
    df["time_to_reference_psnr_s"] = math.nan
    df["speedup_vs_reference"] = math.nan
    df["reference_gain_db"] = math.nan
    for subject, g in df.groupby("subject"):
        df.loc[g.index, "pareto"] = pareto_front(g["train_s"].to_numpy(), g["held_out_psnr"].to_numpy())
        ref = g[g["variant"] == reference]
        if ref.empty:
            continue
        target = float(ref["train_psnr_final"].iloc[0])
        ref_losses = ref["_curve1"].iloc[0]
        gain = psnr_gain(ref_losses)
        df.loc[g.index, "reference_gain_db"] = gain
        if not gain >= MIN_GAIN_DB:
            continue  # the reference did not learn in its steps: no speed-up to measure
        t_ref = time_to_psnr(ref_losses, target)
        for i in g.index:
            t = time_to_psnr(df.at[i, "_curve1"], target)
            df.loc[i, ["reference_psnr", "time_to_reference_psnr_s"]] = [target, t]
            # a run that starts at or above the target "reaches" it in its first steps: the ratio
            # would compare the reference's whole run with one step, not the time to a quality
            if t > 0 and df.at[i, "train_psnr_start"] < target:
                df.loc[i, "speedup_vs_reference"] = t_ref / t
    df = df.drop(columns="_curve1")
    with atomic_path(out_csv) as tmp:
        df.to_csv(tmp, index=False)
    plot(df, out_png)
    return df


LABEL_FONT = 7.0
"""Point size of the plot's variant labels."""
LABEL_GAP = 3.0
"""Points between a label and its point, right and up, where nothing is in the way."""


def place_labels(anchors: np.ndarray, widths: np.ndarray, height: float, gap: float = LABEL_GAP,
                 tries: int = 12) -> np.ndarray:  # fmt: skip
    """Offsets (N, 2), in points, that keep N labels' boxes apart: each label goes right of and
    above its anchor (N, 2 points) unless that box meets one already placed; then it moves down or
    up by a line at a time, alternately, up to ``tries`` lines; the highest anchors are placed first.
    """
    offsets = np.zeros((len(anchors), 2))
    placed: list[tuple[float, float, float, float]] = []
    for i in np.argsort(-anchors[:, 1], kind="stable"):
        x0 = anchors[i, 0] + gap
        for k in range(tries + 1):
            dy = gap + (height + 1.0) * ((k + 1) // 2) * (-1 if k % 2 else 1)
            box = (x0, anchors[i, 1] + dy, x0 + widths[i], anchors[i, 1] + dy + height)
            if not any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3] for b in placed):
                break
        placed.append(box)
        offsets[i] = (gap, dy)
    return offsets


def plot(df: pd.DataFrame, out_png: str | Path) -> None:
    """Held-out PSNR against training time per subject; the Pareto front joined by a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    subjects = sorted(df["subject"].unique())
    fig, axes = plt.subplots(1, len(subjects), figsize=(5.5 * len(subjects), 4.2), squeeze=False)
    for ax, subject in zip(axes[0], subjects):
        g = df[df["subject"] == subject]
        ax.scatter(g["train_s"] / 60, g["held_out_psnr"], c=np.where(g["pareto"], "C3", "C0"))
        front = g[g["pareto"]].sort_values("train_s")
        ax.plot(front["train_s"] / 60, front["held_out_psnr"], color="C3", lw=1, label="Pareto front")
        ax.set_xscale("log")
        # variants that are the same run (loose's samples_32 is its fast) share one label
        points, labels = [], []
        for (minutes, psnr), same in g.groupby([g["train_s"] / 60, "held_out_psnr"], sort=False):
            names = list(same["variant"])
            labels.append(
                " = ".join(names) if len(names) <= 3 else " = ".join(names[:2]) + f" (+{len(names) - 2} more)"
            )
            points.append((minutes, psnr))
        fig.canvas.draw()  # the axes' limits are final: data -> points
        anchors = ax.transData.transform(np.asarray(points, dtype=float)) * 72.0 / fig.dpi
        offsets = place_labels(anchors, np.array([LABEL_FONT * 0.6 * len(t) for t in labels]), LABEL_FONT + 1.0)
        for point, label, (dx, dy) in zip(points, labels, offsets):
            ax.annotate(label, point, fontsize=LABEL_FONT, xytext=(dx, dy), textcoords="offset points",
                        arrowprops={"arrowstyle": "-", "lw": 0.4, "color": "0.6"} if dy != LABEL_GAP else None)  # fmt: skip
        plain = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}")
        ax.xaxis.set_major_formatter(plain)
        ax.xaxis.set_minor_formatter(plain)
        ax.tick_params(axis="x", which="minor", labelsize=7)
        ax.set_xlabel("training time (min, both stages)")
        ax.set_ylabel("held-out PSNR (dB)")
        ax.set_title(subject)
        ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
