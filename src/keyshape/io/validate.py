"""One validator per file format keyshape reads: track ``.npz``, ``keys.json``, ``weights.csv``,
``take.json``, the header of a ``.glb`` and every cross-reference of a glTF document.

Each reader in :mod:`keyshape.io` calls its validator before it builds a core type, so every
verb that reads a format checks it the same way, and a broken file is one line naming the file,
the field and the bad value (an :class:`~keyshape.exceptions.InputError`), never a traceback
from deep inside the numerics.
"""

from __future__ import annotations

import csv
import io
import math
import re
import struct
from pathlib import Path

import numpy as np

from ..exceptions import InputError

__all__ = ["check_track_arrays", "check_keys_data", "check_weights_table", "check_take_info", "check_glb",
           "check_gltf_document", "check_weight_values", "MAX_COORDINATE", "MAX_WEIGHT", "MAX_GAIN", "MAX_FPS",
           "TRACK_FORMAT_VERSION"]

MAX_COORDINATE = 1e6  # |landmark coordinate| in pixels: beyond it a track is corrupt, not a face
MAX_WEIGHT = 5.0  # a weight above it is no blend of key shapes (solve writes 0 <= w <= --max)
MAX_FRAME = 10**12  # a source frame number beyond it is corrupt (ten years at 1000 frames a second)
MAX_TIME = 1e9  # |time| in seconds: beyond it a take's clock is corrupt
MAX_FPS = 1000.0  # frames a second: capture times frames in whole milliseconds
TRACK_FORMAT_VERSION = 1  # the newest track file layout this keyshape reads (and writes)
FILE_VERSION = 1  # the newest "version" of keys.json and take.json this keyshape reads (and writes)
MAX_GAIN = 100.0  # |gain| of a key on a target (map.json): beyond it no weight <= MAX_WEIGHT comes of a key's


def _fail(path, field: str, text: str) -> InputError:
    """``PATH: FIELD must ...`` or ``PATH: FIELD: what is wrong``."""
    return InputError(f"{path}: {field} {text}" if text.startswith("must") else f"{path}: {field}: {text}")


def _show(value) -> str:
    text = repr(value.item() if isinstance(value, np.generic) else value)
    return text if len(text) <= 60 else text[:57] + "..."


# -- track .npz ---------------------------------------------------------------------------------

def check_track_arrays(path, arrays: dict[str, np.ndarray], *, points_values: bool = True) -> None:
    """Check the arrays of a track file: ``points (n_frames, n_landmarks, 2|3)`` finite or NaN
    frames, at least one face, within ±:data:`MAX_COORDINATE`; ``fps`` > 0; the optional
    ``frame_index``, ``time``, ``image_size``, ``blendshapes``, ``blendshape_names`` and
    ``head_matrix`` of matching shapes.

    ``points_values=False`` checks the points' shape and type only: a reader that streams the
    points checks their values chunk by chunk as it reads them (:class:`PointsCheck`)."""
    missing = {"points", "fps"} - set(arrays)
    if missing:
        raise InputError(f"{path}: track file lacks {sorted(missing)} (needs 'points' and 'fps')")
    points = arrays["points"]
    if not _numeric(points) or points.ndim != 3 or points.shape[2] not in (2, 3) or 0 in points.shape[:2]:
        raise _fail(path, "points", f"must have shape (n_frames, n_landmarks, 2 or 3), numbers; got "
                                    f"{points.shape} {points.dtype}")
    _check_fps(path, arrays["fps"])
    if "format_version" in arrays:
        _check_track_version(path, arrays["format_version"])
    n = points.shape[0]
    if "frame_index" in arrays:
        _check_increasing(path, "frame_index", arrays["frame_index"], n, integer=True)
    if "time" in arrays:
        _check_increasing(path, "time", arrays["time"], n, integer=False)
    scored = _check_track_extras(path, arrays, n)
    if points_values:
        _check_points_values(path, points, scored)


def _numeric(array: np.ndarray) -> bool:
    return np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)


_CHECK_FRAMES = 4096  # frames checked at a time: the temporaries stay small however long the take


def _check_points_values(path, points: np.ndarray, scored: np.ndarray | None = None) -> None:
    check = PointsCheck(path, scored)
    for lo in range(0, points.shape[0], _CHECK_FRAMES):
        check.add(lo, points[lo : lo + _CHECK_FRAMES])
    check.finish()


