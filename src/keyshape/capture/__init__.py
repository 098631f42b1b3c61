"""Stage 1, capture: video → :class:`~keyshape.containers.Track`.

``track_video`` decodes with PyAV (``video.py``) and tracks with MediaPipe's FaceLandmarker
(``mediapipe.py``). A frame without a face becomes a NaN frame; a video with no face at all
is an error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..containers import Track
from ..exceptions import NoFaceError
from .mediapipe import Detection, MediaPipeTracker, TrackerOptions, default_model_path
from .video import VideoInfo, iter_frames, probe

__all__ = ["track_video", "TrackerOptions", "MediaPipeTracker", "default_model_path", "probe",
           "iter_frames", "VideoInfo"]

N_LANDMARKS = 478


def _pick(faces: list[Detection], previous: np.ndarray | None) -> Detection:
    """Follow one person: the largest face first, then the face nearest the last one seen."""
    if len(faces) == 1:
        return faces[0]
    if previous is None:
        return max(faces, key=lambda f: np.prod(np.ptp(f.points[:, :2], axis=0)))
    centre = previous[:, :2].mean(axis=0)
    return min(faces, key=lambda f: np.linalg.norm(f.points[:, :2].mean(axis=0) - centre))


def track_video(path: str | Path, *, options: TrackerOptions | None = None,
                progress: bool = True) -> Track:
    """Track the face in every frame of a video.

    Parameters
    ----------
    path : video file PyAV can open
    options : TrackerOptions, optional (the vendored model by default)
    progress : show a progress bar on stderr

    Returns
    -------
    Track with points (n_frames, 478, 3) in pixels (z on the x scale), NaN where no face;
    blendshapes (n_frames, 52), head_matrix (n_frames, 4, 4).

    Raises
    ------
    InputError : missing or unreadable file. NoFaceError : no face in any frame.
    """
    from tqdm import tqdm

    path = Path(path)
    info = probe(path)
    points, scores, mats = [], [], []
    previous = None
    with MediaPipeTracker(options) as tracker:
        bar = tqdm(iter_frames(path), total=info.n_frames or None, unit="frame",
                   desc=f"track {path.name}", disable=not progress, leave=False)
        for ms, rgb in bar:
            faces = tracker.detect(rgb, ms)
            if faces:
                face = _pick(faces, previous)
                previous = face.points
                points.append(face.points)
                scores.append(face.scores)
                mats.append(face.matrix)
            else:
                points.append(np.full((N_LANDMARKS, 3), np.nan))
                scores.append(None)
                mats.append(np.full((4, 4), np.nan))
        names = tracker.blendshape_names
    if previous is None:
        raise NoFaceError(f"{path}: no face found in any of its {len(points)} frames")
    n_scores = len(names)
    scores = [s if s is not None and len(s) == n_scores else np.full(n_scores, np.nan) for s in scores]
    return Track(np.stack(points), info.fps, (info.width, info.height),
                 np.stack(scores), names, np.stack(mats))
