"""Key files (JSON): the neutral frame and, per region, its landmark indices and key shapes.

A person can read it: names, source take and frame come first; the aligned landmark
positions (neutral, and each key within its region) come last, so ``solve`` can use the
key set on any take of the same actor. A mirrored key (its source key's shape reflected through
the face's symmetry plane) names its source in ``mirror_of`` and carries the source's frame::

    {"format": "keyshape-keys", "version": 1, "method": "spa",
     "n_landmarks": 478, "n_dims": 3, "neutral": {"take": "a.npz", "frame": 12},
     "regions": {"upper": {"indices": [...], "keys": [{"name": "upper_00", "take": "a.npz", "frame": 87},
                                                      {"name": "upper_00_mirror", "take": "a.npz", "frame": 87,
                                                       "mirror_of": "upper_00"}]}},
     "stable": [...], "shapes": {"neutral": [[x, y, z], ...], "upper_00": [[x, y, z], ...]}}
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..containers import KeyShapes
from ..exceptions import InputError
from .atomic import atomic_path, existing_file
from .validate import check_keys_data

__all__ = ["save_keys", "load_keys", "keys_to_dict", "keys_from_dict"]

FORMAT = "keyshape-keys"


def _rounded(points: np.ndarray) -> list:
    return np.round(points, 4).tolist()


def _key_entry(keys: KeyShapes, k: int) -> dict:
    entry = {"name": keys.names[k], "take": keys.takes[k], "frame": int(keys.frames[k])}
    if keys.mirror_of[k]:
        entry["mirror_of"] = keys.mirror_of[k]  # its frame is the source key's frame
    return entry


def keys_to_dict(keys: KeyShapes) -> dict:
    """The JSON-ready form of ``keys``."""
    regions = {}
    for region, indices in keys.regions.items():
        regions[region] = {
            "indices": indices.tolist(),
            "keys": [_key_entry(keys, k) for k in keys.keys_of(region)],
        }
    shapes = {"neutral": _rounded(keys.neutral)}
    for k, name in enumerate(keys.names):
        idx = keys.regions[keys.key_regions[k]]
        shapes[name] = _rounded(keys.neutral[idx] + keys.deltas[k, idx])
    return {
        "format": FORMAT, "version": 1, "method": keys.method,
        "n_landmarks": keys.n_landmarks, "n_dims": keys.n_dims,
        "neutral": {"take": keys.neutral_take, "frame": int(keys.neutral_frame)},
        "regions": regions,
        "stable": None if keys.stable is None else keys.stable.tolist(),
        "shapes": shapes,
    }


def keys_from_dict(data: dict) -> KeyShapes:
    """Inverse of :func:`keys_to_dict`."""
    neutral = np.asarray(data["shapes"]["neutral"], dtype=float)
    names, frames, takes, key_regions, deltas, mirror_of = [], [], [], [], [], []
    regions = {}
    for region, spec in data["regions"].items():
        idx = np.asarray(spec["indices"], dtype=int)
        regions[region] = idx
        for key in spec["keys"]:
            delta = np.zeros_like(neutral)
            delta[idx] = np.asarray(data["shapes"][key["name"]], dtype=float) - neutral[idx]
            names.append(key["name"])
            frames.append(int(key["frame"]))
            takes.append(str(key.get("take", "")))
            key_regions.append(region)
            deltas.append(delta)
            mirror_of.append(str(key.get("mirror_of") or ""))
    return KeyShapes(neutral, np.array(deltas).reshape(-1, *neutral.shape), tuple(names),
                     np.array(frames, dtype=int), tuple(key_regions), regions, tuple(takes),
                     int(data["neutral"]["frame"]), str(data["neutral"].get("take", "")),
                     str(data.get("method", "")), data.get("stable"), tuple(mirror_of))


def save_keys(keys: KeyShapes, path: str | Path) -> Path:
    """Write ``keys`` as JSON, atomically."""
    text = json.dumps(keys_to_dict(keys), indent=1)
    with atomic_path(path) as tmp:
        tmp.write_text(text + "\n")
    return Path(path)


def load_keys(path: str | Path) -> KeyShapes:
    """Read a key file written by ``keyshape keys``."""
    path = existing_file(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))  # a BOM is no JSON error
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: not a readable JSON key file ({exc.__class__.__name__})") from None
    check_keys_data(path, data)
    try:
        return keys_from_dict(data)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: malformed key file ({exc.__class__.__name__}: {exc})") from None
