"""``--record DIR``: a live session written as a take, so nothing seen live is lost.

Frames are spooled to disk as they come (flat memory however long the session), indexed by the
source's frame number: a frame the loop dropped, or one without a face, is a NaN frame, so the
track keeps the source's timing. When the session ends — the source ended or failed, Ctrl-C,
SIGTERM — the spool becomes, in ``DIR``:

* ``track.npz`` — MediaPipe's landmarks, scores and head matrices of every frame, and the
  landmarks' visibility (a hand over the mouth: :mod:`keyshape.capture.visibility`, from the hands
  MediaPipe's hand landmarker finds in each frame as it comes; ``visibility="off"``: none);
* ``keys.json`` — the key set used (the calibrated one with ``--calibrate``);
* ``weights.csv`` — the key weights as they were sent live (causal, smoothed);
* ``animation.glb`` — the character driven by those weights, with the head and eye rotations;
* ``take.json`` — so ``keyshape view DIR`` and ``keyshape report DIR`` open it.

Re-solve it offline with the zero-lag smoother: ``keyshape solve DIR/track.npz DIR/keys.json``.
"""

from __future__ import annotations

import os
import queue
import shutil
import tempfile
import threading
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from ..capture.mediapipe import N_HAND_POINTS, N_HANDS
from ..containers import KeyShapes, Rig, Track, Weights
from .frame import LiveFrame

__all__ = ["Recorder", "RECORD_FILES"]

RECORD_FILES = ("track.npz", "keys.json", "weights.csv", "animation.glb", "take.json")
_NAN = np.float32(np.nan)
HANDS_SHAPE = (N_HANDS, N_HAND_POINTS, 2)  # a frame's hands in the spool
_NO_HANDS = np.full(HANDS_SHAPE, np.nan, np.float32)
HAND_QUEUE = 64  # frames the hands' thread may lag behind (about 45 MB of 640x360 frames)


