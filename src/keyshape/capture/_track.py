"""Stage 1, capture: video → :class:`~keyshape.containers.Track`.

``track_video`` decodes with PyAV (``video.py``, in a background thread so decoding overlaps
inference) and tracks with MediaPipe's FaceLandmarker (``mediapipe.py``). A frame without a
face becomes a NaN frame; a video with no face at all is an error. ``track_to_file`` does the
same but streams the results to disk, so memory stays flat however long the video is. The
landmarks' visibility comes from the hands MediaPipe's hand landmarker finds in each frame as it
is tracked (``visibility.py``; spooled to disk with the rest, ``_spool.py``: 672 bytes a frame).
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..containers import Track
from ..exceptions import InputError, InputWarning, NoFaceError
from ..io.atomic import named_write_errors
from ._spool import N_LANDMARKS, N_SCORES, Spool, spool_folder
from .mediapipe import Detection, HandTracker, MediaPipeTracker, TrackerOptions, default_model_path
from .video import VideoInfo, iter_frames, prefetch, probe
from .visibility import VISIBILITY_MODES

__all__ = ["track_video", "track_to_file", "TrackerOptions", "MediaPipeTracker", "default_model_path",
           "probe", "iter_frames", "VideoInfo", "FaceFollower"]


class FaceFollower:
    """Follow one person through a video: never jump between people.

    The ``face``-th largest face (0 = largest) is chosen when a face is first seen. After
    that the face whose centre is nearest the followed one's last centre is kept, and only
    if it lies within ``max_jump`` face widths of it (the allowance grows by 10 % per frame
    the face was missing); anything farther is another person, and the frame is a gap.
    """

    def __init__(self, face: int = 0, *, max_jump: float = 1.0):
        self.face = face
        self.max_jump = max_jump
        self.last: np.ndarray | None = None
        self.width = 0.0
        self.missing = 0

    def pick(self, faces: list[Detection]) -> Detection | None:
        """The followed person's detection among ``faces``, or None."""
        chosen = self._first(faces) if self.last is None else self._nearest(faces)
        if chosen is None:
            self.missing += 1
            return None
        self.last = chosen.points[:, :2].mean(axis=0)
        self.width = float(np.ptp(chosen.points[:, 0]))
        self.missing = 0
        return chosen

    def _first(self, faces: list[Detection]) -> Detection | None:
        ranked = sorted(faces, key=lambda f: -np.prod(np.ptp(f.points[:, :2], axis=0)))
        return ranked[self.face] if len(ranked) > self.face else None

    def _nearest(self, faces: list[Detection]) -> Detection | None:
        if not faces:
            return None
        distance = [np.linalg.norm(f.points[:, :2].mean(axis=0) - self.last) for f in faces]
        best = int(np.argmin(distance))
        allowed = self.max_jump * self.width * (1 + 0.1 * self.missing)
        return faces[best] if distance[best] <= allowed else None


@dataclass(frozen=True)
class _Frame:
    points: np.ndarray  # (478, 3) float32, NaN if no face
    scores: np.ndarray  # (52,) float32
    matrix: np.ndarray  # (4, 4) float32
    index: int = 0  # the source frame number
    ms: int = 0  # its presentation time in milliseconds
    n_seen: int = 0  # faces the tracker saw in it (anyone's)
    hands: np.ndarray | None = None  # (2, 21, 2) float32 pixels, the hands found (NaN rows; None: not looked for)


def _nan_frame(index: int = 0, ms: int = 0, n_seen: int = 0) -> _Frame:
    return _Frame(np.full((N_LANDMARKS, 3), np.nan, np.float32), np.full(N_SCORES, np.nan, np.float32),
                  np.full((4, 4), np.nan, np.float32), index, ms, n_seen)


def _frames(path: Path, info: VideoInfo, *, options: TrackerOptions | None, start: int,
            end: int | None, fps: float | None, face: int, progress: bool,
            one_euro: dict | None = None, follower: FaceFollower | None = None,
            pts: np.ndarray | None = None, hands: bool = True) -> Iterator[_Frame]:
    from tqdm import tqdm

    from .filters import OneEuro

    smooth = OneEuro(info.fps, **one_euro) if one_euro is not None else None
    options = options or TrackerOptions()
    if face > 0 and options.num_faces < face + 2:  # see the others too, so we can tell them apart
        options = TrackerOptions(options.model_path, face + 2, options.min_detection_confidence,
                                 options.min_tracking_confidence, options.min_presence_confidence)
    total = (min(end, info.n_frames) if end is not None and info.n_frames else end or info.n_frames) - start
    follower = follower or FaceFollower(face)
    with MediaPipeTracker(options) as tracker, (HandTracker() if hands else contextlib.nullcontext()) as hand_tracker:
        source = prefetch(iter_frames(path, start=start, end=end, fps=fps, pts=pts))
        # disable=None: a bar only when stderr is a terminal, never in a log
        for index, (ms, rgb) in enumerate(tqdm(source, total=total if total > 0 else None, unit="frame",
                                               desc=f"track {path.name}", disable=None if progress else True,
                                               leave=False, dynamic_ncols=True), start=start):
            faces = tracker.detect(rgb, ms)
            chosen = follower.pick(faces)
            if chosen is None or len(chosen.scores) != N_SCORES:
                if smooth is not None:
                    smooth(np.full(1, np.nan))  # a gap restarts the filter
                yield _nan_frame(index, ms, len(faces))
            else:
                points = (smooth(chosen.points) if smooth is not None else chosen.points).astype(np.float32)
                # the hands are looked for here, in the frame being tracked: no second decode for them
                yield _Frame(points, chosen.scores.astype(np.float32), chosen.matrix.astype(np.float32),
                             index, ms, len(faces), hand_tracker.detect(rgb, ms, points) if hands else None)


