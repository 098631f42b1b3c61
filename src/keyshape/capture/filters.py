"""Temporal clean-up shared by the stages: gaps in a take and the One Euro filter.

The default, recommended path is offline and zero-lag: the solve smooths weights over the whole
sequence (see :mod:`keyshape.decompose._solve`). The One Euro filter is causal, for live-like use; on
MediaPipe's VIDEO-mode landmarks (already smoothed over time) it mostly adds lag.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["find_gaps", "GapReport", "gap_report", "OneEuro", "one_euro", "hold_neutral", "segments", "fill_edges"]


def find_gaps(valid: np.ndarray) -> list[tuple[int, int]]:
    """Runs of missing frames as ``(start, length)``.

    Parameters
    ----------
    valid : (n_frames,) bool, True where a face was found

    Examples
    --------
    >>> find_gaps(np.array([1, 0, 0, 1, 0], dtype=bool))
    [(1, 2), (4, 1)]
    """
    missing = np.concatenate([[0], ~np.asarray(valid, dtype=bool), [0]]).astype(np.int8)
    edges = np.diff(missing)
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(a), int(b - a)) for a, b in zip(starts, stops)]


@dataclass(frozen=True)
class GapReport:
    """Frames without a face, and what the solve does with them.

    Gaps of at most ``max_bridge`` frames that have faces on both sides are bridged by the
    smoothed solve; the others (longer ones, and those at the start or end) hold the neutral pose.
    """

    n_frames: int
    n_missing: int
    gaps: tuple[tuple[int, int], ...]
    max_bridge: int

    @property
    def longest(self) -> int:
        return max((n for _, n in self.gaps), default=0)

    @property
    def bridged(self) -> tuple[tuple[int, int], ...]:
        return tuple(g for g in self.gaps if self._inner(g) and g[1] <= self.max_bridge)

    @property
    def held(self) -> tuple[tuple[int, int], ...]:
        return tuple(g for g in self.gaps if g not in self.bridged)

    def _inner(self, gap: tuple[int, int]) -> bool:
        return gap[0] > 0 and gap[0] + gap[1] < self.n_frames

    def __str__(self) -> str:
        if not self.gaps:
            return "no gaps: a face in every frame"
        return (f"{self.n_missing} of {self.n_frames} frames without a face in {len(self.gaps)} gaps "
                f"(longest {self.longest}); {len(self.bridged)} bridged by the smooth solve, "
                f"{len(self.held)} held at neutral")


def gap_report(valid: np.ndarray, *, max_bridge: int = 12) -> GapReport:
    """Summarise the gaps of a take; ``max_bridge`` is the longest gap to bridge (frames)."""
    valid = np.asarray(valid, dtype=bool)
    return GapReport(len(valid), int((~valid).sum()), tuple(find_gaps(valid)), int(max_bridge))


def hold_neutral(values: np.ndarray, report: GapReport) -> np.ndarray:
    """Weights ``(n_frames, n_channels)`` with the frames of held gaps set to 0 (the neutral)."""
    out = np.array(values, dtype=float)
    for start, length in report.held:
        out[start:start + length] = 0.0
    return out


def segments(report: GapReport) -> list[tuple[int, int]]:
    """``(start, stop)`` runs of frames between the held gaps (each starts and ends with a face):
    a take's solve splits there, since nothing across a held gap is bridged.

    Examples
    --------
    >>> segments(gap_report(np.array([1, 1, 0, 0, 0, 1, 0, 1], dtype=bool), max_bridge=1))
    [(0, 2), (5, 8)]
    """
    held = np.zeros(report.n_frames, dtype=bool)
    for start, length in report.held:
        held[start:start + length] = True
    edges = np.flatnonzero(np.diff(np.concatenate([[1], held.astype(np.int8), [1]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def fill_edges(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Weights ``(n_frames, n_keys)`` with a value in every frame that has a face (``valid (n_frames,)``).

    A region hidden (a hand over the mouth) at the start or end of a run of faces has nothing to
    be bridged from on one side: its weights hold the nearest solved frame's (inside a run the
    smooth solve has bridged them already; this interpolates any that are left).
    """
    missing = valid[:, None] & np.isnan(values)
    if not missing.any():
        return values
    values = values.copy()
    frames = np.arange(len(values))
    for k in np.flatnonzero(missing.any(axis=0)):
        known = np.isfinite(values[:, k])
        values[missing[:, k], k] = np.interp(frames[missing[:, k]], frames[known], values[known, k]) \
            if known.any() else 0.0
    return values


def _alpha(cutoff: np.ndarray | float, rate: float) -> np.ndarray:
    tau = 1.0 / (2 * np.pi * np.asarray(cutoff))
    return 1.0 / (1.0 + tau * rate)


class OneEuro:
    """The One Euro filter (Casiez, Roussel & Vogel, CHI 2012), one sample at a time.

    A first-order low-pass whose cutoff rises with speed: ``fc = min_cutoff + beta·|dx/dt|``,
    so slow motion is smoothed and fast motion follows with little lag. Causal (live-friendly);
    a NaN sample resets the filter.

    Parameters
    ----------
    fps : frame rate
    min_cutoff : Hz, the cutoff at rest; lower = smoother
    beta : speed coefficient; higher = less lag on fast motion
    d_cutoff : Hz, cutoff of the speed estimate
    """

    def __init__(self, fps: float, *, min_cutoff: float = 1.0, beta: float = 0.05, d_cutoff: float = 1.0):
        self.fps, self.min_cutoff, self.beta = float(fps), min_cutoff, beta
        self._a_d = _alpha(d_cutoff, self.fps)
        self._x = self._dx = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Filter one sample (any shape); returns the filtered sample."""
        x = np.asarray(x, dtype=float)
        if np.isnan(x).any():
            self._x = self._dx = None
            return x
        if self._x is None:
            self._x, self._dx = x, np.zeros_like(x)
            return x
        self._dx = self._a_d * (x - self._x) * self.fps + (1 - self._a_d) * self._dx
        a = _alpha(self.min_cutoff + self.beta * np.abs(self._dx), self.fps)
        self._x = a * x + (1 - a) * self._x
        return self._x


def one_euro(points: np.ndarray, fps: float, *, min_cutoff: float = 1.0, beta: float = 0.05,
             d_cutoff: float = 1.0) -> np.ndarray:
    """:class:`OneEuro` over a whole sequence ``(n_frames, ...)``; returns the filtered copy."""
    step = OneEuro(fps, min_cutoff=min_cutoff, beta=beta, d_cutoff=d_cutoff)
    return np.stack([step(x) for x in np.asarray(points, dtype=float)])
