"""MediaPipe FaceLandmarker and HandLandmarker: the only module that imports ``mediapipe``.

Uses the official ``face_landmarker.task`` model vendored in ``keyshape/data`` (Apache-2.0,
see ``data/NOTICE``), in VIDEO running mode, and converts results to arrays at once. The hands
(:class:`HandTracker`) come from the vendored ``hand_landmarker.task``: its landmarker on the whole
picture, and its hand landmark model alone, read by OpenCV, on windows over the face.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import signal
import sys
import threading
import types
import zlib
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
N_HANDS = 2 * MAX_HANDS  # hands a frame's detection holds: the whole picture's, then the face windows'
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
    """Context manager: the hands in front of a face, the evidence of an occluder that
    :mod:`keyshape.capture.visibility` uses, from MediaPipe's two hand models.

    Two finders look at each frame:

    - MediaPipe's ``HandLandmarker`` (VIDEO mode) on the whole picture: its palm detector finds a
      hand as it comes into the picture and its landmark model follows it from frame to frame.
    - :class:`_FaceWindows`, when the face's landmarks are given: the same hand landmark model run
      on windows anchored to the face (over the mouth, over the eyes), which it answers with a
      hand's presence score. The palm detector seldom finds a hand already lying on a face (on
      the embedded clip's covered frames, one picture at a time: 13 %); the landmark model in a
      window over the mouth says a hand is there in 73 % of them and in none of the clear ones
      (docs/occlusion.md).

    ``detect(rgb, timestamp_ms, face)`` returns ``(N_HANDS, N_HAND_POINTS, 2)`` float32 pixels,
    the whole picture's hands first, then the windows'; rows of hands not found are NaN. The
    confidences are MediaPipe's defaults (0.5).
    """

    def __init__(self, model_path: Path | None = None):
        self.model_path = Path(model_path or default_hand_model_path())
        self._landmarker = None
        self._windows: _FaceWindows | None = None

    def __enter__(self) -> Self:
        BaseOptions, vision = _tasks()
        self._mp_image = _image_factory()
        try:
            with _quiet_native_stderr(), _signals_held():
                self._landmarker = vision.HandLandmarker.create_from_options(vision.HandLandmarkerOptions(
                    base_options=BaseOptions(model_asset_path=str(self.model_path)),
                    running_mode=vision.RunningMode.VIDEO, num_hands=MAX_HANDS))
                self._windows = _FaceWindows(self.model_path)
        except BaseException:
            self.__exit__()
            raise
        self._calls = 0
        self._last_ms = -1
        return self

    def __exit__(self, *exc) -> None:
        landmarker, self._landmarker, self._windows = self._landmarker, None, None
        if landmarker is not None:
            with _quiet_native_stderr(), _signals_held():  # LiteRT logs its accelerators' teardown
                landmarker.close()

    def detect(self, rgb: np.ndarray, timestamp_ms: int, face: np.ndarray | None = None) -> np.ndarray:
        """The hands in one RGB frame ``(height, width, 3) uint8`` and, with ``face`` (n, >= 2) its
        landmarks in pixels, over that face -> ``(N_HANDS, 21, 2)`` float32 pixels."""
        ms = max(int(timestamp_ms), self._last_ms + 1)  # VIDEO mode wants increasing times
        self._last_ms = ms
        hands = np.full((N_HANDS, N_HAND_POINTS, 2), np.nan, np.float32)
        quiet = _quiet_native_stderr() if self._calls < 2 else contextlib.nullcontext()
        with quiet:
            height, width = rgb.shape[:2]
            result = self._landmarker.detect_for_video(self._mp_image(rgb), ms)
            for k, landmarks in enumerate(result.hand_landmarks[:MAX_HANDS]):
                hands[k] = np.array([(p.x, p.y) for p in landmarks], dtype=np.float32) * (width, height)
        hands[MAX_HANDS:] = self._windows.find(rgb, ms, face)
        self._calls += 1
        return hands


# the windows asked over the mouth and over the eyes: (side, shift across the face), in face sizes
FACE_WINDOWS = ((1.0, -0.25), (1.0, 0.0), (1.0, 0.25), (1.4, -0.25), (1.4, 0.0), (1.4, 0.25))
HAND_PRESENCE = 0.5  # the landmark model's presence score that counts as a hand: MediaPipe's default
_MODEL_SIDE = 224  # the hand landmark model's input, pixels (RGB in [0, 1])
_PALM = (0, 1, 2, 3, 5, 6, 9, 10, 13, 14, 17, 18)  # the landmarks MediaPipe frames a hand's next window by


class _FaceWindows:
    """MediaPipe's hand landmark model on windows anchored to a face, run by OpenCV's TFLite reader.

    Each frame: a hand found in the frame before is followed (its next window framed from its
    landmarks as MediaPipe frames it: the palm's box, turned so that the wrist -> middle knuckle
    points up, doubled, moved up a tenth); with none to follow, one window over the mouth and one
    over the eyes are asked, each one of ``FACE_WINDOWS`` (sizes and shifts across the face, turned
    with the face's roll; which one is a hash of the frame's time, so a run is repeatable and a
    take asks them all), and a hand found in one is framed again from its own landmarks and asked
    once more. A hand counts when the model's presence score is at least ``HAND_PRESENCE``. A hand
    the whole picture's landmarker also has is found twice; the masks are a union, so it costs
    nothing but the window.

    ``find(rgb, ms, face)`` -> ``(MAX_HANDS, N_HAND_POINTS, 2)`` float32 pixels, NaN rows for
    hands not found. Its state (the hands followed) makes it a per-take object, like MediaPipe's
    VIDEO mode.
    """

    def __init__(self, bundle: Path):
        import zipfile

        import cv2

        with zipfile.ZipFile(bundle) as models:
            data = models.read("hand_landmarks_detector.tflite")
        self._cv2 = cv2
        self._net = cv2.dnn.readNetFromTFLite(np.frombuffer(data, np.uint8))
        self._outputs = self._net.getUnconnectedOutLayersNames()
        self._followed: list[np.ndarray] = []

    def find(self, rgb: np.ndarray, ms: int, face: np.ndarray | None) -> np.ndarray:
        out = np.full((MAX_HANDS, N_HAND_POINTS, 2), np.nan, np.float32)
        xy = None if face is None else np.asarray(face, dtype=float)[:, :2]
        if xy is None or not np.isfinite(xy).all():
            self._followed = []
            return out
        found: list[np.ndarray] = []
        for before in self._followed:
            hand = self._ask(rgb, *_hand_window(before))
            if hand is not None and not any(_same_hand(hand, other) for other in found):
                found.append(hand)
        if not found:
            windows = _face_windows(xy)
            turn = zlib.crc32(int(ms).to_bytes(8, "little", signed=True)) % (len(windows) // 2)
            for window in windows[turn::len(windows) // 2]:  # one over the mouth, one over the eyes
                hand = self._ask(rgb, *window)
                if hand is not None:
                    hand = self._ask(rgb, *_hand_window(hand))
                if hand is not None:
                    found.append(hand)
                    break
        self._followed = found[:MAX_HANDS]
        for k, hand in enumerate(self._followed):
            out[k] = hand
        return out

    def _ask(self, rgb: np.ndarray, centre: np.ndarray, side: float, angle: float) -> np.ndarray | None:
        """The hand in the square window of ``side`` pixels about ``centre`` (x, y), turned by
        ``angle`` radians -> (21, 2) pixels, or None when its presence is below ``HAND_PRESENCE``."""
        cv2 = self._cv2
        c, s = np.cos(angle), np.sin(angle)
        to_picture = np.array([[c, -s], [s, c]]) * (side / _MODEL_SIDE)  # window pixels -> picture pixels
        affine = np.hstack([to_picture, (np.asarray(centre) - to_picture @ np.full(2, _MODEL_SIDE / 2))[:, None]])
        window = cv2.warpAffine(rgb, cv2.invertAffineTransform(affine), (_MODEL_SIDE, _MODEL_SIDE),
                                flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        self._net.setInput((window.astype(np.float32) / 255.0).transpose(2, 0, 1)[None])
        landmarks, presence, *_ = self._net.forward(self._outputs)
        if float(np.ravel(presence)[0]) < HAND_PRESENCE:
            return None
        points = np.asarray(landmarks, dtype=float).reshape(N_HAND_POINTS, 3)[:, :2]
        return (points @ affine[:, :2].T + affine[:, 2]).astype(np.float32)


def _face_windows(xy: np.ndarray) -> list[tuple[np.ndarray, float, float]]:
    """(centre, side, angle) of the windows asked for a hand over a face of 478 landmarks ``xy``
    (n, 2) pixels: over the mouth, then over the eyes, each ``FACE_WINDOWS`` (side, shift across)
    in face sizes, turned with the face's roll (the line between the eyes' outer corners)."""
    from ..schemes import mediapipe_scheme

    contours = mediapipe_scheme()["contours"]
    size = float(np.ptp(xy, axis=0).max())
    across = xy[263] - xy[33]
    angle = float(np.arctan2(across[1], across[0]))
    sideways = across / max(float(np.linalg.norm(across)), 1e-9)
    mouth = xy[list(contours["lips"])].mean(axis=0)
    eyes = xy[list(contours["right_eye"]) + list(contours["left_eye"])].mean(axis=0)
    return [(centre + shift * size * sideways, side * size, angle)
            for centre in (mouth, eyes) for side, shift in FACE_WINDOWS]


def _hand_window(hand: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(centre, side, angle) of the window MediaPipe frames a hand's next frame by, from its 21
    landmarks ``hand`` (21, 2) pixels."""
    hand = np.asarray(hand, dtype=float)
    up = hand[9] - hand[0]
    angle = float(np.arctan2(up[1], up[0]) + np.pi / 2)  # turned so that wrist -> middle knuckle points up
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, -s], [s, c]])
    upright = (hand[list(_PALM)] - hand[0]) @ turn  # each row turned by -angle
    low, high = upright.min(axis=0), upright.max(axis=0)
    side = 2.0 * float((high - low).max())
    middle = (low + high) / 2 - [0.0, 0.1 * side / 2]
    return hand[0] + turn @ middle, side, angle


def _same_hand(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two findings are one hand: their wrists closer than its knuckle span."""
    return float(np.linalg.norm(a[0] - b[0])) < float(np.linalg.norm(a[5] - a[17]))


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
