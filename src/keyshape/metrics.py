"""How well key shapes explain a performance.

The reconstruction of a frame is its best *non-negative* blend of the key shapes of each
region (Chuang & Bregler 2002, Eq. 1 in delta form), found by non-negative least squares
(Lawson & Hanson 1974), optionally with the weights bounded above as the product solves them.
Errors are RMS landmark distances in aligned (canonical) units; :func:`face_scale` gives the
length that makes them relative (% of the inter-ocular distance).
"""

from __future__ import annotations

import numpy as np

from .containers import KeyShapes, Track, Weights
from .decompose import check_upper, solve_nnls
from .exceptions import InputError
from .schemes import eye_corners

__all__ = ["face_scale", "reconstruction_error"]


def reconstruction_error(
    aligned: Track, keys: KeyShapes, *, weights: Weights | np.ndarray | None = None,
    upper: float | None = None,
) -> dict[str, float]:
    """RMS reconstruction error of each region of an aligned take.

    ``error_r = sqrt(mean_{f, p in r} |x_fp - x̂_fp|²)`` over the valid frames ``f`` in which the
    region is not hidden (:meth:`keyshape.containers.Track.hidden`) and the region's landmarks
    ``p``, with ``x̂ = neutral + Σ_k w_fk · delta_k``.

    Parameters
    ----------
    aligned : Track
        ``points (n_frames, n_landmarks, d)``, in the key shapes' canonical coordinates.
    keys : KeyShapes
    weights : Weights or (n_frames, n_keys) float, optional, keyword-only
        Per-frame weights to evaluate; frames with NaN weights are skipped. If None, each
        region's weights are the exact non-negative least-squares fit of its keys.
    upper : float or None, keyword-only
        Upper bound of the fitted weights (``0 <= w <= upper``; None for none), when
        ``weights`` is None.

    Returns
    -------
    dict str -> float
        One RMS error per region of ``keys``, in canonical units.

    References
    ----------
    .. [1] C. L. Lawson and R. J. Hanson, *Solving Least Squares Problems*, 1974, ch. 23.

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> from keyshape.alignment._procrustes import align
    >>> from keyshape.keyshapes._search import find_keyshapes
    >>> perf = make_performance(noise=0.0)
    >>> aligned, _ = align(perf.track, reference=perf.neutral, stable=perf.stable)
    >>> keys = find_keyshapes(aligned, regions=perf.regions, n_keys=2, neutral_frame=perf.neutral_frame)
    >>> {r: round(e, 6) for r, e in reconstruction_error(aligned, keys).items()}
    {'upper': 0.0, 'lower': 0.0}
    """
    if aligned.points.shape[1:] != keys.neutral.shape:
        raise InputError(
            f"aligned points {aligned.points.shape[1:]} do not match the key shapes {keys.neutral.shape}"
        )
    fitted = None if weights is None else _check_weights(weights, aligned.n_frames, keys.n_keys)
    upper = check_upper(upper)
    return {region: _region_error(aligned, keys, region, fitted, upper) for region in keys.regions}


def face_scale(neutral: np.ndarray) -> tuple[float, str]:
    """The length errors are measured against, and its unit name.

    The inter-ocular distance (outer eye corners, :func:`keyshape.schemes.eye_corners`,
    in the image plane) when the landmark scheme has eye corners; otherwise twice the RMS
    distance of the landmarks from their centroid (image plane), "face size". The same
    lengths as the take report's (:func:`keyshape.report._take.face_scale`).

    Parameters
    ----------
    neutral : (n_landmarks, n_dims) float

    Returns
    -------
    (length, unit) : (float, str)
        An error ``e`` is ``100 * e / length`` in ``unit``: ``"% inter-ocular"`` or ``"% face size"``.

    Examples
    --------
    >>> face_scale(np.array([[0.0, 0.0], [3.0, 4.0]]))
    (5.0, '% face size')
    """
    neutral = np.asarray(neutral, dtype=float)
    corners = eye_corners(len(neutral))
    if corners is not None:
        length = float(np.linalg.norm(neutral[corners[0], :2] - neutral[corners[1], :2]))
        if length > 0:
            return length, "% inter-ocular"
    xy = neutral[:, :2]
    return float(2 * np.sqrt(((xy - xy.mean(axis=0)) ** 2).sum(axis=1).mean())), "% face size"


def _check_weights(weights, n_frames: int, n_keys: int) -> np.ndarray:
    values = np.asarray(weights.values if isinstance(weights, Weights) else weights, dtype=float)
    if values.shape != (n_frames, n_keys):
        raise InputError(f"weights must have shape ({n_frames}, {n_keys}); got {values.shape}")
    return values


def _region_error(aligned: Track, keys: KeyShapes, region: str, weights, upper) -> float:
    """RMS error ``sqrt(mean |x - x̂|²)`` on one region's landmarks."""
    lm, k = keys.regions[region], keys.keys_of(region)
    ok = aligned.valid & ~aligned.hidden(lm)  # the tracker's guesses under a hand are not the face
    ok = ok if weights is None else ok & np.isfinite(weights[:, k]).all(axis=1)
    targets = (aligned.points[ok][:, lm] - keys.neutral[lm]).reshape(ok.sum(), -1)
    bases = keys.deltas[k][:, lm].reshape(len(k), -1)
    if targets.size == 0:
        return float("nan")
    w = solve_nnls(bases.T, targets, upper=upper) if weights is None else weights[ok][:, k]
    residual = targets - w @ bases
    return float(np.sqrt((residual**2).sum() / (targets.shape[0] * len(lm))))
