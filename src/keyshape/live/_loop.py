"""The live loop: newest frame -> MediaPipe -> causal solve -> every output, until the source ends.

The source decodes in its own thread (on the other core) and keeps only the newest frame, so
the loop never works on a stale one; tracking, solving and sending run here, one frame at a
time. The loop stops when the source ends or fails, on Ctrl-C or SIGTERM, or when
``controls.stop`` is set; every output is closed on the way out (a recording is then written,
whatever further signal comes meanwhile).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..capture import FaceFollower, MediaPipeTracker, TrackerOptions
from ..containers import KeyShapes, Track, Weights
from ..exceptions import InputError, Terminated
from .frame import LiveFrame, Output
from .solver import DEFAULT_SMOOTHING, LiveSolver
from .sources import FrameSource, Mailbox, pin_thread

__all__ = ["run_live", "Controls", "Session", "LiveSummary"]


@dataclass
class Controls:
    """Requests from outside the loop (signal handlers, a key-press thread, tests)."""

    stop: threading.Event = field(default_factory=threading.Event)
    neutral: threading.Event = field(default_factory=threading.Event)


@dataclass
class Session:
    """What :func:`run_live` sends to, made once the key set is known: the outputs, and the
    mapping from key weights to the targets they carry (None: the key names themselves)."""

    outputs: list[Output]
    mapping: object = None


@dataclass
class LiveSummary:
    """How a live session went.

    ``delivered`` frames came from the source after calibration, ``processed`` of them were solved
    and sent, ``dropped`` were replaced by newer ones before the loop could take them.
    ``latency`` and ``detect`` are ``(processed,)`` seconds: frame arrival -> the last output's
    ``send`` returned, and MediaPipe's own share.
    """

    source: str
    fps: float
    keys: KeyShapes | None = None
    delivered: int = 0
    processed: int = 0
    dropped: int = 0
    faces: int = 0
    neutral_captures: int = 0
    seconds: float = 0.0
    ended: str = ""
    error: str | None = None
    latency: np.ndarray = field(default_factory=lambda: np.zeros(0))
    detect: np.ndarray = field(default_factory=lambda: np.zeros(0))


class _Tracker:
    """MediaPipe in VIDEO mode with strictly increasing timestamps, following one face."""

    def __init__(self, tracker: MediaPipeTracker, face: int):
        self.tracker, self.follower = tracker, FaceFollower(face)
        self.last_ms = -1

    def __call__(self, frame):
        ms = max(int(round(frame.time * 1000)), self.last_ms + 1)
        self.last_ms = ms
        chosen = self.follower.pick(self.tracker.detect(frame.rgb, ms))
        return chosen if chosen is not None and chosen.points.shape[0] == 478 else None


def _warm_up(tracker: _Tracker, size) -> None:
    """Load the model's graph before the first real frame (at time 0, before any frame's)."""
    tracker.tracker.detect(np.zeros((size[1], size[0], 3), np.uint8), 0)
    tracker.last_ms = 0


def _warm_up_solver(keys: KeyShapes) -> None:
    """Compile (or load) the solver's kernels before the first real frame."""
    from ..decompose import solve_weights

    solve_weights(Track(keys.neutral[None], 30.0), keys, upper=1.0)


def _calibrate(mailbox: Mailbox, tracker: _Tracker, seconds: float, fps: float, say) -> KeyShapes:
    """Track the first ``seconds`` as a range-of-motion take and discover its key shapes."""
    from ..app import discover_keys

    say(f"calibrating: make every expression you will use for {seconds:g} s (range of motion) ...")
    points, first, seen = [], None, []
    while True:
        frame = mailbox.get(0.1)
        if frame is None:
            if mailbox.closed:
                break
            continue
        first = frame.time if first is None else first
        chosen = tracker(frame)
        points.append(chosen.points if chosen is not None else np.full((478, 3), np.nan))
        seen.append((frame, chosen))
        if frame.time - first >= seconds:
            break
    track = Track(np.array(points) if points else np.zeros((0, 478, 3)), fps)
    if track.n_frames == 0 or track.valid.sum() < 2:
        raise InputError(f"calibration saw {int(track.valid.sum()) if track.n_frames else 0} frames with a face "
                         f"in {seconds:g} s; face the camera and try again")
    keys = discover_keys(track, take="calibration")
    say(f"calibrated on {track.n_frames} frames ({int(track.valid.sum())} with a face): {keys.n_keys} keys")
    return keys, seen


