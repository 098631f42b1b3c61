"""Landmark schemes and axis conventions: which landmark is which, how the face splits into
regions, and how image axes become glTF axes.

Two schemes are known by landmark count:

* **MediaPipe 478** (468 without irises): tables derived from MediaPipe's
  ``FaceLandmarksConnections`` by ``tools/gen_mediapipe_scheme.py`` into
  ``data/mediapipe478.json`` (contours, regions, stable points, mesh triangles).
* **iBUG 68** (Multi-PIE 68-point markup, used by dlib, OpenFace, face-alignment):
  the standard index ranges (jaw 0–16, brows 17–26, nose 27–35, eyes 36–47, mouth 48–67).

Any other landmark count works with ``whole`` or a user REGIONS.json, and aligns on all points.

Axes: tracks live in **image axes** (x right, y down, z away from the camera, as MediaPipe);
characters and every exported file in **glTF axes** (x right, y up, z toward the viewer). The
change of basis is ``C = diag(1, −1, −1)``, its own inverse: a point maps to ``C p``
(:func:`points_to_gltf`), a rotation to ``C R C`` (:func:`rotations_to_gltf`,
:func:`head_rotations`). This module is the one place that knows it.
"""

from __future__ import annotations

import json
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np

from .exceptions import InputError

__all__ = ["REGION_SCHEMES", "resolve_regions", "stable_points", "face_triangles", "mediapipe_scheme", "eye_corners",
           "part_contours",
           "mirror_pairs",
           "IMAGE_TO_GLTF", "as_xyz", "points_to_gltf", "rotations_to_gltf", "head_rotations", "hold_valid"]

REGION_SCHEMES = ("upper-lower", "whole", "eyes")

_IBUG68 = {
    "contours": {
        "jaw": list(range(17)),
        "right_eyebrow": list(range(17, 22)),
        "left_eyebrow": list(range(22, 27)),
        "nose": list(range(27, 36)),
        "right_eye": list(range(36, 42)),
        "left_eye": list(range(42, 48)),
        "lips": list(range(48, 68)),
    },
    "stable": [36, 39, 42, 45, 27, 28, 29, 30, 0, 16],
}


@cache
def mediapipe_scheme() -> dict:
    """The MediaPipe face-mesh tables (contours, region schemes, stable ids, triangles)."""
    text = resources.files("keyshape").joinpath("data/mediapipe478.json").read_text()
    return json.loads(text)


def _ibug_regions() -> dict[str, list[int]]:
    c = _IBUG68["contours"]
    brows = c["right_eyebrow"] + c["left_eyebrow"]
    mouth = c["lips"] + c["jaw"][4:13]
    return {
        "upper-lower": {"upper": brows + c["right_eye"] + c["left_eye"], "lower": mouth},
        "eyes": {"brows": brows, "left_eye": c["left_eye"], "right_eye": c["right_eye"], "mouth": mouth},
        "whole": {"whole": list(range(68))},
    }


def _builtin_regions(name: str, n_landmarks: int) -> dict[str, list[int]]:
    if name == "whole" and n_landmarks not in (468, 478, 68):
        return {"whole": list(range(n_landmarks))}
    if n_landmarks in (468, 478):
        return mediapipe_scheme()["region_schemes"][name]
    if n_landmarks == 68:
        return _ibug_regions()[name]
    raise InputError(
        f"region scheme {name!r} needs a MediaPipe (468/478) or iBUG (68) track; this track has "
        f"{n_landmarks} landmarks: use --regions whole or a REGIONS.json"
    )


def _load_regions_file(path: Path) -> dict[str, list[int]]:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: regions file not found") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(data, dict) or not data or not all(isinstance(v, list) for v in data.values()):
        raise InputError(f"{path}: expected a JSON object mapping region names to lists of landmark indices")
    return data


def resolve_regions(spec: str | Path, n_landmarks: int) -> dict[str, np.ndarray]:
    """Region name → landmark indices for a scheme name or a REGIONS.json path.

    Parameters
    ----------
    spec : "upper-lower", "whole", "eyes", or the path of a JSON object ``{"region": [indices]}``
    n_landmarks : int, the track's landmark count

    Returns
    -------
    dict str -> (n_region_landmarks,) int, each sorted, unique and in range

    Examples
    --------
    >>> sorted(resolve_regions("upper-lower", 478))
    ['lower', 'upper']
    >>> resolve_regions("whole", 5)["whole"]
    array([0, 1, 2, 3, 4])
    """
    spec_s = str(spec)
    raw = _builtin_regions(spec_s, n_landmarks) if spec_s in REGION_SCHEMES else _load_regions_file(Path(spec_s))
    regions = {}
    for name, idx in raw.items():
        arr = np.unique(np.asarray(idx, dtype=int))
        if arr.size == 0 or arr.min() < 0 or arr.max() >= n_landmarks:
            raise InputError(
                f"region {name!r} of {spec_s}: indices must be in 0..{n_landmarks - 1} and non-empty; "
                f"got {arr.size} indices up to {arr.max() if arr.size else None}"
            )
        regions[str(name)] = arr
    return regions


