"""Figures of the report: loss curves of a training stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from delta import DeltaError
from delta.io import atomic_path


def smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Moving average over ``window`` steps (shorter at the start), same length as ``values``."""
    if window <= 1 or len(values) == 0:
        return values.astype(float)
    c = np.cumsum(np.insert(values.astype(float), 0, 0.0))
    idx = np.arange(1, len(values) + 1)
    lo = np.maximum(idx - window, 0)
    return (c[idx] - c[lo]) / (idx - lo)


def plot_losses(losses_csv: str | Path, out_png: str | Path, title: str = "") -> None:
    """Total loss and every non-zero term (log scale) and the training-ray PSNR, against the step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    try:
        df = pd.read_csv(losses_csv)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError) as e:
        raise DeltaError(f"{losses_csv}: cannot read the losses ({e})") from None
    if "step" not in df.columns or df.empty:
        raise DeltaError(f"{losses_csv}: no 'step' column or no rows; not a losses.csv of 'delta train'")
    window = max(1, len(df) // 50)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4))
    terms = [c for c in df.columns if c not in ("step", "psnr", "samples", "seconds") and (df[c].abs() > 0).any()]
    for c in terms:
        ax.plot(df["step"], smooth(df[c].to_numpy(), window), label=c, lw=2.0 if c == "loss" else 1.0)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_title("losses (moving average)")
    ax.legend(fontsize=7, ncol=2)
    if "psnr" in df.columns:
        bx.plot(df["step"], df["psnr"], color="0.8", lw=0.5)
        bx.plot(df["step"], smooth(df["psnr"].to_numpy(), window), color="C0")
    bx.set_xlabel("step")
    bx.set_ylabel("dB")
    bx.set_title("PSNR of the training rays")
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