def _replay_calibration(seen, outputs, keys: KeyShapes) -> None:
    """Hand the calibration's frames to the outputs that keep a record (``calibration`` method)."""
    nothing = np.full(keys.n_keys, np.nan)
    for output in outputs:
        if hasattr(output, "calibration"):
            output.calibration([(frame.index, chosen) for frame, chosen in seen], nothing)


def _values(solve, mapping, names, fps, gaze=None) -> np.ndarray:
    """The frame's target values: the key weights through ``mapping``, its gaze targets from the
    frame's scores (``gaze``: a :class:`_Gaze`, None without a ``"gaze"`` section)."""
    keyed = np.nan_to_num(solve.keys, nan=0.0)
    if mapping is None:
        return keyed
    from ..targets import retarget

    values = np.array(retarget(Weights(keyed[None], names, fps), mapping).values[0])
    return gaze(values) if gaze is not None else values


class _Gaze:
    """A mapping's gaze targets (MAP.json's ``"gaze"``) driven by each frame's tracker scores, as
    :func:`keyshape.targets.drive_gaze` does offline: ``clip(score − rest, 0, 1)``; a frame without
    a face holds the last value (offline, the gap is filled from both sides)."""

    def __init__(self, mapping, score_names):
        names = list(score_names)
        entries = [(mapping.targets.index(t), names.index(s), r) for t, s, r in mapping.gaze if s in names]
        self.columns = np.array([c for c, _, _ in entries], dtype=int)
        self.scores = np.array([j for _, j, _ in entries], dtype=int)
        self.rest = np.array([r for _, _, r in entries], dtype=float)
        self.last = np.zeros(len(entries))
        self.chosen = None  # the frame's detection, set before each call

    def __call__(self, values: np.ndarray) -> np.ndarray:
        if self.chosen is not None and len(self.columns):
            self.last = np.clip(np.asarray(self.chosen.scores, dtype=float)[self.scores] - self.rest, 0, 1)
        values[self.columns] = self.last
        return values


def run_live(source: FrameSource, setup: Callable[[KeyShapes], Session], *, keys: KeyShapes | None = None,
             calibrate: float | None = None, upper: float | None = 1.0, smoothing: dict | None = DEFAULT_SMOOTHING,
             tracker_options: TrackerOptions | None = None, face: int = 0, controls: Controls | None = None,
             duration: float | None = None, cores: tuple[int, int] | None = None,
             say: Callable[[str], None] = print) -> LiveSummary:
    """Drive ``setup(keys)``'s outputs from ``source`` until it ends or is stopped.

    Parameters
    ----------
    source : FrameSource (not started)
    setup : called once with the key set; returns the :class:`Session` (outputs and mapping)
    keys : KeyShapes, or None with ``calibrate``: seconds of range of motion to discover them from
    upper, smoothing : the solve's weight bound and One Euro settings (see :class:`LiveSolver`)
    tracker_options, face : MediaPipe's settings and which face to follow (as offline)
    controls : stop / neutral requests; Ctrl-C and SIGTERM stop too
    duration : seconds of live frames after which to stop (None: until the source ends)
    cores : ``(tracking, decoding)``: run MediaPipe (and the loop) on the first core, the source's
        decoding on the second (Linux); None leaves the scheduler free (see BENCHMARKS.md)

    Returns
    -------
    LiveSummary
    """
    if keys is None and not calibrate:
        raise InputError("live needs a key set (--keys) or a calibration (--calibrate SECONDS)")
    run = _Run(source, controls or Controls(), LiveSummary(source.name, source.fps))
    previous_cores = pin_thread(cores[0]) if cores else None  # MediaPipe's threads inherit it
    try:
        with MediaPipeTracker(tracker_options or TrackerOptions()) as mediapipe:
            tracker = _Tracker(mediapipe, face)
            _warm_up(tracker, source.size)
            decoding = cores[1] if cores else None
            seen = None
            if keys is None:
                keys, seen = _calibrate(source.start(cpu=decoding), tracker, float(calibrate), source.fps, say)
            _warm_up_solver(keys)
            run.summary.keys = keys
            session = setup(keys)
            run.outputs = session.outputs
            if seen is not None:
                _replay_calibration(seen, run.outputs, keys)
                source.mailbox.get(timeout=0)  # stale: it arrived while the session was set up
            mailbox = source.mailbox if seen is not None else source.start(cpu=decoding)
            del seen
            solver = LiveSolver(keys, fps=source.fps, upper=upper, smoothing=smoothing)
            run.loop(mailbox, tracker, solver, session, duration)
    except (KeyboardInterrupt, Terminated) as stop:
        run.summary.ended = _stopped(stop)
    finally:
        try:
            run.finish()  # first: a recording is written whatever comes next
        except (KeyboardInterrupt, Terminated) as stop:  # one more signal while it was written: it was
            run.summary.ended = _stopped(stop)
        if previous_cores is not None:
            os.sched_setaffinity(0, previous_cores)
    return run.summary


