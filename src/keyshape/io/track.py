"""Track files (``.npz``): ``points`` (n_frames, n_landmarks, 2|3) and ``fps``, plus optional
``frame_index`` (n_frames,) source frame numbers, ``time`` (n_frames,) source times in seconds,
``image_size``, ``blendshapes`` + ``blendshape_names``, ``head_matrix`` (DESIGN.md) and
``visibility`` (n_frames, n_landmarks) in [0, 1]. Files written before ``frame_index`` and
``time`` existed still load: their frames count from 0 at ``fps``; files without ``visibility``
load as all visible. Every file read is checked by :func:`keyshape.io.validate.check_track_arrays`."""

from __future__ import annotations

import struct
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..containers import Track
from ..exceptions import InputError
from .atomic import atomic_path, existing_file
from .validate import TRACK_FORMAT_VERSION, PointsCheck, check_track_arrays

__all__ = ["save_track", "load_track", "open_track", "TrackFile"]

FORMAT_VERSION = TRACK_FORMAT_VERSION
_BLOCK_BYTES = 1 << 19  # read by TrackFile.chunks at a time: half a core's L2 cache (90 frames of 478 landmarks)


def save_track(track: Track, path: str | Path) -> Path:
    """Write ``track`` to ``path`` (.npz), atomically."""
    return write_track_arrays(path, points=track.points, fps=track.fps, image_size=track.image_size,
                              blendshapes=track.blendshapes, blendshape_names=track.blendshape_names,
                              head_matrix=track.head_matrix, frame_index=track.frame_index, time=track.time,
                              visibility=track.visibility)