class PointsCheck:
    """The values check of a track's points, fed a chunk of frames at a time, in order.

    :meth:`add` returns each chunk's faces (frames all finite); :meth:`finish` raises what the
    whole array would have: a non-finite value that is not NaN first, then a coordinate beyond
    ±:data:`MAX_COORDINATE`, then a take without a face (the first frame of each, in order), then
    a frame with a face but no scores, when ``scored`` (n_frames,) bool (the frames whose
    ``blendshapes`` are finite, :func:`blendshape_rows`) is given.
    """

    def __init__(self, path, scored: np.ndarray | None = None):
        self.path, self.bad, self.large, self.faces, self.n_frames = path, None, None, 0, 0
        self.scored, self.unscored = scored, None

    @staticmethod
    def extremes(chunk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The ``(n,)`` largest and smallest values of each frame of ``chunk (n, n_landmarks, d)``
        (NaN or ±inf where a frame is not all finite), as :meth:`add` needs them."""
        flat = _as_float(chunk).reshape(len(chunk), -1)
        return flat.max(axis=1), flat.min(axis=1)

    def add(self, lo: int, chunk: np.ndarray, extremes: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(n,) bool, the frames of ``chunk (n, n_landmarks, d)`` (frames ``lo``...) with a face;
        ``extremes``: :meth:`extremes` of ``chunk``, if the caller has them already."""
        flat = _as_float(chunk).reshape(len(chunk), -1)
        high, low = self.extremes(chunk) if extremes is None else extremes
        face = np.isfinite(high) & np.isfinite(low)
        if self.scored is not None and self.unscored is None:
            missing = np.flatnonzero(face & ~self.scored[lo : lo + len(face)])
            if missing.size:
                self.unscored = lo + int(missing[0])
        self.faces += int(face.sum())
        self.n_frames += len(face)
        rest = np.flatnonzero(~face)  # frames without a face, or partly finite: looked at closely
        if self.bad is None and rest.size:
            bad = np.isinf(flat[rest])
            if bad.any():
                row, col = np.argwhere(bad)[0]
                self.bad = (lo + int(rest[row]), flat[rest[row], col])
        if self.large is None and self.bad is None:
            extreme = max(float(high[face].max(initial=0.0)), -float(low[face].min(initial=0.0)))
            if rest.size:  # partly finite frames count too (fmax/fmin skip NaN)
                extreme = max(extreme, float(np.fmax.reduce(np.abs(flat[rest]), axis=None)))
            if extreme > MAX_COORDINATE:
                large = np.isfinite(flat) & (np.abs(flat) > MAX_COORDINATE)
                row, col = np.argwhere(large)[0]
                self.large = (lo + int(row), flat[row, col])
        return face

    def finish(self) -> None:
        if self.bad is not None:
            raise _fail(self.path, "points", f"frame {self.bad[0]} holds {_show(self.bad[1])} (missing faces are NaN)")
        if self.large is not None:
            raise _fail(self.path, "points", f"frame {self.large[0]} holds {self.large[1]:.3g}, beyond "
                                             f"±{MAX_COORDINATE:g} pixels")
        if not self.faces:
            raise _fail(self.path, "points", f"no frame has a face (all {self.n_frames} frames are NaN)")
        if self.unscored is not None:
            raise _fail(self.path, "blendshapes", f"frame {self.unscored} has a face but no scores (NaN): the "
                                                  "tracker scores every frame it finds a face in")


def _as_float(chunk: np.ndarray) -> np.ndarray:
    return chunk if chunk.dtype.kind == "f" else chunk.astype(float)  # float32 tracks: no copy


def _check_fps(path, fps) -> None:
    fps = np.asarray(fps)
    if fps.size != 1 or not _numeric(fps) or not math.isfinite(float(fps.reshape(-1)[0])) \
            or not float(fps.reshape(-1)[0]) > 0:
        raise _fail(path, "fps", f"must be a positive number; got {_show(fps.tolist())}")
    if float(fps.reshape(-1)[0]) > MAX_FPS:
        raise _fail(path, "fps", f"must be at most {MAX_FPS:g} frames a second (frames are timed in whole "
                                 f"milliseconds); got {float(fps.reshape(-1)[0]):g}")


def _check_track_version(path, version) -> None:
    version = np.asarray(version)
    if version.shape != () or not np.issubdtype(version.dtype, np.integer) or not 1 <= int(version):
        raise _fail(path, "format_version", f"must be a whole number >= 1; got {_show(version.tolist())}")
    if int(version) > TRACK_FORMAT_VERSION:
        raise _fail(path, "format_version", f"{int(version)} is newer than this keyshape reads "
                                            f"({TRACK_FORMAT_VERSION}): a newer keyshape wrote it")


def _check_version(path, data: dict) -> None:
    """A ``"version"`` (of keys.json, take.json), where given: a whole number this keyshape reads."""
    version = data.get("version", 1)
    _whole(path, "version", version, low=1)
    if version > FILE_VERSION:
        raise _fail(path, "version", f"{version} is newer than this keyshape reads ({FILE_VERSION}): a newer "
                                     "keyshape wrote it")


def _check_increasing(path, name: str, values, n: int, *, integer: bool) -> None:
    values = np.asarray(values)
    kind = "whole numbers" if integer else "numbers"
    ok_type = np.issubdtype(values.dtype, np.integer) if integer else _numeric(values)
    if not ok_type or values.shape != (n,):
        raise _fail(path, name, f"must be {n} {kind} (one per frame); got {values.shape} {values.dtype}")
    v = values.astype(float)
    with np.errstate(invalid="ignore"):
        out = ~np.isfinite(v) | ((v < 0) | (v > MAX_FRAME) if integer else np.abs(v) > MAX_TIME)
    if out.any():
        i = int(np.flatnonzero(out)[0])
        raise _fail(path, name, f"frame {i} holds {_show(values[i])}")
    steps = np.flatnonzero(np.diff(v) <= 0)
    if steps.size:
        i = int(steps[0]) + 1
        raise _fail(path, name, f"must increase from frame to frame; frame {i} holds {_show(values[i])} "
                                f"after {_show(values[i - 1])}")


def _check_track_extras(path, arrays: dict, n: int) -> np.ndarray | None:
    """Check the optional arrays; returns the (n,) bool frames with scores (None without scores)."""
    size = arrays.get("image_size")
    if size is not None and (size.shape != (2,) or not np.issubdtype(size.dtype, np.integer) or (size <= 0).any()):
        raise _fail(path, "image_size", f"must be (width, height) > 0; got {_show(size.tolist())}")
    scores, scored = arrays.get("blendshapes"), None
    if scores is not None:
        if not _numeric(scores) or scores.ndim != 2 or scores.shape[0] != n:
            raise _fail(path, "blendshapes", f"must have shape ({n}, n_scores); got {scores.shape}")
        scored = blendshape_rows(path, scores)
    names = arrays.get("blendshape_names")
    if names is not None and (names.ndim != 1 or names.dtype.kind not in "US"
                              or (scores is not None and names.shape != (scores.shape[1],))):
        count = "the scores" if scores is None else f"the {scores.shape[1]} scores"
        raise _fail(path, "blendshape_names", f"must be strings naming {count}; got {names.shape} {names.dtype}")
    matrix = arrays.get("head_matrix")
    if matrix is not None and (not _numeric(matrix) or matrix.shape != (n, 4, 4)):
        raise _fail(path, "head_matrix", f"must have shape ({n}, 4, 4); got {matrix.shape}")
    seen = arrays.get("visibility")
    if seen is not None and (not _numeric(seen) or seen.shape != (n, arrays["points"].shape[1])
                             or not _within(seen, 0.0, 1.0)):
        raise _fail(path, "visibility", f"must be (n_frames, n_landmarks) = ({n}, {arrays['points'].shape[1]}) "
                                        f"values in [0, 1]; got shape {seen.shape}")
    return scored


def blendshape_rows(path, scores: np.ndarray) -> np.ndarray:
    """The ``(n_frames,)`` bool frames of ``scores (n_frames, n_scores)`` that have scores: each
    frame's scores are all in ``[0, 1]`` (the tracker's probabilities) or all NaN (no face);
    else InputError naming the first bad frame."""
    values = _as_float(scores)
    finite = np.isfinite(values)
    scored = finite.all(axis=1)
    partial = np.flatnonzero(~scored & (finite.any(axis=1) | np.isinf(values).any(axis=1)))
    if partial.size:
        i = int(partial[0])
        bad = values[i][~np.isfinite(values[i])][0]
        raise _fail(path, "blendshapes", f"frame {i} holds {_show(bad)} among its scores (a frame without a "
                                         "face has all its scores NaN)")
    if scored.any() and not _within(values[scored], 0.0, 1.0):
        outside = scored[:, None] & ((values < 0.0) | (values > 1.0))
        i, j = (int(k) for k in np.argwhere(outside)[0])
        raise _fail(path, "blendshapes", f"frame {i} holds {values[i, j]:.3g}; scores are in [0, 1]")
    return scored


def _within(values: np.ndarray, low: float, high: float) -> bool:
    """Every value in ``[low, high]`` (NaN is not): two reductions, no temporary the size of ``values``."""
    return bool(values.size == 0 or (values.min() >= low and values.max() <= high))


# -- keys.json ----------------------------------------------------------------------------------

def check_keys_data(path, data) -> None:
    """Check a key file's JSON: landmark counts, the neutral, every region's indices and keys
    (unique names, whole frame numbers >= 0, an optional ``mirror_of`` naming another key), and
    one finite shape per key of its region's size."""
    if not isinstance(data, dict) or data.get("format") != "keyshape-keys":
        raise InputError(f"{path}: not a keyshape key file (expected \"format\": \"keyshape-keys\")")
    _check_version(path, data)
    missing = [name for name in _KEYS_FIELDS if name not in data]
    if missing:
        raise InputError(f"{path}: a key file needs {', '.join(map(repr, _KEYS_FIELDS))}; it lacks "
                         f"{', '.join(map(repr, missing))}")
    n_landmarks = _whole(path, "n_landmarks", data.get("n_landmarks"), low=1)
    n_dims = data.get("n_dims")
    if n_dims not in (2, 3) or isinstance(n_dims, bool):
        raise _fail(path, "n_dims", f"must be 2 or 3; got {_show(n_dims)}")
    neutral = data.get("neutral")
    if not isinstance(neutral, dict):
        raise _fail(path, "neutral", f"must be {{\"frame\": N, \"take\": ...}}; got {_show(neutral)}")
    _whole(path, "neutral.frame", neutral.get("frame"), low=0)
    shapes = data.get("shapes")
    if not isinstance(shapes, dict):
        raise _fail(path, "shapes", f"must map names to landmark lists; got {_show(shapes)}")
    _check_shape(path, "shapes.neutral", shapes.get("neutral"), n_landmarks, n_dims)
    names = _check_regions(path, data.get("regions"), shapes, n_landmarks, n_dims)
    stable = data.get("stable")
    if stable is not None:
        _indices(path, "stable", stable, n_landmarks)
    _check_mirrors(path, data["regions"], names)


_KEYS_FIELDS = ("n_landmarks", "n_dims", "neutral", "regions", "shapes")  # what keys_to_dict always writes


def _whole(path, field: str, value, *, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise _fail(path, field, f"must be a whole number >= {low}; got {_show(value)}")
    return value


def _indices(path, field: str, value, n_landmarks: int) -> list[int]:
    if not isinstance(value, list) or not value:
        raise _fail(path, field, f"must be a non-empty list of landmark indices; got {_show(value)}")
    for i in value:
        if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < n_landmarks:
            raise _fail(path, field, f"landmark indices must be whole numbers in 0..{n_landmarks - 1}; "
                                     f"got {_show(i)}")
    if len(set(value)) != len(value):
        raise _fail(path, field, "lists a landmark twice")
    return value


def _check_shape(path, field: str, value, n_points: int, n_dims: int) -> None:
    try:
        shape = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise _fail(path, field, f"must be {n_points} points of {n_dims} numbers; got {_show(value)}") from None
    if shape.shape != (n_points, n_dims):
        raise _fail(path, field, f"must be {n_points} points of {n_dims} numbers; got shape {shape.shape}")
    if not np.isfinite(shape).all() or (np.abs(shape) > MAX_COORDINATE).any():
        bad = shape[~np.isfinite(shape) | (np.abs(np.nan_to_num(shape)) > MAX_COORDINATE)][0]
        raise _fail(path, field, f"holds {_show(float(bad))} (coordinates must be finite, within "
                                 f"±{MAX_COORDINATE:g})")


def _check_regions(path, regions, shapes: dict, n_landmarks: int, n_dims: int) -> list[str]:
    if not isinstance(regions, dict) or not regions:
        raise _fail(path, "regions", f"must map region names to {{indices, keys}}; got {_show(regions)}")
    names: list[str] = []
    for region, spec in regions.items():
        field = f"regions.{region}"
        if not isinstance(spec, dict) or not isinstance(spec.get("keys"), list):
            raise _fail(path, field, f"must be {{\"indices\": [...], \"keys\": [...]}}; got {_show(spec)}")
        indices = _indices(path, f"{field}.indices", spec.get("indices"), n_landmarks)
        for i, key in enumerate(spec["keys"]):
            where = f"{field}.keys[{i}]"
            if not isinstance(key, dict) or not isinstance(key.get("name"), str) or not key["name"] \
                    or key["name"] == "neutral":
                raise _fail(path, where, f"needs a \"name\" (a non-empty string, not 'neutral'); got {_show(key)}")
            if key["name"] in names:
                raise _fail(path, f"{where}.name", f"{key['name']!r} names two keys; names must be unique")
            _whole(path, f"{where}.frame", key.get("frame"), low=0)
            if not isinstance(key.get("take", ""), str):
                raise _fail(path, f"{where}.take", f"must be a string; got {_show(key['take'])}")
            if key["name"] not in shapes:
                raise _fail(path, "shapes", f"has no shape for key {key['name']!r}")
            _check_shape(path, f"shapes.{key['name']}", shapes[key["name"]], len(indices), n_dims)
            names.append(key["name"])
    return names


def _check_mirrors(path, regions: dict, names: list[str]) -> None:
    for region, spec in regions.items():
        for i, key in enumerate(spec["keys"]):
            source = key.get("mirror_of")
            if source in (None, ""):
                continue
            if not isinstance(source, str) or source not in names or source == key["name"]:
                raise _fail(path, f"regions.{region}.keys[{i}].mirror_of",
                            f"must name another key of the file; got {_show(source)}")


# -- weights.csv --------------------------------------------------------------------------------

def check_weights_table(path, rows: list[list[str]]) -> tuple[list[str], np.ndarray]:
    """Check a weights CSV's rows (header ``frame,time,<name>,...``) and return (names, table):
    ``table (n_frames, 2 + n_channels)`` float, frames whole and increasing, times finite and
    increasing, weights empty (no estimate) or in ``0..MAX_WEIGHT``."""
    if not rows or rows[0][:2] != ["frame", "time"] or len(rows[0]) < 3:
        raise InputError(f"{path}: expected a header 'frame,time,<name>,...'")
    names = rows[0][2:]
    empty = [i for i, n in enumerate(names) if not n.strip()]
    if empty:
        raise _fail(path, "header", f"column {empty[0] + 3} has no name")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise _fail(path, "header", f"names {twice[0]!r} twice")
    body = [(i, r) for i, r in enumerate(rows[1:], start=2) if r]
    if not body:
        raise InputError(f"{path}: has a header but no rows (no frames)")
    table = np.array([_weights_row(path, line, row, names) for line, row in body], dtype=float)
    _check_increasing_column(path, "frame", table[:, 0], [line for line, _ in body])
    _check_increasing_column(path, "time", table[:, 1], [line for line, _ in body])
    return names, table


def check_weights_text(path, text: str) -> tuple[list[str], np.ndarray]:
    """:func:`check_weights_table` on a whole weights CSV's text, at numpy speed: a plain file (no
    quotes or spaces, every row complete and valid) is parsed and checked at once; anything else
    is read by the ``csv`` module and checked row by row, so its message is the same."""
    table = _plain_weights_table(text)
    if table is not None:
        return table
    try:
        rows = list(csv.reader(io.StringIO(text, newline="")))
    except csv.Error as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc.__class__.__name__})") from None
    return check_weights_table(path, rows)


