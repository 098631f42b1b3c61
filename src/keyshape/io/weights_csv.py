"""Weights CSV: header ``frame,time,<name>,...``, one row per frame; empty cell = no estimate."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..containers import Weights
from ..exceptions import InputError
from .atomic import atomic_path, existing_file

__all__ = ["save_weights_csv", "load_weights_csv"]


def _cell(value: float) -> str:
    return "" if np.isnan(value) else f"{value:.6f}"


def save_weights_csv(weights: Weights, path: str | Path) -> Path:
    """Write ``weights`` as CSV (times in seconds at ``weights.fps``), atomically."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["frame", "time", *weights.names])
        for f, (t, row) in enumerate(zip(weights.times, weights.values)):
            out.writerow([f, f"{t:.6f}", *map(_cell, row)])
    return Path(path)


def load_weights_csv(path: str | Path) -> Weights:
    """Read a weights CSV; the frame rate is recovered from the time column."""
    path = existing_file(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc.__class__.__name__})") from None
    if not rows or rows[0][:2] != ["frame", "time"] or len(rows[0]) < 3:
        raise InputError(f"{path}: expected a header 'frame,time,<name>,...'")
    names = rows[0][2:]
    try:
        table = np.array([[float(c) if c else np.nan for c in r] for r in rows[1:] if r], dtype=float)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    if table.ndim != 2 or table.shape[0] < 1 or table.shape[1] != len(names) + 2:
        raise InputError(f"{path}: every row needs {len(names) + 2} columns")
    times = table[:, 1]
    span = times[-1] - times[0]
    if len(times) > 1 and not span > 0:
        raise InputError(f"{path}: the time column must increase")
    fps = (len(times) - 1) / span if len(times) > 1 else 30.0
    return Weights(table[:, 2:], names, fps)