def write_track_arrays(path: str | Path, *, points: np.ndarray, fps: float,
                       image_size: tuple[int, int] | None = None, blendshapes: np.ndarray | None = None,
                       blendshape_names: tuple[str, ...] = (), head_matrix: np.ndarray | None = None,
                       frame_index: np.ndarray | None = None, time: np.ndarray | None = None,
                       visibility: np.ndarray | None = None) -> Path:
    """Write track arrays (memory maps welcome: they are streamed in chunks), atomically.

    points : (n_frames, n_landmarks, 2|3); blendshapes : (n_frames, n_scores);
    head_matrix : (n_frames, 4, 4); frame_index : (n_frames,) int; time : (n_frames,) seconds;
    visibility : (n_frames, n_landmarks) in [0, 1].
    """
    arrays = {"points": points, "fps": np.float64(fps), "format_version": np.int64(FORMAT_VERSION)}
    if frame_index is not None:
        arrays["frame_index"] = np.asarray(frame_index, dtype=np.int64)
    if time is not None:
        arrays["time"] = np.asarray(time, dtype=np.float64)
    if image_size is not None:
        arrays["image_size"] = np.array(image_size, dtype=np.int64)
    if blendshapes is not None:
        arrays["blendshapes"] = blendshapes
        arrays["blendshape_names"] = np.array(blendshape_names, dtype=str)
    if head_matrix is not None:
        arrays["head_matrix"] = head_matrix
    if visibility is not None:
        arrays["visibility"] = np.asarray(visibility, dtype=np.float32)
    with atomic_path(path) as tmp:
        _write_npz(tmp, arrays)
    return Path(path)


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez`` that streams each array, so memory stays flat.

    Stored, not deflated: tracker output is noise to zlib (it saved 5-9 % of a track file and made
    reading 100,000 frames take seconds, in every verb that reads a track).

    A memory map is copied from its file in 8 MiB reads (mapping its pages in would grow the
    resident set with the array); other arrays go through numpy's chunked writer.
    """
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, array in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
                if isinstance(array, np.memmap) and array.filename and array.flags.c_contiguous:
                    _copy_memmap(fh, array)
                else:
                    np.lib.format.write_array(fh, np.asanyarray(array), allow_pickle=False)


def _copy_memmap(fh, array: np.memmap, chunk: int = 1 << 23) -> None:
    header = {"descr": np.lib.format.dtype_to_descr(array.dtype), "fortran_order": False,
              "shape": array.shape}
    np.lib.format.write_array_header_1_0(fh, header)
    with open(array.filename, "rb") as src:
        src.seek(array.offset)
        remaining = array.nbytes
        while remaining:
            data = src.read(min(remaining, chunk))
            if not data:
                raise OSError(f"{array.filename}: ended {remaining} bytes early")
            fh.write(data)
            remaining -= len(data)

def load_track(path: str | Path, *, fps: float | None = None) -> Track:
    """Read a track: a keyshape ``.npz`` (any file with ``points`` and ``fps``) or a landmark CSV.

    A CSV from another tool has the header ``frame,x0,y0[,z0],x1,y1[,z1],...`` (optionally a
    ``time`` column in seconds after ``frame``), coordinates in pixels, empty cells for frames
    without a face. Its frame rate comes from the time column, else ``fps``, else 30.
    """
    path = existing_file(path)
    if path.suffix.lower() == ".csv":
        return _load_csv_track(path, fps)
    arrays = _read_npz(path)
    check_track_arrays(path, arrays)
    size = arrays.get("image_size")
    names = arrays.get("blendshape_names")
    try:
        return Track(arrays["points"], float(np.asarray(arrays["fps"]).reshape(-1)[0]),
                     tuple(size) if size is not None else None,
                     arrays.get("blendshapes"), tuple(str(n) for n in names) if names is not None else (),
                     arrays.get("head_matrix"), arrays.get("frame_index"), arrays.get("time"),
                     arrays.get("visibility"))
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def _read_npz(path: Path, skip: str = "") -> dict[str, np.ndarray]:
    """Every array of an .npz file (but ``skip``); the file is opened here, so it is closed however it fails."""
    try:
        with open(path, "rb") as fh:
            loaded = np.load(fh, allow_pickle=False)
            if not isinstance(loaded, np.lib.npyio.NpzFile):
                raise InputError(f"{path}: not a .npz track file (it holds a single array)")
            with loaded as data:
                return {k: data[k] for k in data.files if k != skip}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error, KeyError, NotImplementedError,
            RuntimeError, TypeError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path}: not a readable .npz track file ({exc.__class__.__name__})") from None


@dataclass(frozen=True, eq=False)
class TrackFile:
    """A track file opened for one pass over its frames (:func:`open_track`).

    Every array but ``points`` is read and checked; the points are read a chunk of frames at a
    time by :meth:`chunks`, and checked as they are read, so a long take never needs a copy of
    all its landmarks in memory.

    Attributes
    ----------
    path : Path
    shape : (n_frames, n_landmarks, n_dims)
    fps : float
    frame_index, time : (n_frames,) int and float, or None (the Track defaults)
    visibility : (n_frames, n_landmarks) float32 or None
    """

    path: Path
    shape: tuple[int, int, int]
    fps: float
    frame_index: np.ndarray | None
    time: np.ndarray | None
    visibility: np.ndarray | None
    _offset: int | None
    _dtype: np.dtype
    _scored: np.ndarray | None = None  # (n_frames,) bool, the frames with blendshape scores (None: no scores)

    n_frames = property(lambda self: self.shape[0])
    n_landmarks = property(lambda self: self.shape[1])
    n_dims = property(lambda self: self.shape[2])

    def chunks(self, landmarks: np.ndarray, *, frames: int = 4096) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """``(start, face (n,) bool, points (n, n_chosen, n_dims) float)`` for successive chunks of frames.

        ``points`` holds the landmarks ``landmarks`` of frames ``start ... start + n - 1`` as float64;
        a frame without a face, or with any non-finite coordinate (of any landmark), is all NaN, as
        in a :class:`~keyshape.containers.Track`. After the last chunk the values of every frame
        have been checked as :func:`load_track` checks them; a bad file raises
        :class:`~keyshape.exceptions.InputError` there.

        A chunk is read a block of frames at a time (:data:`_BLOCK_BYTES`), each checked and its
        landmarks taken while it is in the core's cache: every value of the file is read from
        memory once.
        """
        landmarks = np.asarray(landmarks, dtype=np.intp)
        check = PointsCheck(self.path, self._scored)
        block = max(1, _BLOCK_BYTES // max(self.n_landmarks * self.n_dims * self._dtype.itemsize, 1))
        with _points_file(self.path, self._offset) as fh:
            buffer = np.empty((min(frames, self.n_frames), *self.shape[1:]), dtype=self._dtype)
            for start in range(0, self.n_frames, frames):
                raw = buffer[: min(frames, self.n_frames - start)]
                points = np.empty((len(raw), len(landmarks), self.n_dims))
                high, low = [], []
                for lo in range(0, len(raw), block):
                    part = raw[lo : lo + block]
                    _read_into(fh, part, self.path)
                    extremes = check.extremes(part)
                    high.append(extremes[0])
                    low.append(extremes[1])
                    points[lo : lo + block] = np.take(part, landmarks, axis=1)
                face = check.add(start, raw, (np.concatenate(high), np.concatenate(low)))
                points[~face] = np.nan
                yield start, face, points
        check.finish()

    def load(self) -> Track:
        """The whole take, as :func:`load_track` reads it."""
        return load_track(self.path)


def open_track(path: str | Path) -> TrackFile | None:
    """Open a keyshape ``.npz`` track for a pass over its frames (:meth:`TrackFile.chunks`).

    The file is checked as :func:`load_track` checks it, the points' values as they are read.
    None for a file whose points are not streamed (a landmark CSV, an array in Fortran order, a
    file ``np.load`` reads but this reader does not): :func:`load_track` reads (or refuses) it.
    """
    path = existing_file(path)
    if path.suffix.lower() == ".csv":
        return None
    try:
        offset, dtype, shape = _points_layout(path)
    except _NotStreamable:
        return None
    arrays = _read_npz(path, skip="points")
    arrays["points"] = np.broadcast_to(np.zeros((), dtype=dtype), shape)  # its shape and type, no data
    check_track_arrays(path, arrays, points_values=False)
    scores = arrays.get("blendshapes")
    scored = None if scores is None else np.isfinite(scores).all(axis=1)  # checked: all finite or all NaN
    return TrackFile(path, tuple(shape), float(np.asarray(arrays["fps"]).reshape(-1)[0]), arrays.get("frame_index"),
                     arrays.get("time"), arrays.get("visibility"), offset, dtype, scored)


class _NotStreamable(Exception):
    """The points of this file are read whole (by :func:`load_track`)."""


def _points_layout(path: Path) -> tuple[int | None, np.dtype, tuple[int, ...]]:
    """``(offset, dtype, shape)`` of a track file's ``points.npy``: ``offset`` is where its data
    starts in the file when the member is stored (as :func:`save_track` writes), None when it is
    deflated (read through :mod:`zipfile`). Raises :class:`_NotStreamable` for what only
    ``np.load`` reads (Fortran order, a header of another version, not a zip file)."""
    try:
        with zipfile.ZipFile(path) as zf, open(path, "rb") as raw:
            info = zf.getinfo("points.npy")
            offset = None
            if info.compress_type == zipfile.ZIP_STORED:
                raw.seek(info.header_offset)
                head = raw.read(30)  # the local file header: name and extra field lengths at 26..29
                if len(head) < 30 or head[:4] != b"PK\x03\x04":
                    raise _NotStreamable
                name_len, extra_len = struct.unpack("<HH", head[26:30])
                raw.seek(info.header_offset + 30 + name_len + extra_len)
                dtype, shape = _npy_header(raw)
                offset = raw.tell()
            else:
                with zf.open(info) as fh:
                    dtype, shape = _npy_header(fh)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError, zlib.error, struct.error) as exc:
        raise _NotStreamable from exc
    return offset, dtype, shape


def _npy_header(fh) -> tuple[np.dtype, tuple[int, ...]]:
    """``(dtype, shape)`` of the ``.npy`` data at ``fh``, which is left at the first value."""
    version = np.lib.format.read_magic(fh)
    if version not in ((1, 0), (2, 0)):
        raise _NotStreamable
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran, dtype = read(fh)
    if fortran or len(shape) != 3 or dtype.hasobject:
        raise _NotStreamable
    return dtype, shape


@contextmanager
def _points_file(path: Path, offset: int | None):
    """A binary file positioned at the first value of a track file's points."""
    if offset is not None:
        with open(path, "rb") as fh:
            fh.seek(offset)
            yield fh
    else:
        with zipfile.ZipFile(path) as zf, zf.open("points.npy") as fh:
            _npy_header(fh)
            yield fh


