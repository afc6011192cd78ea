"""Writing a benchmark's rows: one CSV, optionally after the rows already in it."""

from __future__ import annotations

from pathlib import Path

import pandas as pd


def save_table(table: pd.DataFrame, path: str | Path, append: bool = False) -> pd.DataFrame:
    """Write ``table`` to ``path``; with ``append``, after the rows the file already holds. Returns what
    was written."""
    path = Path(path)
    if append and path.is_file():
        table = pd.concat([pd.read_csv(path), table], ignore_index=True)
    table.to_csv(path, index=False)
    return table
