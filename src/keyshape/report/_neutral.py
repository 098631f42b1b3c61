"""The picture of a neutral that comes from a separate file (``--neutral FILE``: a still image or a
short clip of the actor at rest), for the contact sheets."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..containers import KeyShapes

__all__ = ["separate_neutral", "neutral_picture"]


def separate_neutral(keys: KeyShapes) -> bool:
    """Whether the keys' neutral comes from a file of its own, not a frame of their takes.

    Examples
    --------
    >>> keys = KeyShapes(np.zeros((2, 2)), np.ones((1, 2, 2)), ("a",), [4], ("lower",), {"lower": [0, 1]},
    ...                  ("take.mp4",), 0, "rest.png")
    >>> separate_neutral(keys)
    True
    """
    return bool(keys.neutral_take) and keys.neutral_take not in keys.takes


def neutral_picture(path, frame: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """Frame ``frame`` of the neutral's file (a still image: its only frame) and its landmarks.

    Parameters
    ----------
    path : str or Path
        The still image or clip (``take.json``'s ``neutral_source``).
    frame : int
        ``keys.neutral_frame``: the clip's frame nearest its median shape.

    Returns
    -------
    (rgb, points) : (height, width, 3) uint8 and (n_landmarks, 2) float pixels (NaN: no face
    found), or None when the file is gone or has no such frame. The frame is tracked again
    (one frame: about a second, most of it loading the model).
    """
    from ..capture import track_video
    from ..capture.video import iter_frames

    path = Path(path)
    if not path.is_file():
        return None
    pictures = [rgb for _, rgb in iter_frames(path, start=frame, end=frame + 1)]
    if not pictures:
        return None
    track = track_video(path, start=frame, end=frame + 1, progress=False)
    points = track.points[0, :, :2] if track.n_frames else np.full((1, 2), np.nan)
    return pictures[0], points
