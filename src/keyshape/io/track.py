"""Track files (``.npz``): ``points`` (n_frames, n_landmarks, 2|3) and ``fps``, plus optional
``frame_index`` (n_frames,) source frame numbers, ``time`` (n_frames,) source times in seconds,
``image_size``, ``blendshapes`` + ``blendshape_names``, ``head_matrix`` (DESIGN.md) and
``visibility`` (n_frames, n_landmarks) in [0, 1]. Files written before ``frame_index`` and
``time`` existed still load: their frames count from 0 at ``fps``; files without ``visibility``
load as all visible. Every file read is checked by :func:`keyshape.io.validate.check_track_arrays`."""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..containers import Track
from ..exceptions import InputError
from .atomic import atomic_path, existing_file
from .validate import check_track_arrays

__all__ = ["save_track", "load_track"]

FORMAT_VERSION = 1


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


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of an .npz file; the file is opened here, so it is closed however it fails."""
    try:
        with open(path, "rb") as fh:
            loaded = np.load(fh, allow_pickle=False)
            if not isinstance(loaded, np.lib.npyio.NpzFile):
                raise InputError(f"{path}: not a .npz track file (it holds a single array)")
            with loaded as data:
                return {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error, KeyError, NotImplementedError,
            RuntimeError, TypeError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path}: not a readable .npz track file ({exc.__class__.__name__})") from None


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
        with open(path, newline="") as fh:
            rows = [r for r in csv.reader(fh) if r]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc.__class__.__name__})") from None
    if len(rows) < 2:
        raise InputError(f"{path}: a landmark CSV needs a header and at least one row")
    first, n_dims = _csv_layout(path, rows[0])
    try:
        table = np.array([[float(c) if c.strip() else np.nan for c in r] for r in rows[1:]])
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    if table.ndim != 2 or table.shape[1] != len(rows[0]):
        raise InputError(f"{path}: every row needs {len(rows[0])} columns")
    if first == 2 and len(table) > 1 and table[-1, 1] > table[0, 1]:
        fps = (len(table) - 1) / (table[-1, 1] - table[0, 1])
    points = table[:, first:].reshape(len(table), -1, n_dims)
    frames = table[:, 0]
    if not (np.isfinite(frames) & (frames == np.round(frames))).all():
        raise InputError(f"{path}: frame: every row needs a whole frame number")
    arrays = {"points": points, "fps": np.float64(fps or 30.0), "frame_index": frames.astype(np.int64)}
    if first == 2:
        arrays["time"] = table[:, 1]
    check_track_arrays(path, arrays)
    return Track(points, float(arrays["fps"]), frame_index=arrays["frame_index"], time=arrays.get("time"))
