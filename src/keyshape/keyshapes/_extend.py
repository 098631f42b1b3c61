"""Extending a key set to a new take: the fewest new keys that bring it within the error target.

The artist has sculpted a target per key; a new take shows expressions the keys cannot blend.
:func:`extend_keyshapes` keeps every key (name, shape, source) and adds, per region, frames of
the new take one at a time until the take's RMS reconstruction error (best bounded blend,
``0 ≤ w ≤ upper``, as :func:`keyshape.metrics.reconstruction_error`) is below ``max_error`` % of
the inter-ocular distance. Each step adds the best of three proposals, as ``spa`` grows
(:func:`keyshape.keyshapes._select.spa_steps`): the frame farthest from the keys' span, the frame of
largest first-order gain, and the worst-explained frame; only strong frames qualify
(``_select.MIN_STRENGTH`` of the take's 95th-percentile delta). The old keys never move.
"""

from __future__ import annotations

import numpy as np

from ..containers import KeyShapes, Track
from ..defaults import DEFAULT_UPPER, MAX_ERROR, MAX_KEYS
from ..exceptions import InputError
from ..metrics import face_scale
from . import _select
from ._search import MAX_CANDIDATES, _check_target

__all__ = ["extend_keyshapes", "region_errors"]


def region_errors(keys: KeyShapes, aligned: Track, *, upper: float | None = DEFAULT_UPPER) -> dict[str, np.ndarray]:
    """Per region, each frame's RMS error (% of the inter-ocular distance) of its best blend.

    Parameters
    ----------
    keys : KeyShapes
    aligned : Track ``(n_frames, n_landmarks, n_dims)`` aligned onto ``keys.neutral``

    Returns
    -------
    dict region -> (n_frames,) float, NaN where the track has no face or the region is hidden
    (:meth:`keyshape.containers.Track.hidden`)
    """
    from ..decompose import solve_nnls

    scale, _ = face_scale(keys.neutral)
    valid = np.flatnonzero(aligned.valid)
    out = {}
    for region, landmarks in keys.regions.items():
        error = np.full(aligned.n_frames, np.nan)
        x = (aligned.points[np.ix_(valid, landmarks)] - keys.neutral[landmarks]).reshape(len(valid), -1)
        rows = keys.keys_of(region)
        if len(rows):
            basis = keys.deltas[np.ix_(rows, landmarks)].reshape(len(rows), -1)
            w = solve_nnls(basis.T, x, upper=upper)
            x = x - w @ basis
        error[valid] = 100 * np.sqrt((x**2).sum(axis=1) / len(landmarks)) / scale
        error[aligned.hidden(landmarks)] = np.nan
        out[region] = error
    return out