def _check_range(start: int, end: int | None) -> None:
    if start < 0 or (end is not None and end <= start):
        raise InputError(f"frame range must satisfy 0 <= start < end; got start={start}, end={end}")


def _blendshape_names() -> tuple[str, ...]:
    from .mediapipe import BLENDSHAPE_NAMES

    return BLENDSHAPE_NAMES


def _probe(path: Path, fps: float | None, start: int) -> VideoInfo:
    info = probe(path, fps=fps)
    if info.n_frames and start >= info.n_frames:
        raise InputError(f"{path}: start frame {start} is past its end (it has {info.n_frames} frames, "
                         f"0..{info.n_frames - 1})")
    return info


def _spool(path, *, options, start, end, fps, face, progress, folder: Path,
           one_euro: dict | None = None, workers: int | None = 1, visibility: str = "auto") -> tuple[Spool, VideoInfo]:
    _check_range(start, end)
    if visibility not in VISIBILITY_MODES:
        raise InputError(f"visibility must be one of {', '.join(VISIBILITY_MODES)}; got {visibility!r}")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a finite number > 0; got {fps!r}")
    path = Path(path)
    spool, processes = None, []
    if workers != 1:  # segments in parallel; the workers start importing while we probe
        from ._parallel import default_workers, spool_parallel, start_workers, stop_workers

        processes = start_workers((default_workers() if workers is None else workers) - 1)
    try:
        info = _probe(path, fps, start)
        settings = {"options": options, "fps": fps, "face": face, "one_euro": one_euro,
                    "hands": visibility == "auto"}
        if processes:  # None: too short to split
            with named_write_errors(folder):  # the segments' joins: a full disk says where
                spool = spool_parallel(path, info, _track_segment, Spool, start=start, end=end,
                                       progress=progress, folder=folder, processes=processes, **settings)
    finally:
        if processes:
            stop_workers(processes)
    if spool is None:
        with Spool(folder) as spool:
            for frame in _frames(path, info, start=start, end=end, progress=progress, **settings):
                spool.append(frame)
    if spool.n_frames == 0:
        raise InputError(f"{path}: no frame from frame {start} on (the video ends before it)")
    _warn_if_truncated(path, info, start + spool.n_frames, end)
    if spool.n_faces == 0:
        raise NoFaceError(_no_face_message(path, spool, face))
    return spool, info


def _track_segment(path: Path, info: VideoInfo, first: int, end: int, folder: Path, pts: np.ndarray | None,
                   kwargs: dict, seed: dict | None = None) -> dict:
    """Frames ``first <= i < end`` into a spool in ``folder`` (one segment of a parallel run,
    :mod:`keyshape.capture._parallel`); ``seed``: the :class:`FaceFollower`'s state to start from.
    Returns the spool's counters and clock."""
    follower = FaceFollower(kwargs["face"])
    vars(follower).update(seed or {})
    with Spool(folder) as spool:
        for frame in _frames(path, info, start=first, end=end, progress=False, follower=follower, pts=pts,
                             **kwargs):
            spool.append(frame)
    return {"n_frames": spool.n_frames, "n_faces": spool.n_faces, "most_seen": spool.most_seen,
            "n_hands": spool.n_hands, "index": spool.index, "ms": spool.ms}


def _no_face_message(path: Path, spool: Spool, face: int) -> str:
    if face > 0 and spool.most_seen > 0:
        ordinal = {1: "2nd", 2: "3rd"}.get(face, f"{face + 1}th")
        return (f"{path}: no {ordinal} face to follow (face={face}): at most {spool.most_seen} "
                f"{'face was' if spool.most_seen == 1 else 'faces were'} seen in any of its {spool.n_frames} frames")
    return f"{path}: no face found in any of its {spool.n_frames} frames"


