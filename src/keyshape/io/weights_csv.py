"""Weights CSV: header ``frame,time,<name>,...``, one row per frame (its source frame number and
time in seconds); empty cell = no estimate."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..containers import Weights
from ..exceptions import InputError
from .atomic import atomic_path, existing_file
from .validate import check_weights_table

__all__ = ["save_weights_csv", "load_weights_csv"]


def _cell(value: float) -> str:
    return "" if np.isnan(value) else f"{value:.6f}"


def save_weights_csv(weights: Weights, path: str | Path) -> Path:
    """Write ``weights`` as CSV, atomically: ``frame`` is the source frame number of each row and
    ``time`` its source time in seconds (``weights.frame_index`` and ``weights.time``)."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["frame", "time", *weights.names])
        for f, t, row in zip(weights.frame_index, weights.time, weights.values):
            out.writerow([int(f), f"{t:.6f}", *map(_cell, row)])
    return Path(path)


def load_weights_csv(path: str | Path) -> Weights:
    """Read a weights CSV, checked by :func:`keyshape.io.validate.check_weights_table`; the
    frame numbers and times come from its columns, the (mean) frame rate from the times."""
    path = existing_file(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc.__class__.__name__})") from None
    names, table = check_weights_table(path, rows)
    times = table[:, 1]
    fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 30.0
    return Weights(table[:, 2:], names, fps, table[:, 0].astype(np.int64), times)