def extend_keyshapes(keys: KeyShapes, aligned: Track, *, max_error: float = MAX_ERROR, max_keys: int = MAX_KEYS,
                     upper: float | None = DEFAULT_UPPER, take: str = "") -> tuple[KeyShapes, dict[str, list[float]]]:
    """``keys`` and the fewest frames of ``aligned`` per region that bring it below ``max_error``.

    Parameters
    ----------
    keys : KeyShapes, the key set the artist has sculpted
    aligned : Track, the new take aligned onto ``keys.neutral``
    max_error : target RMS error, % of the inter-ocular distance, per region over the take
    max_keys : most keys added per region
    upper : the weight bound
    take : the new take's name, recorded with its keys

    Returns
    -------
    (KeyShapes, curves)
        The extended set: every old key first, unchanged, then per region the new keys
        (``frames`` in ``aligned``, named ``f"{region}_{i:02d}"`` after the region's highest
        number); ``curves[region]`` the take's RMS error with 0, 1, 2, … keys added.
    """
    max_error, max_keys = _check_target(max_error, max_keys)
    if (aligned.n_landmarks, aligned.n_dims) != (keys.n_landmarks, keys.n_dims):
        raise InputError(f"the take has {aligned.n_landmarks} landmarks in {aligned.n_dims}D but the key set "
                         f"{keys.n_landmarks} in {keys.n_dims}D")
    valid = np.flatnonzero(aligned.valid)
    if not len(valid):
        raise InputError("the take has no frame with a face to extend the keys with")
    bound = upper
    scale, _ = face_scale(keys.neutral)
    names, used = set(keys.names), {}
    new: list[tuple[str, int, str]] = []  # (region, frame, name)
    curves = {}
    for region, landmarks in keys.regions.items():
        seen = valid[~aligned.hidden(landmarks)[valid]]  # no key (and no error) from under a hand
        seen = seen if len(seen) else valid
        data = (aligned.points[np.ix_(seen, landmarks)] - keys.neutral[landmarks]).reshape(len(seen), -1)
        rows = keys.keys_of(region)
        basis = keys.deltas[np.ix_(rows, landmarks)].reshape(len(rows), -1)
        picks, curve = _grow_from(basis, data, bound, max_error, max_keys,
                                  to_percent=100.0 / (scale * np.sqrt(len(seen) * len(landmarks))))
        curves[region] = curve
        for pick in picks:
            name = _next_name(region, names, used)
            new.append((region, int(seen[pick]), name))
    if not new:
        return keys, curves
    deltas, frames = list(keys.deltas), list(keys.frames)
    regions_of, takes, all_names = list(keys.key_regions), list(keys.takes), list(keys.names)
    for region, frame, name in new:
        delta = np.zeros_like(keys.neutral)
        landmarks = keys.regions[region]
        delta[landmarks] = aligned.points[frame, landmarks] - keys.neutral[landmarks]
        deltas.append(delta)
        frames.append(frame)
        regions_of.append(region)
        takes.append(take)
        all_names.append(name)
    order = np.argsort([list(keys.regions).index(r) for r in regions_of], kind="stable")
    pick = lambda seq: tuple(seq[i] for i in order)  # noqa: E731
    return KeyShapes(keys.neutral, np.array(deltas)[order], pick(all_names), np.array(frames)[order],
                     pick(regions_of), keys.regions, pick(takes), keys.neutral_frame, keys.neutral_take,
                     keys.method, keys.stable, pick(list(keys.mirror_of) + [""] * len(new))), curves


def _grow_from(basis: np.ndarray, data: np.ndarray, upper, max_error: float, max_keys: int, *,
               to_percent: float) -> tuple[list[int], list[float]]:
    """Rows of ``data`` added greedily to the fixed ``basis`` rows; the error after each addition."""
    pool = _select.pool(data, MAX_CANDIDATES)
    X = np.concatenate([basis, pool.X])
    obj = _select.Objective(X, upper)
    fixed = list(range(len(basis)))
    strength = np.sqrt(np.diag(obj.gram))
    allowed = np.zeros(len(X), dtype=bool)
    q95 = pool.q95 if pool.q95 is not None else float(np.quantile(strength[len(basis):], 0.95))
    allowed[len(basis):] = strength[len(basis):] >= _select.MIN_STRENGTH * q95

    def error(keys) -> float:
        if not keys:
            squared = float((data**2).sum())
        elif pool.whole:
            squared = obj(keys)
        else:  # the pool is a sample of the take: measure every frame (the fixed keys' own rows cost 0)
            added = [len(basis) + pool.rows[k - len(basis)] for k in keys if k >= len(basis)]
            squared = _select.squared_error(np.concatenate([basis, data]), [*fixed, *added], upper)
        return float(np.sqrt(squared) * to_percent)

    keys = fixed
    curve = [error(keys)]
    if keys:
        weights, cost = obj.fit(keys)
    else:
        weights, cost = np.zeros((len(X), 0)), np.diag(obj.gram).copy()
    while curve[-1] >= max_error and len(keys) - len(fixed) < max_keys and allowed.any():
        if not keys:
            keys = [_select._best_single(obj.gram, obj.bound, allowed)]
            weights, cost = obj.fit(keys)
        else:
            keys, weights, cost = _select._grow(obj, keys, weights, cost, allowed.copy())
        allowed[keys] = False
        curve.append(error(keys))
    picks = [pool.rows[k - len(basis)] for k in keys[len(fixed):]]
    return [int(p) for p in picks], curve


def _next_name(region: str, names: set[str], used: dict[str, int]) -> str:
    """``f"{region}_{i:02d}"`` with ``i`` past every number the region's names already use."""
    if region not in used:
        numbers = [int(n[len(region) + 1:]) for n in names
                   if n.startswith(region + "_") and n[len(region) + 1:].isdigit()]
        used[region] = max(numbers, default=-1) + 1
    while f"{region}_{used[region]:02d}" in names:
        used[region] += 1
    name = f"{region}_{used[region]:02d}"
    names.add(name)
    used[region] += 1
    return name