def _warn_if_truncated(path: Path, info: VideoInfo, decoded: int, end: int | None) -> None:
    """Warn when the video ends well before the frame count its container declares (by more than
    5 frames and 5 %: containers often declare a few frames more than they hold, e.g. QuickTime's
    edit lists)."""
    wanted = info.n_frames if end is None else min(end, info.n_frames)
    if info.n_frames and wanted - decoded > max(5, 0.05 * info.n_frames):
        warnings.warn(f"{path}: only {decoded} frames could be decoded but its container declares "
                      f"{info.n_frames}: the file may be truncated, and the track ends at frame {decoded - 1}",
                      InputWarning, stacklevel=3)


def _visibility(spool: Spool, points: np.ndarray) -> np.ndarray | None:
    """(n_frames, n_landmarks) visibility of the tracked landmarks from the hands found while
    tracking (:func:`~.visibility.visibility_from_hands`); None when no hand covered the face."""
    from .visibility import visibility_from_hands

    if spool.n_hands == 0:
        return None
    return visibility_from_hands(points, spool.arrays()["hands"])


def track_video(path: str | Path, *, options: TrackerOptions | None = None, start: int = 0,
                end: int | None = None, fps: float | None = None, face: int = 0,
                one_euro: dict | None = None, progress: bool = True, workers: int | None = 1,
                visibility: str = "auto") -> Track:
    """Track one face in every frame of a video file or a folder of images.

    Parameters
    ----------
    path : video file PyAV can open (rotation metadata is honoured) or a folder of images
    options : TrackerOptions, optional (the vendored model by default)
    start, end : frame range ``start <= i < end`` (``end=None``: to the last frame)
    fps : frame rate override (image folders default to 30)
    face : which person to follow when several are visible: 0 = the largest face at the start
    one_euro : None (default), or the settings of a causal One Euro filter on the landmarks
        (``{}`` for the defaults; see :class:`keyshape.capture.filters.OneEuro`) for live-like use.
        Offline, the default zero-lag smoothing of the solve is the better choice.
    progress : show a progress bar with frames/s and ETA on stderr
    workers : processes tracking overlapping segments of the video in parallel, each with its
        own landmarker (1, the default: this process only; None: one per core). Short inputs
        use fewer. See :mod:`keyshape.capture._parallel`.
    visibility : "auto" (default): MediaPipe's hand landmarker looks for hands in every frame
        with a face, and the landmarks a hand covers get visibility 0
        (:mod:`~keyshape.capture.visibility`); "off": no hands looked for, no visibility.

    Returns
    -------
    Track with points (n_frames, 478, 3) in pixels (z on the x scale), NaN where no face;
    blendshapes (n_frames, 52) ARKit-style scores; head_matrix (n_frames, 4, 4); visibility
    (n_frames, 478) in {0, 1} where a hand covered the face in some frame, else None (all seen).

    Raises
    ------
    InputError : missing or unreadable input, bad range. NoFaceError : no face in any frame.
    """
    with spool_folder() as tmp:
        spool, info = _spool(path, options=options, start=start, end=end, fps=fps, face=face,
                             progress=progress, folder=tmp, one_euro=one_euro, workers=workers,
                             visibility=visibility)
        arrays = spool.arrays()
        clock = spool.clock()
        track = Track(arrays["points"], info.fps, (info.width, info.height), arrays["scores"],
                      _blendshape_names(), arrays["matrix"], clock["frame_index"], clock["time"],
                      _visibility(spool, arrays["points"]))
        del arrays
    return track


def track_to_file(path: str | Path, output: str | Path, *, options: TrackerOptions | None = None,
                  start: int = 0, end: int | None = None, fps: float | None = None, face: int = 0,
                  one_euro: dict | None = None, progress: bool = True, workers: int | None = 1,
                  visibility: str = "auto") -> dict:
    """Track a video straight into a track file; memory use does not grow with its length.

    Same parameters as :func:`track_video`. Returns a summary dict: ``n_frames``,
    ``n_faces`` (frames with a face), ``fps``, ``image_size``.
    """
    from ..io.track import write_track_arrays

    output = Path(output)
    spool_dir = output.parent if output.parent.exists() else None
    with spool_folder(spool_dir) as tmp:
        spool, info = _spool(path, options=options, start=start, end=end, fps=fps, face=face,
                             progress=progress, folder=tmp, one_euro=one_euro, workers=workers,
                             visibility=visibility)
        arrays = spool.arrays()
        write_track_arrays(output, points=arrays["points"], fps=info.fps,
                           image_size=(info.width, info.height), blendshapes=arrays["scores"],
                           blendshape_names=_blendshape_names(), head_matrix=arrays["matrix"],
                           visibility=_visibility(spool, arrays["points"]),
                           **spool.clock())
        del arrays
    return {"n_frames": spool.n_frames, "n_faces": spool.n_faces, "fps": info.fps,
            "image_size": (info.width, info.height)}
