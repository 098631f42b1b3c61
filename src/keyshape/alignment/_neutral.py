"""The neutral frame from the tracker's expression scores, and how sure the choice is.

MediaPipe scores 52 ARKit-style expressions per frame (0 = not at all). The frame of least total
activation among those with the whole face in view is the face most at rest by the tracker's
own reading; gaze (``eyeLook*``) is not an expression and does not count. The median-shape rule
(:func:`keyshape.alignment._procrustes.choose_neutral`) is kept as the check and as the fallback
for tracks without scores: on a take that never rests (the embedded clip smiles throughout) the
median shape is a typical *expression*, not rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..containers import Track
from ._procrustes import choose_neutral, procrustes, to_canonical

__all__ = ["NeutralChoice", "activation", "least_activated", "choose_neutral_frame", "explain_neutral"]

REST_SCORE = 0.3  # a face at rest has no expression score above this
AGREE = 2.0  # the two rules agree when their frames are this close (% of the face scale)


def activation(track: Track) -> tuple[np.ndarray, tuple[int, ...]] | None:
    """``(n_frames,)`` total expression score per frame (NaN without a face) and the scores counted.

    None when the track has no scores. Names starting with ``_`` (MediaPipe's ``_neutral``) and
    the gaze scores ``eyeLook*`` are left out.
    """
    if track.blendshapes is None or not track.blendshape_names:
        return None
    counted = tuple(i for i, n in enumerate(track.blendshape_names) if not n.startswith(("_", "eyeLook")))
    total = track.blendshapes[:, counted].sum(axis=1)
    return np.where(track.valid, total, np.nan), counted


def whole_face_visible(track: Track, regions: dict | None) -> np.ndarray:
    """(n_frames,) bool: a face, and no landmark of the regions (all landmarks if None) hidden
    (visibility below 0.5: a hand over it)."""
    ok = track.valid.copy()
    if track.visibility is None:
        return ok
    for landmarks in (regions or {"face": np.arange(track.n_landmarks)}).values():
        ok &= ~(track.visibility[:, np.asarray(landmarks)] < 0.5).any(axis=1)
    return ok


def least_activated(track: Track, *, regions: dict | None = None) -> int | None:
    """The frame of least total expression score with the whole face in view; None without scores.

    Frames with a hidden region count only when no frame shows the whole face.

    Examples
    --------
    >>> scores = np.array([[0.5, 0.2], [0.1, 0.0], [0.3, 0.3]])
    >>> track = Track(np.zeros((3, 4, 2)), fps=30, blendshapes=scores, blendshape_names=("a", "b"))
    >>> least_activated(track)
    1
    """
    scored = activation(track)
    if scored is None or not track.valid.any():
        return None
    total = scored[0]
    seen = whole_face_visible(track, regions)
    pool = (seen if seen.any() else track.valid) & np.isfinite(total)
    if not pool.any():  # no frame of the pool is scored: the median-shape rule decides
        return None
    return int(np.argmin(np.where(pool, total, np.inf)))


def choose_neutral_frame(track: Track, *, stable: np.ndarray, regions: dict | None = None) -> int:
    """The automatic neutral: :func:`least_activated`, or the median-shape rule without scores."""
    frame = least_activated(track, regions=regions)
    return choose_neutral(track, stable=stable, regions=regions) if frame is None else frame


@dataclass(frozen=True)
class NeutralChoice:
    """Why a frame is the neutral, and how sure that is.

    frame : the neutral frame; rule : "scores", "median" (the automatic rules) or "given";
    check_frame : the other rule's frame (the median-shape rule's; for a median-rule choice the least
    activated frame); distance : the two frames' RMS landmark distance, % of the face scale;
    activation : the neutral's total expression score and ``median_activation`` the take's median
    (None without scores); share_below : share of the frames with the whole face in view that are
    less activated than the neutral; top : its strongest scores (name, value);
    confidence : "high", "medium" or "low"; reason : one sentence saying why
    """

    frame: int
    rule: str
    check_frame: int
    distance: float
    activation: float | None
    median_activation: float | None
    share_below: float | None
    top: tuple[tuple[str, float], ...]
    confidence: str
    reason: str


def explain_neutral(track: Track, frame: int, *, stable: np.ndarray, scale: float, rule: str = "scores",
                    regions: dict | None = None) -> NeutralChoice:
    """Measure the neutral ``frame`` of ``track`` against the take and the median-shape rule.

    ``scale`` is the face's length unit (the inter-ocular distance) in the track's coordinates.
    """
    median = choose_neutral(track, stable=stable, regions=regions)
    if rule == "median":
        median = least_activated(track, regions=regions)
        median = frame if median is None else median
    distance = _distance(track, frame, median, stable) / scale * 100.0
    scored = activation(track)
    if scored is None:
        agree = distance <= AGREE
        return NeutralChoice(frame, rule, median, distance, None, None, None, (), "medium" if agree else "low",
                             f"the track has no expression scores; the median-shape frame {median} is "
                             f"{distance:.1f} % away")
    total, counted = scored
    pool = whole_face_visible(track, regions)
    pool = pool if pool.any() else track.valid
    values = track.blendshapes[frame, list(counted)]
    order = np.argsort(-values)[:3]
    top = tuple((track.blendshape_names[counted[i]], round(float(values[i]), 3)) for i in order)
    share = float((total[pool] < total[frame]).mean())
    at_rest, agree = float(values.max()) <= REST_SCORE, distance <= AGREE
    confidence = "high" if at_rest and agree else "medium" if at_rest or agree else "low"
    reason = (f"its strongest expression score is {top[0][0]} {top[0][1]:.2f}"
              + (" (at rest)" if at_rest else f" (above {REST_SCORE}: the take may never rest)")
              + f"; total {total[frame]:.2f} against the take's median {np.nanmedian(total[pool]):.2f}"
              + f"; the {'least activated' if rule == 'median' else 'median-shape'} frame {median} is {distance:.1f} % "
              f"of the face away"
              + (" (they agree)" if agree else f" (over {AGREE} %: they disagree)"))
    return NeutralChoice(frame, rule, median, distance, float(total[frame]), float(np.nanmedian(total[pool])),
                         share, top, confidence, reason)


def _distance(track: Track, a: int, b: int, stable: np.ndarray) -> float:
    """RMS landmark distance between frames ``a`` and ``b`` after aligning ``b`` onto ``a``."""
    pair = track.points[[b]]
    aligned = to_canonical(pair, procrustes(track.points[a][stable], pair[:, stable]))[0]
    return float(np.sqrt(((aligned - track.points[a]) ** 2).sum(axis=1).mean()))