_PLAIN = re.compile(r"[0-9.,+\-eE\n]*")  # numbers and separators only: no quotes, spaces, 'nan' or 'inf'


def _plain_weights_table(text: str) -> tuple[list[str], np.ndarray] | None:
    """(names, table) of a weights CSV that passes every check, else None (for the row-by-row path)."""
    head, _, body = text.replace("\r\n", "\n").partition("\n")
    names = head.split(",")[2:]
    if head.split(",")[:2] != ["frame", "time"] or not names or len(set(names)) != len(names) \
            or not all(n.strip() == n and n and '"' not in n for n in names) or not _PLAIN.fullmatch(body):
        return None
    body = "\n".join(line for line in body.split("\n") if line)  # blank lines are no rows
    if not body or any(line.count(",") != len(names) + 1 for line in body.split("\n")):
        return None
    for _ in range(2):  # empty cells -> nan (twice: runs of them share their commas)
        body = body.replace(",,", ",nan,")
    body = body.replace(",\n", ",nan\n") + ("nan" if body.endswith(",") else "")
    try:
        table = np.loadtxt(io.StringIO(body), delimiter=",", ndmin=2)
    except ValueError:
        return None
    frames, times, values = table[:, 0], table[:, 1], table[:, 2:]
    if not np.isfinite(table[:, :2]).all() or (frames < 0).any() or (frames != np.round(frames)).any() \
            or (frames > MAX_FRAME).any() or (np.abs(times) > MAX_TIME).any() \
            or (np.diff(frames) <= 0).any() or (np.diff(times) <= 0).any():
        return None
    if ((values < 0) | (values > MAX_WEIGHT)).any():  # NaN (empty) compares False
        return None
    return names, table