def _stopped(stop: BaseException) -> str:
    return "stopped (Ctrl-C)" if isinstance(stop, KeyboardInterrupt) else "stopped (SIGTERM)"


class _Run:
    """One session's state: the outputs, the counts and the per-frame timings."""

    def __init__(self, source: FrameSource, controls: Controls, summary: LiveSummary):
        self.source, self.controls, self.summary = source, controls, summary
        self.outputs: list[Output] = []
        self.latency, self.detect = [], []
        self.base = (0, 0)  # the mailbox's (delivered, dropped) when the session started
        self.solver: LiveSolver | None = None
        self.gaze: _Gaze | None = None
        self.start = time.perf_counter()

    def loop(self, mailbox: Mailbox, tracker: _Tracker, solver: LiveSolver, session: Session,
             duration: float | None) -> None:
        self.solver, self.base = solver, (mailbox.delivered, mailbox.dropped)
        self.start = time.perf_counter()
        deadline = self.start + duration if duration else float("inf")
        while not self.controls.stop.is_set() and time.perf_counter() < deadline:
            frame = mailbox.get(0.1)
            if frame is not None:
                self.step(frame, tracker, solver, session)
            elif mailbox.closed:
                break
        ended = "the stream ended" if self.source.kind != "file" else "end of the video"
        self.summary.ended = mailbox.error or (ended if mailbox.closed else "stopped")
        self.summary.error = mailbox.error

    def step(self, frame, tracker: _Tracker, solver: LiveSolver, session: Session) -> None:
        """Track, solve and send one frame."""
        if self.controls.neutral.is_set():
            self.controls.neutral.clear()
            solver.recapture_neutral()
        began = time.perf_counter()
        chosen = tracker(frame)
        self.detect.append(time.perf_counter() - began)
        solve = solver.step(chosen.points if chosen is not None else None)
        keys = solver.keys
        names = session.mapping.targets if session.mapping is not None else keys.names
        gaze = self._gaze(session.mapping, tracker, chosen)
        live = LiveFrame(frame.index, frame.time, frame.arrival, tuple(names),
                         _values(solve, session.mapping, keys.names, self.source.fps, gaze), solve.keys,
                         solve.head, solve.eyes, solve.face, frame.rgb, chosen)
        for output in self.outputs:
            output.send(live)
        self.latency.append(time.perf_counter() - frame.arrival)
        self.summary.faces += solve.face

    def _gaze(self, mapping, tracker: _Tracker, chosen):
        """The :class:`_Gaze` of ``mapping`` (made once the tracker knows its score names), or None."""
        if mapping is None or not mapping.gaze or not tracker.tracker.blendshape_names:
            return None
        if self.gaze is None:
            self.gaze = _Gaze(mapping, tracker.tracker.blendshape_names)
        self.gaze.chosen = chosen
        return self.gaze

    def finish(self) -> None:
        """Stop the source, close every output (a recording is written now), fill in the summary.

        Ctrl-C and SIGTERM wait meanwhile (the common double Ctrl-C): they are acted on once every
        output is closed, so a live take, which cannot be redone, is always written whole."""
        from ..io.atomic import held_signals

        with held_signals(waiting="keyshape: closing the outputs (writing the recording); a moment"):
            self._finish()

    def _finish(self) -> None:
        self.source.stop()
        summary, mailbox = self.summary, self.source.mailbox
        summary.seconds = time.perf_counter() - self.start
        summary.delivered, summary.dropped = mailbox.delivered - self.base[0], mailbox.dropped - self.base[1]
        summary.processed = len(self.latency)
        summary.latency, summary.detect = np.array(self.latency), np.array(self.detect)
        summary.neutral_captures = self.solver.neutral_captures if self.solver is not None else 0
        for output in self.outputs:
            output.close()
