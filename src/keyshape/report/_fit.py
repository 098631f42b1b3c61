"""Fit quality of a take: how well the solved weights reproduce the aligned landmarks.

:func:`fit_quality` measures, per frame and region, the aligned landmarks ``x`` against
the blend the weights reach, ``x̂ = neutral + Σ_k w_k δ_k`` (Chuang & Bregler 2002, Eq. 1):

* **error** — RMS over the region's landmarks of ``|x − x̂|``, in % of the inter-ocular
  distance (outer eye corners of the neutral shape, :func:`keyshape.schemes.eye_corners`).
* **cost of w ≥ 0** — ``sqrt(error² − error_ls²)`` where ``error_ls`` is the residual of the
  best *unconstrained* blend of the same keys. Both fits lie in the span of the key deltas,
  so by Pythagoras this is the distance from the reached blend to the best linear one: the
  part of the error due to the non-negativity (and any bounds or smoothing) of the weights.
* **outside the hull** — a frame whose cost of w ≥ 0 exceeds ``tolerance`` (default 1.5 %
  of the inter-ocular distance, about the tracker's jitter): the key shapes could only
  reach it with negative weights, so it lies outside the cone the key shapes span from the
  neutral. Such frames are the ones an extra key shape would fix.

:func:`take_numbers` sums these up with the track's detection and gap counts into the
JSON-ready numbers of :mod:`keyshape.report._take`. No I/O here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..capture.filters import find_gaps
from ..containers import KeyShapes, Track, Weights
from ..exceptions import InputError
from ..metrics import face_scale as metrics_face_scale

__all__ = ["FitQuality", "fit_quality", "face_scale", "gap_runs", "take_numbers", "HULL_TOLERANCE"]

HULL_TOLERANCE = 1.5  # % of the inter-ocular distance


@dataclass(frozen=True, eq=False)
class FitQuality:
    """Per-frame fit quality of each region.

    Attributes
    ----------
    error : dict str -> (n_frames,) float
        RMS landmark residual, in ``unit``; NaN where the frame has no face or no weights.
    excess : dict str -> (n_frames,) float
        The part of ``error`` due to the constraints on the weights (cost of w ≥ 0), in ``unit``.
    outside : dict str -> (n_frames,) bool
        ``excess > tolerance``: the frame lies outside the key-shape hull of the region.
    scale : float
        The length that is 100 ``unit`` (inter-ocular distance), in aligned coordinates.
    unit : str
    tolerance : float
    """

    error: dict[str, np.ndarray]
    excess: dict[str, np.ndarray]
    outside: dict[str, np.ndarray]
    scale: float
    unit: str = "% inter-ocular"
    tolerance: float = HULL_TOLERANCE
    regions: tuple[str, ...] = field(default=())


def face_scale(keys: KeyShapes) -> tuple[float, str]:
    """(length, unit) errors are measured against: :func:`keyshape.metrics.face_scale` of the neutral."""
    return metrics_face_scale(keys.neutral)


def fit_quality(aligned: Track, keys: KeyShapes, weights: Weights, *,
                tolerance: float = HULL_TOLERANCE) -> FitQuality:
    """Per-frame reconstruction error, cost of the non-negativity, and frames outside the hull.

    Parameters
    ----------
    aligned : Track
        ``points (n_frames, n_landmarks, d)`` in the key shapes' canonical coordinates.
    keys : KeyShapes
    weights : Weights
        ``values (n_frames, n_keys)`` with a column for every key name (any order).
    tolerance : float, keyword-only
        Cost of w ≥ 0 above which a frame counts as outside the hull, in % of the inter-ocular distance.

    Returns
    -------
    FitQuality

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> from keyshape.alignment._procrustes import align
    >>> from keyshape.keyshapes._search import find_keyshapes
    >>> perf = make_performance(noise=0.0)
    >>> aligned, _ = align(perf.track, reference=perf.neutral, stable=perf.stable)
    >>> keys = find_keyshapes(aligned, regions=perf.regions, n_keys=2, neutral_frame=perf.neutral_frame)
    >>> w = Weights(np.zeros((aligned.n_frames, keys.n_keys)), keys.names, 30.0)
    >>> fit = fit_quality(aligned, keys, w)
    >>> sorted(fit.error), fit.error["upper"].shape
    (['lower', 'upper'], (200,))
    """
    if aligned.points.shape[1:] != keys.neutral.shape:
        raise InputError(f"aligned points {aligned.points.shape[1:]} do not match the key shapes "
                         f"{keys.neutral.shape}")
    values = _key_columns(weights, keys, aligned.n_frames)
    scale, unit = face_scale(keys)
    error, excess = {}, {}
    for region in keys.regions:
        error[region], excess[region] = _region_fit(aligned.points, keys, region, values, 100 / scale)
    outside = {r: np.nan_to_num(excess[r]) > tolerance for r in keys.regions}
    return FitQuality(error, excess, outside, scale, unit, float(tolerance), tuple(keys.regions))


def _key_columns(weights: Weights, keys: KeyShapes, n_frames: int) -> np.ndarray:
    """(n_frames, n_keys) weights in key order."""
    missing = [n for n in keys.names if n not in weights.names]
    if missing or weights.n_frames != n_frames:
        raise InputError(f"weights must have {n_frames} frames and a column per key; got "
                         f"{weights.n_frames} frames, missing {missing}")
    return weights.values[:, [weights.names.index(n) for n in keys.names]]


def _region_fit(points, keys: KeyShapes, region: str, values, to_unit: float):
    """(error, excess) ``(n_frames,)`` of one region, in the report's unit."""
    lm, k = keys.regions[region], keys.keys_of(region)
    targets = points[:, lm] - keys.neutral[lm]  # (n_frames, n_region_landmarks, d)
    bases = keys.deltas[k][:, lm]  # (n_region_keys, n_region_landmarks, d)
    # f: frame, k: key, p: landmark, d: dimension
    reached = np.einsum("fk,kpd->fpd", values[:, k], bases)
    error = np.sqrt(((targets - reached) ** 2).sum(axis=2).mean(axis=1))
    flat_t, flat_b = targets.reshape(len(targets), -1), bases.reshape(len(k), -1)
    ok = np.isfinite(flat_t).all(axis=1)
    best = np.full(len(targets), np.nan)
    if ok.any() and len(k):
        w_ls = np.linalg.lstsq(flat_b.T, flat_t[ok].T, rcond=None)[0].T  # min |t − wᵀB|, no constraints
        best[ok] = np.sqrt(((flat_t[ok] - w_ls @ flat_b) ** 2).sum(axis=1) / len(lm))
    elif ok.any():
        best[ok] = error[ok]
    excess = np.sqrt(np.maximum(error**2 - best**2, 0.0))
    return error * to_unit, excess * to_unit