def _weights_row(path, line: int, row: list[str], names: list[str]) -> list[float]:
    if len(row) != len(names) + 2:
        raise _fail(path, f"line {line}", f"has {len(row)} columns; the header has {len(names) + 2}")
    frame, time = _cell(path, line, "frame", row[0]), _cell(path, line, "time", row[1])
    if frame is None or not float(frame).is_integer() or not 0 <= frame <= MAX_FRAME:
        raise _fail(path, f"line {line}, frame", f"must be a whole number in 0..{MAX_FRAME:.0e}; got {row[0]!r}")
    if time is None:
        raise _fail(path, f"line {line}, time", "is empty")
    if abs(time) > MAX_TIME:
        raise _fail(path, f"line {line}, time", f"{row[1].strip()} is beyond ±{MAX_TIME:g} seconds")
    values = []
    for name, text in zip(names, row[2:]):
        value = _cell(path, line, name, text)
        if value is not None and not 0 <= value <= MAX_WEIGHT:
            raise _fail(path, f"line {line}, {name}", f"{text.strip()} is outside 0..{MAX_WEIGHT:g} (weights "
                                                      "are >= 0; empty means no estimate)")
        values.append(np.nan if value is None else value)
    return [frame, time, *values]


def _cell(path, line: int, column: str, text: str) -> float | None:
    if not text.strip():
        return None
    try:
        value = float(text)
    except ValueError:
        raise _fail(path, f"line {line}, {column}", f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise _fail(path, f"line {line}, {column}", f"{text!r} is not a finite number (leave a cell empty "
                                                    "for no estimate)")
    return value


def _check_increasing_column(path, column: str, values: np.ndarray, lines: list[int]) -> None:
    steps = np.flatnonzero(np.diff(values) <= 0)
    if steps.size:
        i = int(steps[0]) + 1
        raise _fail(path, f"line {lines[i]}, {column}", f"{values[i]:g} does not follow {values[i - 1]:g}: rows "
                                                        "must be in increasing frame and time order")


def check_weight_values(path, names, values: np.ndarray, frames: np.ndarray | None = None) -> None:
    """The rule for weights every writer of weights (CSV, glTF, USD, Live Link, Blender) applies
    before it writes, as the weights reader does: each value of ``values (n_frames, n_channels)``
    (named ``names``) is NaN (no estimate) or finite within ``0..MAX_WEIGHT``; else InputError
    naming ``path``, the channel and the frame (``frames (n_frames,)``, default the row)."""
    values = np.asarray(values, dtype=float)
    if not values.size:
        return
    with np.errstate(invalid="ignore"):
        bad = np.isinf(values) | (values < 0) | (values > MAX_WEIGHT)
    if not bad.any():
        return
    row, col = (int(i) for i in np.argwhere(bad)[0])
    frame = row if frames is None else int(np.asarray(frames)[row])
    raise InputError(f"{path}: {list(names)[col]!r} would be written as {values[row, col]:.3g} at frame {frame}; "
                     f"weights must be finite, within 0..{MAX_WEIGHT:g} (what keyshape reads back): lower the "
                     "mapping's gains")


# -- take.json and the animation ------------------------------------------------------------------

def check_take_info(path, info) -> None:
    """Check ``take.json``: its format and, where given, ``fps`` > 0, ``n_frames`` >= 1, ``video``
    a path, ``files`` a map of names to file names, ``written`` a list of file names,
    ``neutral_frame`` and ``image_size``."""
    if not isinstance(info, dict) or info.get("format") != "keyshape-take":
        raise InputError(f"{path}: not a keyshape take description (expected \"format\": \"keyshape-take\")")
    _check_version(path, info)
    fps = info.get("fps", 1.0)  # fps and n_frames: what `run` writes; a hand-made one may name only the video
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or not fps > 0:
        raise _fail(path, "fps", f"must be a positive number; got {_show(fps)}")
    if "n_frames" in info:
        _whole(path, "n_frames", info["n_frames"], low=1)
    if info.get("neutral_frame") is not None:
        _whole(path, "neutral_frame", info["neutral_frame"], low=0)
    if info.get("video") is not None and not isinstance(info["video"], str):
        raise _fail(path, "video", f"must be the video's path; got {_show(info['video'])}")
    if info.get("neutral_source") is not None and not isinstance(info["neutral_source"], str):
        raise _fail(path, "neutral_source", f"must be the neutral image's or clip's path; got "
                                            f"{_show(info['neutral_source'])}")
    files = info.get("files", {})
    if not isinstance(files, dict) or not all(isinstance(k, str) and isinstance(v, str) and v
                                              for k, v in files.items()):
        raise _fail(path, "files", f"must map roles to file names; got {_show(files)}")
    written = info.get("written", [])
    if not isinstance(written, list) or not all(isinstance(n, str) and n for n in written):
        raise _fail(path, "written", f"must list the file names the run wrote; got {_show(written)}")
    size = info.get("image_size")
    if size is not None and (not isinstance(size, list) or len(size) != 2
                             or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)):
        raise _fail(path, "image_size", f"must be [width, height]; got {_show(size)}")