class Recorder:
    """An :class:`~keyshape.live.frame.Output` that writes the session into ``folder`` at ``close``.

    Parameters
    ----------
    folder : Path
    keys : KeyShapes
    fps : float
    image_size : (width, height)
    rig : Rig and mapping : Mapping, for ``animation.glb`` (default: the built-in character)
    source : Path or str, recorded in ``take.json``
    builtin : bool
        Whether ``rig`` is keyshape's stylised head (:func:`keyshape.live.live_targets`' ``builtin``):
        the animation then gets its colours and its eyes turned by the gaze, as ``keyshape run``'s.
    visibility : "auto" (default): the hands in each frame with a face are looked for (12-15 ms a
        frame), and the landmarks they cover are hidden in ``track.npz``; "off": none looked for.
    """

    def __init__(self, folder, keys: KeyShapes, *, fps: float, image_size, rig: Rig | None = None,
                 mapping=None, source=None, blendshape_names: tuple[str, ...] = (), builtin: bool = False,
                 visibility: str = "auto"):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.keys, self.fps, self.image_size = keys, float(fps), tuple(image_size)
        self.rig, self.mapping, self.source = rig, mapping, source
        self.builtin = builtin or rig is None
        self.blendshape_names = tuple(blendshape_names)
        self._spool = Path(tempfile.mkdtemp(prefix=".live-spool-", dir=self.folder))
        self._stack = ExitStack()
        self._files = {name: self._stack.enter_context(open(self._spool / f"{name}.f32", "wb"))  # noqa: SIM115
                       for name in ("points", "scores", "matrix", "weights")}
        self._sizes = {"points": keys.n_landmarks * 3, "scores": len(blendshape_names) or 52,
                       "matrix": 16, "weights": keys.n_keys, "hands": int(np.prod(HANDS_SHAPE))}
        # the hands: looked for on a thread of their own, so the live loop never waits for them (25-30
        # ms a frame); each frame's row is written NaN here first, then the thread's finding over it
        self._hands_fd = os.open(self._spool / "hands.f32", os.O_RDWR | os.O_CREAT, 0o600)
        self._stack.callback(os.close, self._hands_fd)
        self._queue: queue.Queue | None = None
        if visibility == "auto":
            from ..capture.mediapipe import HandTracker

            tracker = self._stack.enter_context(HandTracker())
            self._queue = queue.Queue(maxsize=HAND_QUEUE)
            worker = threading.Thread(target=self._look, args=(tracker,), name="keyshape-hands", daemon=True)
            worker.start()
            self._stack.callback(worker.join)
            self._stack.callback(self._queue.put, None)  # (callbacks run last first: the stop, then the join)
        self.n_frames = 0
        self.files: tuple[Path, ...] = ()

    def send(self, frame: LiveFrame) -> None:
        while self.n_frames < frame.index:  # frames the loop dropped: gaps
            self._write(None, None)
        if frame.index == self.n_frames:
            self._write(frame.detection if frame.face else None, frame.keys, frame.rgb)

    def calibration(self, frames, keys: np.ndarray) -> None:
        """Record the calibration's ``(index, detection)`` frames (before the session's first frame)."""
        for index, detection in frames:
            while self.n_frames < index:
                self._write(None, None)
            if index == self.n_frames:
                self._write(detection, keys)

    def _write(self, detection, keys, rgb=None) -> None:
        parts = {"points": None, "scores": None, "matrix": None, "weights": keys}
        if detection is not None:
            parts.update(points=detection.points, scores=detection.scores, matrix=detection.matrix)
        for name, fh in self._files.items():
            value = parts[name]
            size = self._sizes[name]
            if value is None or np.size(value) != size:
                value = np.full(size, _NAN)
            fh.write(np.asarray(value, dtype=np.float32).tobytes())
        self._write_hands(None if detection is None else detection.points, rgb)
        self.n_frames += 1

    def _write_hands(self, points, rgb) -> None:
        """This frame's hands row: NaN now, and the frame handed to the hands' thread (the loop waits
        only when that thread is :data:`HAND_QUEUE` frames behind: a hand is followed frame by frame,
        so no frame is skipped)."""
        row = self.n_frames
        os.pwrite(self._hands_fd, _NO_HANDS.tobytes(), row * _NO_HANDS.nbytes)
        if self._queue is not None and points is not None and rgb is not None:
            self._queue.put((row, rgb, np.reshape(points, (-1, 3))))  # waits only when HAND_QUEUE behind

    def _look(self, tracker) -> None:
        """The hands' thread: the frames' hands, each written over its NaN row, until None comes."""
        while (item := self._queue.get()) is not None:
            row, rgb, points = item
            try:
                hands = tracker.detect(rgb, round(1000 * row / self.fps), points)
            except Exception:  # noqa: BLE001 (a frame the landmarker fails on keeps its NaN row: seen)
                continue
            os.pwrite(self._hands_fd, np.ascontiguousarray(hands, dtype=np.float32).tobytes(), row * _NO_HANDS.nbytes)

    def _visibility(self, points: np.ndarray, hands: np.ndarray) -> np.ndarray | None:
        """(n_frames, n_landmarks) visibility from the hands found (:func:`~keyshape.capture.visibility.
        visibility_from_hands`); None when no hand covered the face."""
        from ..capture.visibility import visibility_from_hands

        return visibility_from_hands(points, hands.reshape(len(hands), *HANDS_SHAPE))

    def _complete_frames(self) -> int:
        """The frames every spool file holds whole (SIGTERM may land between one file's write and
        the next's)."""
        counts = [(self._spool / f"{name}.f32").stat().st_size // (4 * size) for name, size in self._sizes.items()]
        return min(self.n_frames, *counts)

    def _arrays(self) -> dict[str, np.ndarray]:
        """The spool files' first :attr:`n_frames` frames (a file may hold one more, written whole
        before a signal stopped the next file's write)."""
        return {name: np.fromfile(self._spool / f"{name}.f32", dtype=np.float32,
                                  count=self.n_frames * size).reshape(self.n_frames, size)
                for name, size in self._sizes.items()}

    def close(self) -> None:
        """Write the take files (see the module docstring) and remove the spool."""
        self._stack.close()
        try:
            self.n_frames = self._complete_frames()  # a signal between two files' writes: the whole frames
            if self.n_frames:
                self.files = self._finish(self._arrays())
        finally:
            shutil.rmtree(self._spool, ignore_errors=True)

    def _finish(self, arrays: dict[str, np.ndarray]) -> tuple[Path, ...]:
        from ..io import save_keys, save_take_info, save_track, save_weights_csv

        n = self.n_frames
        names = self.blendshape_names or None
        points = arrays["points"].reshape(n, -1, 3)
        track = Track(points, self.fps, self.image_size, arrays["scores"] if names else None, names or (),
                      arrays["matrix"].reshape(n, 4, 4), visibility=self._visibility(points, arrays["hands"]))
        weights = Weights(arrays["weights"].astype(float), self.keys.names, self.fps)
        out = self.folder
        save_track(track, out / "track.npz")
        save_keys(self.keys, out / "keys.json")
        save_weights_csv(weights, out / "weights.csv")
        written = [out / "track.npz", out / "keys.json", out / "weights.csv"]
        if track.valid.any():
            self._animation(track, weights, out / "animation.glb")
            written.append(out / "animation.glb")
        save_take_info(out / "take.json", video=Path(str(self.source or "live")), track=track, keys=self.keys)
        return (*written, out / "take.json")

    def _animation(self, track: Track, weights: Weights, path: Path) -> None:
        from ..app import default_character_extras, solve_take
        from ..io import export
        from ..targets import GAZE_NAMES, Mapping, default_character, drive_gaze, retarget, with_gaze_targets

        rig = self.rig if self.rig is not None else with_gaze_targets(default_character(self.keys))
        mapping = self.mapping if self.mapping is not None else \
            Mapping.by_name(self.keys.names, rig.names, allow_extra=self.builtin)  # the gaze targets: no key
        solved = solve_take(track, self.keys, smoothness=0.0)  # head poses and gaze of every frame
        eyes = solved.gaze.rotations() if solved.gaze is not None else None
        anim, colours = retarget(weights, mapping), None
        anim = drive_gaze(anim, mapping, track.blendshapes, track.blendshape_names)  # as keyshape run does
        if self.builtin and set(GAZE_NAMES) <= set(rig.names):  # the stylised head, as keyshape run writes it
            anim, colours = default_character_extras(anim, solved.gaze)
        export(anim, path, rig=rig, poses=solved.poses, eyes=eyes, colours=colours)