def stable_points(n_landmarks: int) -> np.ndarray:
    """Landmarks that barely move with expression (eye corners, nose bridge, temples).

    Returns (n_stable,) int; all landmarks for unknown schemes.
    """
    if n_landmarks in (468, 478):
        return np.array(sorted(i for ids in mediapipe_scheme()["stable"].values() for i in ids))
    if n_landmarks == 68:
        return np.array(_IBUG68["stable"])
    return np.arange(n_landmarks)


def part_contours(n_landmarks: int) -> dict[str, np.ndarray] | None:
    """The named parts' landmark ids (``left_eye``, ``lips``, ...) of MediaPipe's 468/478 or iBUG's
    68 landmarks; None for other schemes."""
    if n_landmarks in (468, 478):
        contours = mediapipe_scheme()["contours"]
    elif n_landmarks == 68:
        contours = _IBUG68["contours"]
    else:
        return None
    return {name: np.unique(np.asarray(ids, dtype=np.int64)) for name, ids in contours.items()}


def eye_corners(n_landmarks: int) -> tuple[int, int] | None:
    """Outer eye corners (right, left) used for the inter-ocular distance, or None."""
    if n_landmarks in (468, 478):
        return 33, 263
    if n_landmarks == 68:
        return 36, 45
    return None


def mirror_pairs(n_landmarks: int) -> np.ndarray | None:
    """(n_landmarks,) int: the left-right partner of every landmark (itself on the midline), or None.

    MediaPipe's from its canonical face (``tools/gen_mediapipe_scheme.py``), iBUG 68's from the
    markup; None for other schemes (:func:`keyshape.keyshapes.find_mirror_pairs` finds one from a
    neutral shape).

    Examples
    --------
    >>> pairs = mirror_pairs(68)
    >>> int(pairs[36]), int(pairs[45]), int(pairs[30])  # outer eye corners swap; the nose tip stays
    (45, 36, 30)
    """
    if n_landmarks in (468, 478):
        return np.array(mediapipe_scheme()["mirror"][:n_landmarks], dtype=np.int64)
    if n_landmarks == 68:
        pairs = np.arange(68)
        groups = [(range(17), range(16, -1, -1)), (range(17, 22), range(26, 21, -1)),
                  ((31, 32), (35, 34)), ((36, 37, 38, 39, 40, 41), (45, 44, 43, 42, 47, 46)),
                  ((48, 49, 50, 55, 56, 60, 61, 65), (54, 53, 52, 59, 58, 64, 63, 67))]
        for left, right in groups:
            pairs[list(left)] = list(right)
            pairs[list(right)] = list(left)
        return pairs
    return None


def face_triangles() -> np.ndarray:
    """(n_faces, 3) int triangles of MediaPipe's face mesh over the first 468 landmarks."""
    return np.array(mediapipe_scheme()["triangles"], dtype=np.int64)


# --------------------------------------------------------------------------- axes

IMAGE_TO_GLTF = np.array([1.0, -1.0, -1.0])  # the diagonal of C: image (x right, y down, z away) <-> glTF


def as_xyz(points) -> np.ndarray:
    """``(..., 3)`` float: 2D points (or deltas) get z = 0."""
    points = np.asarray(points, dtype=float)
    if points.shape[-1] == 3:
        return points
    return np.concatenate([points, np.zeros(points.shape[:-1] + (1,))], axis=-1)


def points_to_gltf(points: np.ndarray) -> np.ndarray:
    """Points or displacements ``(..., d)``, d = 2 or 3, from image to glTF axes: ``C p``."""
    return points * IMAGE_TO_GLTF[: np.shape(points)[-1]]


def rotations_to_gltf(rotations) -> np.ndarray:
    """Rotations ``(n_frames, d, d)``, d = 2 or 3, in image axes -> ``(n_frames, 3, 3)`` in glTF axes.

    ``R_gltf = C R C``; a 2D rotation turns about the image z axis (the view axis). Frames that
    are not finite stay NaN.
    """
    rotations = np.asarray(rotations, dtype=float)
    if rotations.shape[1] == 2:
        full = np.tile(np.eye(3), (len(rotations), 1, 1))
        full[:, :2, :2] = rotations
        full[~np.isfinite(rotations).all(axis=(1, 2))] = np.nan
        rotations = full
    axes = np.diag(IMAGE_TO_GLTF)
    return axes @ rotations @ axes


def head_rotations(poses, *, hold: bool = False) -> np.ndarray:
    """Head rotations ``(n_frames, 3, 3)`` in glTF axes from image-space ``poses.rotations``.

    Frames without a pose are NaN, or with ``hold=True`` hold the previous valid rotation
    (:func:`hold_valid`), as the written animations do.
    """
    rotations = rotations_to_gltf(poses.rotations)
    return hold_valid(rotations) if hold else rotations


def hold_valid(rotations: np.ndarray) -> np.ndarray:
    """Rotations ``(n_frames, 3, 3)`` with NaN frames holding the previous valid one (leading ones
    the first valid one; none valid at all: identity)."""
    valid = np.isfinite(rotations).all(axis=(1, 2))
    if not valid.any():
        return np.tile(np.eye(3), (len(rotations), 1, 1))
    source = np.maximum.accumulate(np.where(valid, np.arange(len(valid)), -1))
    source[source < 0] = np.flatnonzero(valid)[0]
    return rotations[source]