def gap_runs(valid: np.ndarray) -> tuple[int, int]:
    """(number of runs of frames without a face, length of the longest run).

    Examples
    --------
    >>> gap_runs(np.array([True, False, False, True, False]))
    (2, 2)
    """
    gaps = find_gaps(valid)
    return len(gaps), max((n for _, n in gaps), default=0)


def take_numbers(track: Track, keys: KeyShapes, fit: FitQuality, *, take: str = "") -> dict:
    """The report's numbers as a JSON-ready dict: frames, detection, gaps, K, errors per region.

    ``keys.frames`` and ``neutral_frame`` are rows of the track; ``key_frames`` gives, per key,
    the video's own frame number and time (``track.frame_index``, ``track.time``: they differ under
    ``--start``), or None for a key from another take than ``take``.
    """
    n_gaps, longest = gap_runs(track.valid)
    regions = {}
    for region in keys.regions:
        err = fit.error[region][np.isfinite(fit.error[region])]
        regions[region] = {
            "keys": int(len(keys.keys_of(region))),
            "landmarks": int(len(keys.regions[region])),
            "rms_error": _round(np.sqrt(np.mean(err**2))) if err.size else None,
            "p95_error": _round(np.percentile(err, 95)) if err.size else None,
            "max_error": _round(err.max()) if err.size else None,
            "frames_outside_hull": int(fit.outside[region].sum()),
        }
    return {
        "frames": track.n_frames, "fps": _round(track.fps, 3), "duration_s": _round(track.n_frames / track.fps, 2),
        "frames_with_face": int(track.valid.sum()),
        "detection_rate": _round(track.valid.mean() * 100 if track.n_frames else 0.0, 2),
        "gaps": n_gaps, "longest_gap_frames": longest, "longest_gap_s": _round(longest / track.fps, 2),
        "neutral_frame": int(keys.neutral_frame), "method": keys.method, "n_keys": keys.n_keys,
        "error_unit": fit.unit, "hull_tolerance": fit.tolerance, "regions": regions,
        "neutral": neutral_numbers(track, keys), "hidden": hidden_numbers(track, keys),
        "key_frames": [_video_frame(track, int(f), keys.takes[k], take) for k, f in enumerate(keys.frames)],
        "neutral_video_frame": _video_frame(track, int(keys.neutral_frame), keys.neutral_take, take),
    }