def _read_into(fh, array: np.ndarray, path: Path) -> None:
    """Fill the C-contiguous ``array`` from ``fh``; a file that ends early is an InputError."""
    view = memoryview(array.reshape(-1).view(np.uint8))
    done = 0
    while done < len(view):
        n = fh.readinto(view[done:])
        if not n:
            raise InputError(f"{path}: not a readable .npz track file (points end early)")
        done += n


def _csv_row(path: Path, line: int, row: list[str], header: list[str]) -> list[float]:
    """The numbers of one landmark CSV row (line ``line`` of the file), empty cells NaN; a whole
    frame number first. InputError naming the line and the column otherwise."""
    if len(row) != len(header):
        raise InputError(f"{path}: line {line}: has {len(row)} columns; the header has {len(header)}")
    values = []
    for name, text in zip(header, row, strict=True):
        try:
            values.append(float(text) if text.strip() else np.nan)
        except ValueError:
            raise InputError(f"{path}: line {line}, {name}: {text!r} is not a number") from None
    if not (np.isfinite(values[0]) and float(values[0]).is_integer()):
        raise InputError(f"{path}: line {line}, frame: must be a whole number; got {row[0]!r}")
    return values


def _csv_layout(path: Path, header: list[str]) -> tuple[int, int]:
    """(first coordinate column, n_dims) from a landmark CSV header."""
    if not header or header[0] != "frame":
        raise InputError(f"{path}: a landmark CSV needs the header frame,x0,y0[,z0],x1,...")
    first = 2 if len(header) > 1 and header[1] == "time" else 1
    n_dims = 3 if len(header) > first + 2 and header[first + 2] == "z0" else 2
    expected = [f"{a}{i}" for i in range((len(header) - first) // n_dims) for a in "xyz"[:n_dims]]
    if header[first:] != expected or not expected:
        raise InputError(f"{path}: landmark columns must be x0,y0{',z0' if n_dims == 3 else ''},x1,... "
                         f"in order; got {','.join(header[first:first + 6])}...")
    return first, n_dims


def _load_csv_track(path: Path, fps: float | None) -> Track:
    import csv

    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # a BOM (Excel's) is no header
            reader = csv.reader(fh)
            rows = [(reader.line_num, r) for r in reader if r]  # (line of the file, cells): for the messages
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc.__class__.__name__})") from None
    if len(rows) < 2:
        raise InputError(f"{path}: a landmark CSV needs a header and at least one row")
    header = rows[0][1]
    first, n_dims = _csv_layout(path, header)
    table = np.array([_csv_row(path, line, row, header) for line, row in rows[1:]]).reshape(-1, len(header))
    if first == 2 and len(table) > 1 and table[-1, 1] > table[0, 1]:
        fps = (len(table) - 1) / (table[-1, 1] - table[0, 1])
    points = table[:, first:].reshape(len(table), -1, n_dims)
    frames = table[:, 0]
    arrays = {"points": points, "fps": np.float64(fps or 30.0), "frame_index": frames.astype(np.int64)}
    if first == 2:
        arrays["time"] = table[:, 1]
    check_track_arrays(path, arrays)
    return Track(points, float(arrays["fps"]), frame_index=arrays["frame_index"], time=arrays.get("time"))
