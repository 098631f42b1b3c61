"""MediaPipe FaceLandmarker: the only module that imports ``mediapipe``.

Uses the official ``face_landmarker.task`` model vendored in ``keyshape/data`` (Apache-2.0,
see ``data/NOTICE``), in VIDEO running mode, and converts results to arrays at once.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import signal
import sys
import threading
import types
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Self

import numpy as np

from ..exceptions import MissingDependencyError

__all__ = ["TrackerOptions", "MediaPipeTracker", "Detection", "default_model_path", "BLENDSHAPE_NAMES", "preload",
           "defer_unused_imports", "HandTracker", "default_hand_model_path", "MAX_HANDS", "N_HANDS", "N_HAND_POINTS"]

# The 52 scores of the face blendshapes model, in its output order (ARKit names plus "_neutral").
BLENDSHAPE_NAMES = (
    "_neutral", "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft",
    "browOuterUpRight", "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "eyeBlinkLeft",
    "eyeBlinkRight", "eyeLookDownLeft", "eyeLookDownRight", "eyeLookInLeft", "eyeLookInRight",
    "eyeLookOutLeft", "eyeLookOutRight", "eyeLookUpLeft", "eyeLookUpRight", "eyeSquintLeft",
    "eyeSquintRight", "eyeWideLeft", "eyeWideRight", "jawForward", "jawLeft", "jawOpen",
    "jawRight", "mouthClose", "mouthDimpleLeft", "mouthDimpleRight", "mouthFrownLeft",
    "mouthFrownRight", "mouthFunnel", "mouthLeft", "mouthLowerDownLeft", "mouthLowerDownRight",
    "mouthPressLeft", "mouthPressRight", "mouthPucker", "mouthRight", "mouthRollLower",
    "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthSmileLeft",
    "mouthSmileRight", "mouthStretchLeft", "mouthStretchRight", "mouthUpperUpLeft",
    "mouthUpperUpRight", "noseSneerLeft", "noseSneerRight",
)

MODEL_SHA256 = "64184e229b263107bc2b804c6625db1341ff2bb731874b0bcc2fe6544e0bc9ff"
HAND_MODEL_SHA256 = "1c73bdac1ed829cbbe9c03c932318794585d5bed7a920eabf2795268ae0d1e6b"
MAX_HANDS = 2  # hands each view looks for: an actor's two
N_HANDS = 2 * MAX_HANDS  # hands a frame's detection holds: the whole picture's, then the face view's
FACE_VIEW = 2.0  # the face view's width, in face sizes (the landmarks' largest extent)
N_HAND_POINTS = 21  # MediaPipe's hand landmarks: the wrist, then four per finger from the thumb


def default_model_path() -> Path:
    """Path of the vendored ``face_landmarker.task``."""
    return Path(str(resources.files("keyshape").joinpath("data/face_landmarker.task")))


def default_hand_model_path() -> Path:
    """Path of the vendored ``hand_landmarker.task`` (MediaPipe's palm detector and hand landmark
    model, ``tools/make_hand_model.py``)."""
    return Path(str(resources.files("keyshape").joinpath("data/hand_landmarker.task")))


@dataclass(frozen=True)
class TrackerOptions:
    """Settings of the MediaPipe face landmarker (running mode is always VIDEO)."""

    model_path: Path | None = None
    num_faces: int = 1
    min_detection_confidence: float = 0.5
    min_tracking_confidence: float = 0.5
    min_presence_confidence: float = 0.5


@dataclass(frozen=True)
class Detection:
    """One face in one frame.

    points : (478, 3) float, pixels (z on the x scale)
    scores : (52,) float, ARKit-style blendshape scores
    matrix : (4, 4) float, facial transformation matrix
    """

    points: np.ndarray
    scores: np.ndarray
    matrix: np.ndarray


def _quiet_logs() -> None:
    os.environ.setdefault("GLOG_minloglevel", "2")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")


# MediaPipe's tasks package imports every task and its drawing helpers at once; tracking uses
# neither its audio tasks nor matplotlib's pyplot, which are 0.5 s of its 0.8-1.1 s import.
_UNUSED = ("mediapipe.tasks.python.audio", "matplotlib.pyplot")


class _Deferred(types.ModuleType):
    """Stands in for a module not imported yet: the real one is imported on first attribute use."""

    def __getattr__(self, attribute: str):
        if sys.modules.get(self.__name__) is self:
            del sys.modules[self.__name__]
        return getattr(importlib.import_module(self.__name__), attribute)


def defer_unused_imports() -> None:
    """Let MediaPipe's import skip what tracking never uses (``_UNUSED``), in keyshape's own
    processes only (the ``keyshape`` command, tracking workers): each of those modules is still
    imported, for real, on its first use."""
    for name in _UNUSED:
        if name not in sys.modules:
            sys.modules[name] = _Deferred(name)


def preload() -> None:
    """Import MediaPipe's tasks API now: a tracking worker does it while it waits for its job
    (:mod:`keyshape.capture._parallel`)."""
    _quiet_logs()
    defer_unused_imports()
    with contextlib.suppress(ImportError):  # MediaPipeTracker says what is missing
        from mediapipe.tasks.python import vision  # noqa: F401


class MediaPipeTracker:
    """Context manager around ``FaceLandmarker`` in VIDEO mode.

    ``detect(rgb, timestamp_ms)`` returns a list of :class:`Detection` (empty when no face).
    """

    def __init__(self, options: TrackerOptions | None = None):
        self.options = options or TrackerOptions()
        self._landmarker = None
        self.blendshape_names: tuple[str, ...] = ()

    def __enter__(self) -> Self:
        BaseOptions, vision = _tasks()
        opts = self.options
        model = Path(opts.model_path or default_model_path())
        self._mp_image = _image_factory()
        try:
            with _quiet_native_stderr(), _signals_held():  # made whole, and ours to close
                self._landmarker = vision.FaceLandmarker.create_from_options(
                    vision.FaceLandmarkerOptions(
                        base_options=BaseOptions(model_asset_path=str(model)),
                        running_mode=vision.RunningMode.VIDEO,
                        num_faces=opts.num_faces,
                        min_face_detection_confidence=opts.min_detection_confidence,
                        min_face_presence_confidence=opts.min_presence_confidence,
                        min_tracking_confidence=opts.min_tracking_confidence,
                        output_face_blendshapes=True,
                        output_facial_transformation_matrixes=True,
                    )
                )
        except BaseException:  # a Ctrl-C or SIGTERM held meanwhile: no ``with`` block will close it
            self.__exit__()
            raise
        self._calls = 0
        return self

    def __exit__(self, *exc) -> None:
        landmarker, self._landmarker = self._landmarker, None
        if landmarker is not None:
            with _quiet_native_stderr(), _signals_held():  # LiteRT logs its accelerators' teardown
                landmarker.close()

    def detect(self, rgb: np.ndarray, timestamp_ms: int) -> list[Detection]:
        """Faces in one RGB frame ``(height, width, 3) uint8``."""
        height, width = rgb.shape[:2]
        quiet = _quiet_native_stderr() if self._calls < 2 else contextlib.nullcontext()
        with quiet:  # the first inferences log start-up notes from C++
            result = self._landmarker.detect_for_video(self._mp_image(rgb), int(timestamp_ms))
        self._calls += 1
        faces = []
        for i, landmarks in enumerate(result.face_landmarks):
            pts = np.array([(p.x, p.y, p.z) for p in landmarks], dtype=float)
            pts *= (width, height, width)
            cats = result.face_blendshapes[i] if result.face_blendshapes else []
            if cats and not self.blendshape_names:
                self.blendshape_names = tuple(c.category_name for c in cats)
            scores = np.array([c.score for c in cats], dtype=float)
            mats = result.facial_transformation_matrixes
            matrix = np.asarray(mats[i], dtype=float) if mats else np.full((4, 4), np.nan)
            faces.append(Detection(pts, scores, matrix))
        return faces


class HandTracker:
    """Context manager around MediaPipe's ``HandLandmarker`` in VIDEO mode: the hands in front of a
    face, the evidence of an occluder that :mod:`keyshape.capture.visibility` uses.

    Two landmarkers look: one at the whole picture, one at the square around the face
    (``FACE_VIEW`` face sizes wide, when the face's landmarks are given). The palm detector seldom
    finds a hand already lying on a face, so a hand over a face is found mostly by following it
    from where it was found; two views find it in more frames (measured on the occlusion
    benchmark's composites, docs/occlusion.md). ``detect(rgb, timestamp_ms, face)`` returns
    ``(N_HANDS, N_HAND_POINTS, 2)`` float32 pixels, the whole picture's hands first, then the
    face view's; rows of hands not found are NaN. The confidences are MediaPipe's defaults (0.5).
    """

    def __init__(self, model_path: Path | None = None):
        self.model_path = Path(model_path or default_hand_model_path())
        self._landmarkers: list = []

    def __enter__(self) -> Self:
        BaseOptions, vision = _tasks()
        self._mp_image = _image_factory()
        try:
            with _quiet_native_stderr(), _signals_held():
                for _ in range(2):
                    self._landmarkers.append(vision.HandLandmarker.create_from_options(vision.HandLandmarkerOptions(
                        base_options=BaseOptions(model_asset_path=str(self.model_path)),
                        running_mode=vision.RunningMode.VIDEO, num_hands=MAX_HANDS)))
        except BaseException:
            self.__exit__()
            raise
        self._calls = 0
        self._last_ms = -1
        return self

    def __exit__(self, *exc) -> None:
        landmarkers, self._landmarkers = self._landmarkers, []
        if landmarkers:
            with _quiet_native_stderr(), _signals_held():  # LiteRT logs its accelerators' teardown
                for landmarker in landmarkers:
                    landmarker.close()

    def detect(self, rgb: np.ndarray, timestamp_ms: int, face: np.ndarray | None = None) -> np.ndarray:
        """The hands in one RGB frame ``(height, width, 3) uint8`` and, with ``face`` (n, >= 2) its
        landmarks in pixels, around that face -> ``(N_HANDS, 21, 2)`` float32 pixels."""
        ms = max(int(timestamp_ms), self._last_ms + 1)  # VIDEO mode wants increasing times
        self._last_ms = ms
        hands = np.full((N_HANDS, N_HAND_POINTS, 2), np.nan, np.float32)
        quiet = _quiet_native_stderr() if self._calls < 2 else contextlib.nullcontext()
        with quiet:
            hands[:MAX_HANDS] = self._find(self._landmarkers[0], rgb, ms, (0, 0))
            view = _face_view(rgb.shape, face)
            if view is not None:
                x0, y0, x1, y1 = view
                hands[MAX_HANDS:] = self._find(self._landmarkers[1], np.ascontiguousarray(rgb[y0:y1, x0:x1]), ms,
                                               (x0, y0))
        self._calls += 1
        return hands

    def _find(self, landmarker, rgb: np.ndarray, ms: int, origin) -> np.ndarray:
        height, width = rgb.shape[:2]
        result = landmarker.detect_for_video(self._mp_image(rgb), ms)
        hands = np.full((MAX_HANDS, N_HAND_POINTS, 2), np.nan, np.float32)
        for k, landmarks in enumerate(result.hand_landmarks[:MAX_HANDS]):
            hands[k] = np.array([(p.x, p.y) for p in landmarks], dtype=np.float32) * (width, height) + origin
        return hands


def _face_view(shape, face: np.ndarray | None) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1): the square ``FACE_VIEW`` face sizes wide about the face, within the picture
    of ``shape``; None without a face (or one too small to look at)."""
    if face is None:
        return None
    xy = np.asarray(face, dtype=float)[:, :2]
    if not np.isfinite(xy).all():
        return None
    centre, half = xy.mean(axis=0), FACE_VIEW / 2 * float(np.ptp(xy, axis=0).max())
    x0, y0 = np.maximum(np.floor(centre - half), 0).astype(int)
    x1, y1 = np.minimum(np.ceil(centre + half), (shape[1], shape[0])).astype(int)
    return (int(x0), int(y0), int(x1), int(y1)) if min(x1 - x0, y1 - y0) >= 32 else None


def _tasks():
    """MediaPipe's ``BaseOptions`` and ``vision`` tasks module, imported whole (:func:`_signals_held`)."""
    _quiet_logs()
    try:
        with _signals_held():
            from mediapipe.tasks.python import BaseOptions, vision
    except ImportError:
        raise MissingDependencyError("mediapipe") from None
    return BaseOptions, vision


@contextlib.contextmanager
def _signals_held():
    """Hold Ctrl-C and SIGTERM until the block ends, then raise the first one that came.

    A signal's Python handler (KeyboardInterrupt, the command's
    :class:`~keyshape.exceptions.Terminated`) raises wherever the main thread is, and two
    things of MediaPipe's do not survive that, so :class:`MediaPipeTracker` holds them whole:

    - its import (0.2-1 s, some 190 modules, native ones among them): raised in one of
      importlib's callbacks the exception is printed and dropped (the run goes on to the end as if
      never stopped); raised as a native module has just initialised, the process aborts when it
      exits ("Fatal Python error: PyThreadState_Get"); it has also come out as an ImportError
      ("mediapipe is required").
    - the creation and closing of its landmarker. MediaPipe runs each call of its C API on a
      thread of its own (``SerialDispatcher``) while the caller waits: an abandoned creation
      leaves a landmarker nobody closes, whose graph goes on writing to stderr after the command's
      last line, and when the signal lands as that thread is being started the interpreter is
      never told to stop it (``ThreadPoolExecutor`` registers its thread after starting it) and
      waits for it at exit, forever. An interrupted ``detect`` is harmless: ``close`` runs after
      it on the same thread.

    Only Python handlers are held, in the main thread (the only one they run in); a signal left
    to its default action still ends the process at once.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    held = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        if callable(signal.getsignal(signum)):
            held[signum] = signal.signal(signum, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for signum, handler in held.items():
            signal.signal(signum, handler)
        if caught:
            held[caught[0]](caught[0], None)


@contextlib.contextmanager
def _quiet_native_stderr():
    """Silence MediaPipe's C++ start-up logging (written straight to file descriptor 2)."""
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def _image_factory():
    import mediapipe as mp

    def make(rgb: np.ndarray):
        return mp.Image(image_format=mp.ImageFormat.SRGB, data=np.ascontiguousarray(rgb))

    return make