def check_glb(path: str | Path) -> Path:
    """``path`` if it starts as a glTF binary should (magic ``glTF``, version 2, the length its
    header states, a JSON chunk first); else InputError naming it."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(20)
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if len(head) < 20:
        raise InputError(f"{path}: not a glTF binary (.glb): {size} bytes")
    magic, version, length, _, chunk = struct.unpack("<4sIIII", head)
    if magic != b"glTF" or version != 2 or chunk != 0x4E4F534A:
        raise InputError(f"{path}: not a glTF 2.0 binary (.glb)")
    if length != size:
        raise InputError(f"{path}: a damaged .glb: its header says {length} bytes, the file has {size}")
    return path


_COMPONENT_SIZES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}  # BYTE ... FLOAT
_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def check_gltf_document(path, document, buffers: list[bytes]) -> None:
    """Every index a glTF document's objects give into another list (an accessor's buffer view, a
    primitive's accessors, a node's mesh and children, an animation's samplers and nodes, a
    texture's image) names an element that exists, and every accessor's bytes lie inside its view
    and every view inside its buffer; else InputError naming the file, the member and the index.

    ``document``: a :class:`pygltflib.GLTF2` or the reader's read-only parse (attribute access,
    missing members None); ``buffers``: the bytes of each buffer.

    Examples
    --------
    >>> from types import SimpleNamespace as O
    >>> doc = O(accessors=[], bufferViews=[], buffers=[], meshes=[O(primitives=[O(attributes={"POSITION": 3},
    ...         indices=None, targets=None)])], nodes=[], scenes=[], animations=[], skins=[], images=[],
    ...         textures=[], materials=[])
    >>> check_gltf_document("rig.glb", doc, [])
    Traceback (most recent call last):
    ...
    keyshape.exceptions.InputError: rig.glb: a damaged glTF: meshes[0].primitives[0].attributes.POSITION is 3, \
