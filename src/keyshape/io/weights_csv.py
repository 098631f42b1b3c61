"""Weights CSV: header ``frame,time,<name>,...``, one row per frame (its source frame number and
time in seconds); empty cell = no estimate."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..containers import Weights
from ..exceptions import InputError
from .atomic import atomic_path, existing_file
from .validate import check_weights_text

__all__ = ["save_weights_csv", "load_weights_csv"]


_ROWS = 8192  # rows formatted at a time: one string operation each, memory bounded


def _rows(frames: np.ndarray, times: np.ndarray, values: np.ndarray) -> str:
    """CSV lines for ``values (n, n_channels)``: ``%d`` frame, ``%.6f`` time and weights, NaN empty.

    One ``%`` over a format repeated per row, so no Python call per cell."""
    line = ",".join(["%d", "%.6f"] + ["%.6f"] * values.shape[1]) + "\r\n"  # the csv module's line end
    table = np.column_stack([frames, times, values]).astype(float)
    return ((line * len(table)) % tuple(table.ravel().tolist())).replace("nan", "")


def save_weights_csv(weights: Weights, path: str | Path) -> Path:
    """Write ``weights`` as CSV, atomically: ``frame`` is the source frame number of each row and
    ``time`` its source time in seconds (``weights.frame_index`` and ``weights.time``)."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        csv.writer(fh).writerow(["frame", "time", *weights.names])
        for lo in range(0, weights.n_frames, _ROWS):
            hi = lo + _ROWS
            fh.write(_rows(weights.frame_index[lo:hi], weights.time[lo:hi], weights.values[lo:hi]))
    return Path(path)


def load_weights_csv(path: str | Path) -> Weights:
    """Read a weights CSV, checked by :func:`keyshape.io.validate.check_weights_table`; the
    frame numbers and times come from its columns, the (mean) frame rate from the times."""
    path = existing_file(path)
    try:
        with open(path, newline="") as fh:
            text = fh.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc.__class__.__name__})") from None
    names, table = check_weights_text(path, text)
    times = table[:, 1]
    fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 30.0
    return Weights(table[:, 2:], names, fps, table[:, 0].astype(np.int64), times)