def _video_frame(track: Track, row: int, source: str, take: str) -> dict | None:
    """``{"frame": the video's frame number, "time": s}`` of a track row of this take, else None."""
    if (source and take and source != take) or not 0 <= row < track.n_frames:
        return None
    return {"frame": int(track.frame_index[row]), "time": _round(float(track.time[row]), 3)}


def neutral_numbers(track: Track, keys: KeyShapes) -> dict | None:
    """How sure the neutral frame is (:func:`keyshape.alignment.explain_neutral`); None when it is not
    a frame of this take (a key set from another take)."""
    from ..alignment import choose_neutral, choose_neutral_frame, explain_neutral
    from ..schemes import stable_points

    frame = int(keys.neutral_frame)
    if keys.neutral_take and keys.neutral_take not in keys.takes:  # from a separate clip of the actor at rest
        return {"frame": frame, "rule": "clip", "take": keys.neutral_take, "confidence": "given",
                "reason": f"the median aligned shape of {keys.neutral_take}, a separate clip of the actor at rest"}
    if not 0 <= frame < track.n_frames or not track.valid[frame] or track.valid.sum() < 2:
        return None
    stable = keys.stable if keys.stable is not None else stable_points(track.n_landmarks)
    rule = ("scores" if frame == choose_neutral_frame(track, stable=stable, regions=keys.regions) else
            "median" if frame == choose_neutral(track, stable=stable, regions=keys.regions) else "given")
    c = explain_neutral(track, frame, stable=stable, scale=metrics_face_scale(track.points[frame])[0], rule=rule,
                        regions=keys.regions)
    return {"frame": c.frame, "rule": c.rule, "confidence": c.confidence, "reason": c.reason,
            "check_frame": c.check_frame, "distance": _round(c.distance, 2), "activation": _round(c.activation),
            "median_activation": _round(c.median_activation), "share_below": _round(c.share_below),
            "top": [list(t) for t in c.top]}


def hidden_numbers(track: Track, keys: KeyShapes) -> dict:
    """Per region, the frames whose region is hidden (more than 30 % of its landmarks below visibility 0.5)."""
    out = {}
    for region, landmarks in keys.regions.items():
        hidden = (track.seen[:, landmarks] < 0.5).mean(axis=1) > 0.3
        out[region] = {"frames": int(hidden.sum()), "share": _round(hidden.mean() if track.n_frames else 0.0)}
    return out


def _round(value, digits: int = 3):
    return None if value is None or not np.isfinite(value) else round(float(value), digits)
