"""Per-landmark visibility from the video: a hand over the face.

MediaPipe places all 478 landmarks in every frame, also under a hand, and says nothing about it.
A landmark counts as hidden only on evidence of an occluder: a hand that MediaPipe's hand
landmarker (:class:`~keyshape.capture.mediapipe.HandTracker`, run on every tracked frame) finds
in front of it. Everything else counts as seen, so a take with no hand in it gets no visibility
below 1 and gives exactly the keys, neutral and weights it gives with no visibility at all.

**The hand's silhouette** (:func:`hand_cover`) is drawn from its 21 landmarks: the convex hull of
the wrist and the four fingers (the palm and the fingers held together, as they are over a mouth
or an eye), widened by ``HAND_RADIUS`` of the knuckle span (the fingers' half-width), and the
thumb's bones as capsules of the same radius. A landmark inside it is hidden (visibility 0).
A hand near the face is taken to be in front of it (a hand behind the head is not seen).

Why not appearance. The estimate this replaces scored how *unusual* each landmark's colour patch
looked against the take's typical frames. Tuned on the embedded clip, on takes without any
occluder it read strong expressions, head turns and light as hidden (a third of the frames), and
because key discovery, the neutral, the error measures and the solve trust visibility, every
route got worse. An occluder's own evidence does not move with the face's expression: on the
occlusion benchmark (``benchmarks/bench_occlusion.py``, docs/occlusion.md) no region of any
unoccluded take is hidden in any frame. Objects that are not hands (a cup, a microphone) are not
found: they count as seen.

``HAND_RADIUS`` was chosen on the embedded clip's labels (``benchmarks/occlusion_labels.json``);
every other take of the benchmark is measured only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["estimate_visibility", "visibility_from_hands", "hand_cover", "hand_mask", "hand_picture", "VISIBILITY_MODES",
           "HAND_RADIUS", "FINGERS", "THUMB"]

VISIBILITY_MODES = ("auto", "off")  # --visibility: hands found in front of the face, or none estimated
HAND_RADIUS = 0.15  # the fingers' half-width, of the knuckle span (index to little finger knuckle)
KNUCKLES = (5, 17)  # MediaPipe's index and little finger knuckles (MCP)
FINGERS = (0, *range(5, 21))  # the wrist and the four fingers: their hull is the palm and the fingers together
THUMB = (1, 2, 3, 4)  # the thumb's chain from its base (after the wrist, 0)


def _hull(points: np.ndarray) -> np.ndarray:
    """Convex hull of ``points`` (n, 2), counter-clockwise (Andrew's monotone chain) -> (m, 2)."""
    p = points[np.lexsort((points[:, 1], points[:, 0]))]

    def half(seq):
        out: list[np.ndarray] = []
        for q in seq:
            while len(out) >= 2 and _turn(out[-2], out[-1], q) <= 0:
                out.pop()
            out.append(q)
        return out[:-1]

    return np.array(half(p) + half(p[::-1]))


def _turn(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """z of (a - o) x (b - o): > 0 for a left turn."""
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _inside(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Whether each of ``points`` (n, 2) lies inside the convex ``polygon`` (m, 2), counter-clockwise."""
    if len(polygon) < 3:
        return np.zeros(len(points), bool)
    edge = np.roll(polygon, -1, axis=0) - polygon  # (m, 2)
    rel = points[:, None, :] - polygon[None]  # (n, m, 2)
    return (edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0] >= 0).all(axis=1)


def _near_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """Whether each of ``points`` (n, 2) is within ``radius`` of any segment ``a[k]``-``b[k]`` (k, 2)."""
    ab = b - a  # (k, 2)
    t = np.einsum("nkd,kd->nk", points[:, None] - a[None], ab) / np.maximum((ab ** 2).sum(axis=1), 1e-12)
    nearest = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]  # (n, k, 2)
    return (((points[:, None] - nearest) ** 2).sum(axis=2) <= radius ** 2).any(axis=1)


def hand_cover(points: np.ndarray, hand: np.ndarray) -> np.ndarray:
    """Which landmarks one hand covers.

    Parameters
    ----------
    points : (n_landmarks, >= 2) float, one frame's landmarks in pixels
    hand : (21, 2) float, MediaPipe's hand landmarks in the same pixels

    Returns
    -------
    (n_landmarks,) bool: inside the hull of the wrist and fingers or near the thumb, widened by
    ``HAND_RADIUS`` knuckle spans.

    Examples
    --------
    >>> hand = np.zeros((21, 2)); hand[5], hand[17] = (0.0, 0.0), (30.0, 0.0)
    >>> hand[[6, 7, 8]] = (0, -20), (0, -40), (0, -60); hand[[18, 19, 20]] = (30, -20), (30, -40), (30, -60)
    >>> hand[0] = (15.0, 30.0)
    >>> hand_cover(np.array([[15.0, -30.0], [80.0, -30.0], [34.0, -30.0]]), hand).tolist()
    [True, False, True]
    """
    xy = np.asarray(points, dtype=float)[:, :2]
    hand = np.asarray(hand, dtype=float)[:, :2]
    radius = HAND_RADIUS * float(np.linalg.norm(hand[KNUCKLES[0]] - hand[KNUCKLES[1]]))
    hull = _hull(hand[list(FINGERS)])
    thumb = hand[[0, *THUMB]]
    starts = np.concatenate([hull, thumb[:-1]])
    ends = np.concatenate([np.roll(hull, -1, axis=0), thumb[1:]])
    return _inside(xy, hull) | _near_segments(xy, starts, ends, radius)


def visibility_from_hands(points: np.ndarray, hands: np.ndarray) -> np.ndarray | None:
    """Visibility of a take's landmarks from the hands found in its frames.

    Parameters
    ----------
    points : (n_frames, n_landmarks, 2 or 3) float, the track's pixels (NaN frames: no face); only
        the frames with a hand are read, so it may be a memory map
    hands : (n_frames, n_hands, 21, 2) float, each frame's hands in the same pixels (NaN rows: no
        hand), as :class:`~keyshape.capture.mediapipe.HandTracker` gives them

    Returns
    -------
    (n_frames, n_landmarks) float32: 0 where a hand covers the landmark (:func:`hand_cover`), 1
    elsewhere; None when no hand covers any landmark of any frame (the track then has no
    visibility: everything is seen).
    """
    hands = np.asarray(hands)
    found = np.isfinite(hands).all(axis=(2, 3))  # (n_frames, n_hands)
    frames = np.flatnonzero(found.any(axis=1))
    if not len(frames):
        return None
    seen = None
    for i in frames:
        pts = np.asarray(points[i], dtype=float)
        if not np.isfinite(pts[:, :2]).all():
            continue
        hidden = np.zeros(len(pts), bool)
        for k in np.flatnonzero(found[i]):
            hidden |= hand_cover(pts, hands[i, k])
        if hidden.any():
            if seen is None:
                seen = np.ones(points.shape[:2], np.float32)
            seen[i, hidden] = 0.0
    return seen


def estimate_visibility(path: str | Path, points: np.ndarray, *, start: int = 0, end: int | None = None,
                        fps: float | None = None) -> np.ndarray | None:
    """Per-landmark visibility of a tracked take, read again from its video.

    Parameters
    ----------
    path : the video (or image folder) the track was made from
    points : (n_frames, n_landmarks, 2 or 3) float, its track in pixels (NaN frames: no face);
        row i is the i-th frame decoded with ``start``, ``end`` and ``fps``, as in tracking
    start, end, fps : the range and rate the track was made with

    Returns
    -------
    visibility : (n_frames, n_landmarks) float32 in {0, 1}, or None when no hand covers the face
    (:func:`visibility_from_hands`). Tracking finds the hands as it goes (``keyshape track``):
    this is for a track made without them.
    """
    from .mediapipe import N_HAND_POINTS, N_HANDS, HandTracker
    from .video import iter_frames

    points = np.asarray(points)
    hands = np.full((len(points), N_HANDS, N_HAND_POINTS, 2), np.nan, np.float32)
    with HandTracker() as tracker:
        for i, (ms, rgb) in zip(range(len(points)), iter_frames(path, start=start, end=end, fps=fps)):
            if np.isfinite(points[i]).all():
                hands[i] = tracker.detect(rgb, ms, points[i])
    return visibility_from_hands(points, hands)


def hand_mask(shape: tuple[int, int], hand: np.ndarray) -> np.ndarray:
    """(height, width) bool: the pixels of a picture of ``shape`` under the silhouette of ``hand``
    (21, 2) (:func:`hand_cover`, every pixel centre taken as a landmark)."""
    height, width = shape
    grid = np.stack(np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float)), axis=-1)
    return hand_cover(grid.reshape(-1, 2), hand).reshape(height, width)


def hand_picture(path: str | Path, frame: int, *, since: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``frame`` of a video and its hand's silhouette, to cut out (:func:`keyshape.datasets.cut_out`)
    and paste onto other takes: occluders composited at known places, for the occlusion benchmark
    and the tests.

    The hand landmarker follows the hand from frame ``since`` on (a hand lying on a face is found
    by following it from where it came into the picture). Returns ``rgb`` (h, w, 3) uint8 and
    ``mask`` (h, w) bool; ValueError when no hand is found in ``frame``.
    """
    from .mediapipe import HandTracker
    from .video import iter_frames

    with HandTracker() as tracker:
        for at, (ms, rgb) in enumerate(iter_frames(path, start=since, end=frame + 1), start=since):  # noqa: B007
            hands = tracker.detect(rgb, ms)
    found = np.flatnonzero(np.isfinite(hands[:, 0, 0]))
    if at != frame or not len(found):
        raise ValueError(f"{path}: no hand found in frame {frame}")
    return rgb, hand_mask(rgb.shape[:2], hands[found[0]])
