"""Writing a benchmark's rows: one CSV, optionally after the rows already in it, naming the device."""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
import torch


def save_table(table: pd.DataFrame, path: str | Path, append: bool = False) -> pd.DataFrame:
    """Write ``table`` to ``path``; with ``append``, after the rows the file already holds. Returns what
    was written."""
    path = Path(path)
    if append and path.is_file():
        table = pd.concat([pd.read_csv(path), table], ignore_index=True)
    table.to_csv(path, index=False)
    return table


def device_name(device: torch.device | str, threads: int) -> str:
    """The device a row was measured on, as the CSVs name it: the GPU's model, or the CPU's threads."""
    device = torch.device(device)
    return torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu ({threads} threads)"


def model_arguments(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of a benchmark that reads one trained avatar: the model, its record and body, the subject's name."""
    ap.add_argument("--model", required=True)
    ap.add_argument("--record", required=True)
    ap.add_argument("--body", required=True)
    ap.add_argument("--subject", required=True)
    return ap


def trained_model_arguments(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of a benchmark that scores one trained avatar by the workflow's evaluation: the model,
    its record and body, the subject's name, the splits and frames scored, rays a pixel, ST-LPIPS's folder."""
    model_arguments(ap)
    ap.add_argument("--splits", nargs="+", default=["test_view", "test_pose"])
    ap.add_argument("--max-frames", type=int, default=5)
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--perceptual-dir", default="resources/models/stlpips")
    ap.add_argument("--device", default="cpu", help="cpu or cuda: where the avatar is loaded and scored")
    return ap
