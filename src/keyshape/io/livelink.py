"""Live Link Face CSV: the take format of Epic's Live Link Face app, for ARKit-named rigs.

One row per frame::

    Timecode,BlendShapeCount,EyeBlinkLeft,...,TongueOut,HeadYaw,HeadPitch,HeadRoll,
    LeftEyeYaw,LeftEyePitch,LeftEyeRoll,RightEyeYaw,RightEyePitch,RightEyeRoll

* ``Timecode`` is ``HH:MM:SS:FF.fff``: non-drop-frame timecode at the nominal rate
  ``round(fps)`` (so frame ``f`` of a 23.976 take is frame ``f`` of 24-frame timecode) and a
  sub-frame fraction, here always ``.000``; ``BlendShapeCount`` is 61.
* The 52 ARKit coefficients follow in Live Link's order (:data:`LIVELINK_NAMES`), clipped to
  ``[0, 1]`` (ARKit's range). Rig targets are matched by name, ignoring case, so ARKit
  (``eyeBlinkLeft``), Live Link (``EyeBlinkLeft``) and ``_L``/``_R`` (``eyeBlink_L``, as
  ICT-FaceKit) spellings all work; a coefficient a rig splits into halves (``browInnerUp_L``
  and ``_R``) is their mean. Coefficients the rig lacks are 0.
* Head yaw, pitch and roll are in radians: the head rotation in glTF axes (+Y up, the
  character facing +Z) written as intrinsic Y-X-Z Euler angles (yaw about +Y, pitch about the
  turned +X, roll about the final +Z), right-handed; 0 without poses. Eye angles are the same
  for each eye's rotation relative to the head (``eyes``), the character's left eye first; 0
  without them.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from ..containers import Poses, Weights
from ..exceptions import InputError, RigError
from ..schemes import head_rotations, hold_valid, rotations_to_gltf
from .atomic import atomic_path, existing_file
from .validate import check_weight_values

__all__ = ["LIVELINK_NAMES", "ROTATION_NAMES", "write_livelink_csv", "read_livelink_csv",
           "livelink_columns", "LiveLinkTake"]

LIVELINK_NAMES = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft",
    "EyeSquintLeft", "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight",
    "EyeLookOutRight", "EyeLookUpRight", "EyeSquintRight", "EyeWideRight", "JawForward",
    "JawRight", "JawLeft", "JawOpen", "MouthClose", "MouthFunnel", "MouthPucker", "MouthRight",
    "MouthLeft", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft", "MouthFrownRight",
    "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft", "MouthStretchRight",
    "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper", "MouthPressLeft",
    "MouthPressRight", "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft",
    "MouthUpperUpRight", "BrowDownLeft", "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft",
    "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft", "CheekSquintRight", "NoseSneerLeft",
    "NoseSneerRight", "TongueOut",
)
ROTATION_NAMES = ("HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
                  "RightEyeYaw", "RightEyePitch", "RightEyeRoll")
HEADER = ("Timecode", "BlendShapeCount", *LIVELINK_NAMES, *ROTATION_NAMES)
_SIDE = re.compile(r"[_.\s-](l|r)$", re.IGNORECASE)
_TIMECODE = re.compile(r"^(\d+):(\d\d):(\d\d)[:;](\d+)(?:\.(\d+))?$")


class LiveLinkTake(NamedTuple):
    """A Live Link Face CSV read back.

    Attributes
    ----------
    weights : Weights
        ``values (n_frames, 52)`` named :data:`LIVELINK_NAMES`.
    rotations : (n_frames, 9) float
        :data:`ROTATION_NAMES` (radians as written by :func:`write_livelink_csv`).
    """

    weights: Weights
    rotations: np.ndarray


def _canonical(name: str) -> str:
    """``eyeBlink_L``, ``eyeBlinkLeft``, ``EyeBlinkLeft`` -> ``eyeblinkleft``."""
    match = _SIDE.search(name)
    if match:
        name = name[: match.start()] + ("left" if match.group(1).lower() == "l" else "right")
    return re.sub(r"[_.\s-]", "", name).lower()


def livelink_columns(names) -> tuple[dict[str, list[int]], list[str]]:
    """Which channels feed each Live Link coefficient, and the channels none uses.

    Parameters
    ----------
    names : sequence of str
        Channel (rig target) names.

    Returns
    -------
    sources : dict str -> list of int
        For each coefficient in :data:`LIVELINK_NAMES` that the names provide, the channel
        indices whose mean it is (one, or two halves ``_L``/``_R`` of an unsided coefficient).
    unused : list of str
        Names no coefficient uses.

    Examples
    --------
    >>> sources, unused = livelink_columns(["eyeBlink_L", "browInnerUp_L", "browInnerUp_R", "PupilDilate_L"])
    >>> sources["EyeBlinkLeft"], sources["BrowInnerUp"], unused
    ([0], [1, 2], ['PupilDilate_L'])
    """
    names = [str(n) for n in names]
    canonical = [_canonical(n) for n in names]
    sources = {}
    for column in LIVELINK_NAMES:
        key = column.lower()
        exact = [i for i, c in enumerate(canonical) if c == key]
        halves = [i for i, c in enumerate(canonical) if c in (key + "left", key + "right")]
        if exact or len(halves) == 2:
            sources[column] = exact[:1] or halves
    used = {i for indices in sources.values() for i in indices}
    return sources, [n for i, n in enumerate(names) if i not in used]


def write_livelink_csv(path, weights: Weights, *, poses: Poses | None = None,
                       eyes: np.ndarray | None = None) -> Path:
    """Write ARKit-named weights (and the head rotation) as a Live Link Face CSV, atomically.

    Parameters
    ----------
    path : str or Path
    weights : Weights
        ``values (n_frames, n_channels)`` named by rig targets with ARKit names (see the module
        docstring); NaN frames are written as 0. Channels that are not ARKit coefficients
        are left out (see :func:`livelink_columns`).
    poses : Poses, optional
        Head poses (image convention, as :func:`keyshape.io.gltf.write_glb`): yaw, pitch, roll.
    eyes : (n_frames, 2, 3, 3) float, optional
        Eye rotations relative to the head (image convention), left eye first (as
        :func:`keyshape.io.gltf.animate_gltf`).

    Returns
    -------
    Path

    Raises
    ------
    RigError
        If no channel is an ARKit coefficient.
    InputError
        If ``poses`` has another frame count.
    """
    from ._gltf_anim import check_eyes, check_poses

    sources, _ = livelink_columns(weights.names)
    if not sources:
        raise RigError(f"no ARKit-named targets among {list(weights.names)[:12]}...: Live Link Face "
                       "needs names such as jawOpen, eyeBlinkLeft or eyeBlink_L")
    check_weight_values(path, weights.names, weights.values, weights.frame_index)
    check_poses(poses, weights)
    check_eyes(eyes, weights)
    table = _coefficients(weights, sources)
    angles = np.zeros((weights.n_frames, len(ROTATION_NAMES)))
    if poses is not None:
        angles[:, :3] = head_angles(head_rotations(poses, hold=True))
    for side in range(2 if eyes is not None else 0):
        rotations = hold_valid(np.asarray(eyes, dtype=float)[:, side])
        angles[:, 3 + 3 * side:6 + 3 * side] = head_angles(rotations_to_gltf(rotations))
    _write_rows(path, weights.fps, table, angles)
    return Path(path)


def _coefficients(weights: Weights, sources: dict[str, list[int]]) -> np.ndarray:
    values = np.nan_to_num(weights.values, nan=0.0)
    table = np.zeros((weights.n_frames, len(LIVELINK_NAMES)))
    for k, column in enumerate(LIVELINK_NAMES):
        if column in sources:
            table[:, k] = values[:, sources[column]].mean(axis=1)
    return np.clip(table, 0.0, 1.0)


def head_angles(rotations: np.ndarray) -> np.ndarray:
    """(n_frames, 3) yaw, pitch, roll in radians: intrinsic Y-X-Z Euler angles of glTF-axis rotations."""
    if len(rotations) == 0:
        return np.zeros((0, 3))
    return Rotation.from_matrix(rotations).as_euler("YXZ")


def _write_rows(path, fps: float, table: np.ndarray, angles: np.ndarray) -> None:
    rate = max(int(round(fps)), 1)
    count = len(LIVELINK_NAMES) + len(ROTATION_NAMES)
    row_format = ",".join(["%.6f"] * count)
    values = np.concatenate([table, angles], axis=1)
    lines = [",".join(HEADER)]
    lines += [f"{timecode(frame, rate)},{count}," + row_format % tuple(row) for frame, row in enumerate(values)]
    with atomic_path(path) as tmp:
        tmp.write_text("\r\n".join(lines) + "\r\n", encoding="utf-8")


def timecode(frame: int, rate: int) -> str:
    """``HH:MM:SS:FF.000`` of frame ``frame`` in non-drop timecode at ``rate`` frames/s.

    Examples
    --------
    >>> timecode(0, 30), timecode(61, 30), timecode(24 * 3600, 24)
    ('00:00:00:00.000', '00:00:02:01.000', '01:00:00:00.000')
    """
    seconds, frames = divmod(int(frame), rate)
    minutes, seconds = divmod(seconds, 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours:02d}:{minutes:02d}:{seconds:02d}:{frames:02d}.000"


def read_livelink_csv(path, *, fps: float = 60.0) -> LiveLinkTake:
    """Read a Live Link Face CSV (written here or by the app).

    Parameters
    ----------
    path : str or Path
    fps : float, keyword-only
        The take's frame rate (the file does not state it; the app records at 60 by default).
        Timecode frames count at ``round(fps)``.

    Returns
    -------
    LiveLinkTake
        Weights named :data:`LIVELINK_NAMES` at ``fps`` (rows are frames, in file order),
        and the nine rotation columns.

    Raises
    ------
    InputError
        Missing file, wrong header or a bad row (the message names the file and the row).
    """
    path = Path(path)
    rows = _read_rows(path)
    header = rows[0]
    missing = [n for n in HEADER if n not in header]
    if missing:
        raise InputError(f"{path}: not a Live Link Face CSV (missing columns {missing[:5]})")
    columns = [header.index(n) for n in HEADER[2:]]
    try:
        table = np.array([[float(r[c]) for c in columns] for r in rows[1:] if r], dtype=float)
    except (ValueError, IndexError) as error:
        raise InputError(f"{path}: a row is not numbers ({error})") from None
    table = table.reshape(-1, len(columns))
    for number, row in enumerate(rows[1:], 2):
        if row and not _TIMECODE.match(row[header.index("Timecode")]):
            raise InputError(f"{path}, line {number}: bad Timecode {row[header.index('Timecode')]!r}")
    n = len(LIVELINK_NAMES)
    return LiveLinkTake(Weights(table[:, :n], LIVELINK_NAMES, fps), table[:, n:])


def _read_rows(path: Path) -> list[list[str]]:
    existing_file(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:  # a BOM (Excel's) is no header
            rows = list(csv.reader(handle))
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: not a readable CSV file ({error.__class__.__name__})") from None
    if not rows:
        raise InputError(f"{path}: empty file")
    return rows
