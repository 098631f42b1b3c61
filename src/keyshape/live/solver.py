"""The causal solve: one frame in, its weights, head and eyes out, with bounded lag.

Every frame is aligned onto the key set's neutral (Umeyama on the stable points, as offline),
decomposed by the same bounded per-frame NNLS as ``keyshape solve --smooth 0``
(:func:`keyshape.decompose.solve_weights`), then smoothed by a One Euro filter on the weights
(Casiez et al. 2012; :class:`keyshape.capture.filters.OneEuro`). The filter is a first-order
low-pass whose cutoff rises with the weights' speed, ``fc = min_cutoff + beta·|dw/dt|``; its
delay is largest at rest and never exceeds that of the resting low-pass,
``1 / (2π · min_cutoff)`` seconds (53 ms at the default 3 Hz; ~1.3 frames at 24 fps), and it
shrinks on fast motion. ``smoothing=None`` sends the raw per-frame solve (no lag, all the
tracker's jitter). The defaults were chosen by measurement against the offline zero-lag solve
(``benchmarks/bench_live.py``, BENCHMARKS.md).

Frames without a face hold the last pose for ``hold`` seconds, then return to the neutral.
``recapture_neutral()`` takes the next face as the new neutral: its shape offsets every later
frame (the key deltas stay), its head rotation becomes the rest pose, its gaze straight ahead.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..alignment import align
from ..capture.filters import OneEuro
from ..capture.gaze import estimate_gaze
from ..containers import KeyShapes, Track
from ..decompose import solve_weights
from ..defaults import DEFAULT_UPPER
from ..schemes import head_rotations, rotations_to_gltf, stable_points
from .frame import IDENTITY

__all__ = ["LiveSolver", "Solve", "DEFAULT_SMOOTHING"]

# One Euro settings on the weights (Hz, s): chosen in benchmarks/bench_live.py
DEFAULT_SMOOTHING = {"min_cutoff": 3.0, "beta": 0.3}


class Solve:
    """One frame's result: ``keys (n_keys,)`` weights (NaN until a face is seen), ``head (4,)`` and
    ``eyes (2, 4)`` or None as glTF-axis quaternions, ``face`` whether this frame had one."""

    __slots__ = ("eyes", "face", "head", "keys", "raw")

    def __init__(self, keys, raw, head, eyes, face):
        self.keys, self.raw, self.head, self.eyes, self.face = keys, raw, head, eyes, face


class LiveSolver:
    """Per-frame bounded NNLS on a key set, then a One Euro filter on the weights.

    Parameters
    ----------
    keys : KeyShapes
    fps : float
        The source's frame rate (the filter's sampling rate).
    upper : float or None
        Weight bound, as offline.
    smoothing : dict or None
        ``{"min_cutoff": Hz, "beta": s}`` of the One Euro filter (:data:`DEFAULT_SMOOTHING`), or
        None for the raw per-frame solve.
    hold : float
        Seconds to hold the last pose when the face is lost, before returning to the neutral.
    """

    def __init__(self, keys: KeyShapes, *, fps: float, upper: float | None = DEFAULT_UPPER,
                 smoothing: dict | None = DEFAULT_SMOOTHING, hold: float = 0.5):
        self.keys, self.fps, self.upper = keys, float(fps), upper
        self.stable = keys.stable if keys.stable is not None else stable_points(keys.n_landmarks)
        self.smoothing = smoothing
        self._filter = OneEuro(self.fps, **smoothing) if smoothing is not None else None
        self._hold = max(int(round(hold * self.fps)), 0)
        self._offset = np.zeros_like(keys.neutral)
        self._rest = np.eye(3)
        self._recapture = False
        self._missing = 0
        self._last: Solve | None = None
        self.neutral_captures = 0

    def recapture_neutral(self) -> None:
        """Take the next frame with a face as the new neutral (thread-safe: a flag)."""
        self._recapture = True

    def step(self, points: np.ndarray | None) -> Solve:
        """Solve one frame: ``points (n_landmarks, 3)`` in pixels, or None when no face was found."""
        if points is None:
            return self._no_face()
        aligned, poses = align(Track(points[None], self.fps), reference=self.keys.neutral, stable=self.stable)
        shape = aligned.points[0]
        if not np.isfinite(shape).all():
            return self._no_face()
        rotation = head_rotations(poses)[0]
        if self._recapture:
            self._offset = shape - self.keys.neutral
            self._rest = rotation
            self._recapture = False
            self.neutral_captures += 1
            if self._filter is not None:
                self._filter(np.full(1, np.nan))  # restart the filter from the new neutral
        raw = solve_weights(Track((shape - self._offset)[None], self.fps), self.keys, upper=self.upper).values[0]
        weights = self._smooth(raw)
        head = Rotation.from_matrix(rotation @ self._rest.T).as_quat()
        self._missing = 0
        self._last = Solve(weights, raw, head, self._eyes(shape), True)
        return self._last

    def _smooth(self, raw: np.ndarray) -> np.ndarray:
        if self._filter is None:
            return raw
        smooth = self._filter(raw)
        return np.clip(smooth, 0.0, self.upper if self.upper is not None else np.inf)

    def _eyes(self, shape: np.ndarray) -> np.ndarray | None:
        if self.keys.n_landmarks != 478:
            return None
        gaze = estimate_gaze(shape[None], reference=self.keys.neutral + self._offset)
        eyes = rotations_to_gltf(gaze.rotations()[0])  # (2, 3, 3), left eye first
        return Rotation.from_matrix(eyes).as_quat()

    def _no_face(self) -> Solve:
        self._missing += 1
        if self._filter is not None:
            self._filter(np.full(1, np.nan))
        if self._last is not None and self._missing <= self._hold:
            last = self._last
            return Solve(last.keys, last.raw, last.head, last.eyes, False)
        zeros = np.zeros(self.keys.n_keys) if self._last is not None else np.full(self.keys.n_keys, np.nan)
        return Solve(zeros, zeros, IDENTITY.copy(), None, False)
