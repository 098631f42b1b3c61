"""Track files (``.npz``): ``points`` (n_frames, n_landmarks, 2|3) and ``fps``, plus optional
``image_size``, ``blendshapes`` + ``blendshape_names`` and ``head_matrix`` (DESIGN.md)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from ..containers import Track
from ..exceptions import InputError
from .atomic import atomic_path

__all__ = ["save_track", "load_track"]

FORMAT_VERSION = 1


def save_track(track: Track, path: str | Path) -> Path:
    """Write ``track`` to ``path`` (.npz), atomically."""
    arrays = {"points": track.points, "fps": np.float64(track.fps),
              "format_version": np.int64(FORMAT_VERSION)}
    if track.image_size is not None:
        arrays["image_size"] = np.array(track.image_size, dtype=np.int64)
    if track.blendshapes is not None:
        arrays["blendshapes"] = track.blendshapes
        arrays["blendshape_names"] = np.array(track.blendshape_names, dtype=str)
    if track.head_matrix is not None:
        arrays["head_matrix"] = track.head_matrix
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return Path(path)


def load_track(path: str | Path) -> Track:
    """Read a track file written by keyshape or any tool that writes ``points`` and ``fps``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f"{path}: not a readable .npz track file ({exc.__class__.__name__})") from None
    missing = {"points", "fps"} - set(arrays)
    if missing:
        raise InputError(f"{path}: track file lacks {sorted(missing)} (needs 'points' and 'fps')")
    points = arrays["points"]
    if points.ndim != 3 or points.shape[2] not in (2, 3) or points.shape[0] == 0:
        raise InputError(
            f"{path}: points must have shape (n_frames, n_landmarks, 2 or 3); got {points.shape}"
        )
    size = arrays.get("image_size")
    names = arrays.get("blendshape_names")
    try:
        return Track(points, float(arrays["fps"]), tuple(size) if size is not None else None,
                     arrays.get("blendshapes"), tuple(names) if names is not None else (),
                     arrays.get("head_matrix"))
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
