"""Weights CSV: header ``frame,time,<name>,...``, one row per frame (its source frame number and
time in seconds); empty cell = no estimate."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..containers import Weights
from ..exceptions import InputError
from .atomic import atomic_path, existing_file
from .validate import check_weight_values, check_weights_text

__all__ = ["save_weights_csv", "load_weights_csv"]


_CELLS = 32768  # cells formatted at a time: a temporary (8 bytes a cell) stays within 256 KB, which malloc
# serves from memory it holds (larger ones are fresh pages from the system each time, several times slower)

# A cell is written as "%d" (frame) or "%.6f" (time, weights) writes it, NaN empty, from its digits
# computed with numpy: each cell fills fixed 8-byte words of a grid (little-endian, so byte 0 is the
# first character), unused bytes 0, which are dropped at the end (bytes.translate). Rows with a cell
# this might not write as "%" does (inf, |x| ≥ 1e6, a value within rounding of a tie at the sixth
# decimal, a frame outside 0 ... 10⁸ - 1) are written by "%" itself.
_FULL = np.array([int.from_bytes(f"{i:03d}".encode(), "little") for i in range(1000)], dtype="<u8")  # "000" ... "999"
_BARE = np.array([int.from_bytes(f"{i:3d}".encode().replace(b" ", b"\0"), "little") for i in range(1000)],
                 dtype="<u8")  # the same without leading zeros: "  0", "  1" ... " 10" ... "999"
_COMMA, _MINUS, _DOT = np.uint64(ord(",")), np.uint64(ord("-") << 8), np.uint64(ord("."))
_LINE_END = np.uint64(ord("\r") | ord("\n") << 8)
_MAX_FIXED = 1e6  # |x| below this: its integer digits fit a word, and x·10⁶ is far below 2⁵³


def _digits(n: np.ndarray) -> np.ndarray:
    """The decimal digits of ``n`` (int, 0 ≤ n < 10⁸) right-aligned in 8 bytes, leading zeros 0:
    one '<u8' word per element (the first digit in the lowest byte)."""
    top, mid, low = n // 1_000_000, n // 1000 % 1000, n % 1000
    eight, sixteen, forty = np.uint64(8), np.uint64(16), np.uint64(40)
    whole = _BARE[top % 1000] >> eight | _FULL[mid] << sixteen | _FULL[low] << forty  # top: two digits at most
    return np.where(n >= 1_000_000, whole, np.where(n >= 1000, _BARE[mid] << sixteen | _FULL[low] << forty,
                                                    _BARE[low] << forty))


def _fixed(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``"," + "%.6f" % v`` of every ``v`` of ``x (n, c)`` float, NaN as ``","``: ``(n, c, 2)`` '<u8'
    words (comma, sign and integer digits; point and decimals), and the ``(n,)`` bool rows with a
    cell that "%" must write (see above)."""
    a = np.abs(x)
    q = a * 1e6  # the exact product, rounded to a float: within half an ulp of it
    r = np.rint(q)  # "%.6f" rounds the exact product half to even: r, unless q is within an ulp of a tie
    window = 0.5 - 2.0**-50 * min(float(np.fmax.reduce(q, axis=None, initial=0.0)), 1e12)  # 0.5 - 4 ulp
    with np.errstate(invalid="ignore"):
        exact = (a < _MAX_FIXED) & (np.abs(q - r) < window)
    nan, slow = None, np.zeros(len(x), dtype=bool)
    if not exact.all():
        nan = np.isnan(x)
        slow = (~exact & ~nan).any(axis=1)
        r = np.where(exact, r, 0.0)
    whole = np.floor(r / 1e6)  # exact: r is a whole number below 10¹²
    frac = (r - whole * 1e6).astype(np.int32)
    if whole.max(initial=0.0) < 10:  # one digit (weights): in the word's last byte
        first = (whole.astype("<u8") + np.uint64(ord("0"))) << np.uint64(56) | _COMMA
    else:
        first = _digits(whole.astype(np.int32)) | _COMMA
    negative = np.signbit(x) if nan is None else np.signbit(x) & ~nan
    if negative.any():
        first |= np.where(negative, _MINUS, np.uint64(0))
    words = np.empty((*x.shape, 2), dtype="<u8")
    words[..., 0] = first
    high = frac // 1000
    words[..., 1] = _DOT | _FULL[high] << np.uint64(8) | _FULL[frac - 1000 * high] << np.uint64(32)
    if nan is not None and nan.any():
        words[nan] = [_COMMA, 0]
    return words, slow


def _rows(frames: np.ndarray, times: np.ndarray, values: np.ndarray) -> str:
    """CSV lines for ``values (n, n_channels)``: ``%d`` frame, ``%.6f`` time and weights, NaN empty,
    each line ended as the csv module ends it (``\\r\\n``)."""
    n, c = values.shape
    frames, times = np.asarray(frames), np.asarray(times, dtype=float)
    grid = np.empty((n, 4 + 2 * c), dtype="<u8")  # frame, time (2 words), weights (2 each), line end
    inside = (frames >= 0) & (frames < 100_000_000)
    grid[:, 0] = _digits(np.where(inside, frames, 0).astype(np.int64))
    time_words, slow_time = _fixed(times[:, None])
    grid[:, 1:3] = time_words[:, 0]
    weights, slow = _fixed(np.asarray(values, dtype=float))
    grid[:, 3:-1] = weights.reshape(n, -1)
    grid[:, -1] = _LINE_END
    slow |= slow_time | ~inside
    line = ",".join(["%d", "%.6f"] + ["%.6f"] * c) + "\r\n"
    pieces, done = [], 0
    for i in [*np.flatnonzero(slow), n]:  # runs of rows written from the grid, each followed by one "%" writes
        pieces.append(grid[done:i].tobytes().translate(None, b"\0").decode("ascii"))
        if i < n:
            pieces.append((line % tuple(np.concatenate([[frames[i], times[i]], values[i]]).astype(float).tolist()))
                          .replace("nan", ""))
        done = i + 1
    return "".join(pieces)


def save_weights_csv(weights: Weights, path: str | Path) -> Path:
    """Write ``weights`` as CSV, atomically: ``frame`` is the source frame number of each row and
    ``time`` its source time in seconds (``weights.frame_index`` and ``weights.time``); every
    weight NaN (written empty) or within ``0..MAX_WEIGHT``, as the reader takes them
    (:func:`keyshape.io.validate.check_weight_values`)."""
    check_weight_values(path, weights.names, weights.values, weights.frame_index)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        csv.writer(fh).writerow(["frame", "time", *weights.names])
        rows = max(1, _CELLS // (weights.n_channels + 2))
        for lo in range(0, weights.n_frames, rows):
            hi = lo + rows
            fh.write(_rows(weights.frame_index[lo:hi], weights.time[lo:hi], weights.values[lo:hi]))
    return Path(path)


def load_weights_csv(path: str | Path) -> Weights:
    """Read a weights CSV, checked by :func:`keyshape.io.validate.check_weights_table`; the
    frame numbers and times come from its columns, the (mean) frame rate from the times."""
    path = existing_file(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # a BOM (Excel's) is no header
            text = fh.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc.__class__.__name__})") from None
    names, table = check_weights_text(path, text)
    times = table[:, 1]
    fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 30.0
    return Weights(table[:, 2:], names, fps, table[:, 0].astype(np.int64), times)