but the file has 0 accessors
    """
    lists = {name: list(getattr(document, name, None) or []) for name in
             ("accessors", "bufferViews", "buffers", "meshes", "nodes", "images", "textures", "samplers", "skins")}

    def ref(where: str, value, kind: str, *, optional: bool = True) -> None:
        if value is None and optional:
            return
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < len(lists[kind]):
            raise InputError(f"{path}: a damaged glTF: {where} is {_show(value)}, but the file has "
                             f"{len(lists[kind])} {kind}")

    for b, view in enumerate(lists["bufferViews"]):
        ref(f"bufferViews[{b}].buffer", getattr(view, "buffer", None), "buffers", optional=False)
        end = _int(getattr(view, "byteOffset", None)) + _int(getattr(view, "byteLength", None))
        if end > len(buffers[view.buffer]):
            raise InputError(f"{path}: a damaged glTF: bufferViews[{b}] ends at byte {end}, past the end of "
                             f"buffer {view.buffer}")
    for a, accessor in enumerate(lists["accessors"]):
        _check_accessor(path, f"accessors[{a}]", accessor, lists["bufferViews"], ref)
    for m, mesh in enumerate(lists["meshes"]):
        for p, primitive in enumerate(getattr(mesh, "primitives", None) or []):
            where = f"meshes[{m}].primitives[{p}]"
            for name, index in _members(getattr(primitive, "attributes", None)).items():
                ref(f"{where}.attributes.{name}", index, "accessors")
            ref(f"{where}.indices", getattr(primitive, "indices", None), "accessors")
            for t, target in enumerate(getattr(primitive, "targets", None) or []):
                for name, index in _members(target).items():
                    ref(f"{where}.targets[{t}].{name}", index, "accessors")
    for n, node in enumerate(lists["nodes"]):
        ref(f"nodes[{n}].mesh", getattr(node, "mesh", None), "meshes")
        ref(f"nodes[{n}].skin", getattr(node, "skin", None), "skins")
        for c, child in enumerate(getattr(node, "children", None) or []):
            ref(f"nodes[{n}].children[{c}]", child, "nodes", optional=False)
    for s, scene in enumerate(getattr(document, "scenes", None) or []):
        for k, node in enumerate(getattr(scene, "nodes", None) or []):
            ref(f"scenes[{s}].nodes[{k}]", node, "nodes", optional=False)
    for k, skin in enumerate(lists["skins"]):
        ref(f"skins[{k}].inverseBindMatrices", getattr(skin, "inverseBindMatrices", None), "accessors")
        for j, joint in enumerate(getattr(skin, "joints", None) or []):
            ref(f"skins[{k}].joints[{j}]", joint, "nodes", optional=False)
    for k, animation in enumerate(getattr(document, "animations", None) or []):
        samplers = list(getattr(animation, "samplers", None) or [])
        for s, sampler in enumerate(samplers):
            ref(f"animations[{k}].samplers[{s}].input", getattr(sampler, "input", None), "accessors", optional=False)
            ref(f"animations[{k}].samplers[{s}].output", getattr(sampler, "output", None), "accessors", optional=False)
        for c, channel in enumerate(getattr(animation, "channels", None) or []):
            index = getattr(channel, "sampler", None)
            if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(samplers):
                raise InputError(f"{path}: a damaged glTF: animations[{k}].channels[{c}].sampler is {_show(index)}, "
                                 f"but the animation has {len(samplers)} samplers")
            ref(f"animations[{k}].channels[{c}].target.node", getattr(getattr(channel, "target", None), "node", None),
                "nodes")
    for i, image in enumerate(lists["images"]):
        ref(f"images[{i}].bufferView", getattr(image, "bufferView", None), "bufferViews")
    for t, texture in enumerate(lists["textures"]):
        ref(f"textures[{t}].source", getattr(texture, "source", None), "images")


def _check_accessor(path, where: str, accessor, views: list, ref) -> None:
    """One accessor: known component type and type, a whole count, its bytes inside its view."""
    kind, shape, count = (getattr(accessor, name, None) for name in ("componentType", "type", "count"))
    if kind not in _COMPONENT_SIZES or shape not in _TYPE_WIDTHS:
        raise InputError(f"{path}: a damaged glTF: {where} has componentType {_show(kind)} and type {_show(shape)}")
    if not isinstance(count, int) or isinstance(count, bool) or count < 0:
        raise InputError(f"{path}: a damaged glTF: {where}.count is {_show(count)}")
    element = _COMPONENT_SIZES[kind] * _TYPE_WIDTHS[shape]
    parts = [(where, getattr(accessor, "bufferView", None), getattr(accessor, "byteOffset", None), count, element)]
    sparse = getattr(accessor, "sparse", None)
    if sparse is not None:
        n = getattr(sparse, "count", None)
        if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n <= count:
            raise InputError(f"{path}: a damaged glTF: {where}.sparse.count is {_show(n)}")
        indices, values = getattr(sparse, "indices", None), getattr(sparse, "values", None)
        size = _COMPONENT_SIZES.get(getattr(indices, "componentType", None))
        if size is None or values is None:
            raise InputError(f"{path}: a damaged glTF: {where}.sparse lacks its indices or values")
        ref(f"{where}.sparse.indices.bufferView", getattr(indices, "bufferView", None), "bufferViews", optional=False)
        ref(f"{where}.sparse.values.bufferView", getattr(values, "bufferView", None), "bufferViews", optional=False)
        parts += [(f"{where}.sparse.indices", indices.bufferView, getattr(indices, "byteOffset", None), n, size),
                  (f"{where}.sparse.values", values.bufferView, getattr(values, "byteOffset", None), n, element)]
    for name, view, offset, n, size in parts:
        ref(f"{name}.bufferView", view, "bufferViews")
        if view is None or n == 0:
            continue
        stride = getattr(views[view], "byteStride", None) or size
        end = _int(offset) + (n - 1) * _int(stride) + size
        if end > _int(getattr(views[view], "byteLength", None)):
            raise InputError(f"{path}: a damaged glTF: {name} needs {end} bytes of bufferViews[{view}], which has "
                             f"{_int(getattr(views[view], 'byteLength', None))}")


def _int(value) -> int:
    """A byte count or offset as an int (a missing one is 0; a negative or non-integer one too large to fit)."""
    if value is None:
        return 0
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        return 1 << 62
    return value


def _members(value) -> dict:
    """The members of a glTF object read either way (a dict, the parse's attribute-access object, a
    pygltflib dataclass), without the unset ones."""
    if value is None:
        return {}
    if isinstance(value, dict):
        members = value
    elif hasattr(value, "_members"):
        members = value._members
    else:
        members = vars(value)
    return {k: v for k, v in members.items() if v is not None}
