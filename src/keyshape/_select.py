"""Selection kernels for :mod:`keyshape.keyshapes`.

Each kernel takes the data matrix ``X (n_frames, n_features)`` of one region, rows being
candidate frames minus the neutral frame, and returns ``(n_keys,)`` distinct row indices.
They know nothing about tracks or regions.

References
----------
.. [1] E. Chuang and C. Bregler, "Performance driven facial animation using blendshape
   interpolation", Stanford CS-TR-2002-02, 2002: extremes along principal components
   (``spread``) and the convex hull of the leading components (``hull``).
.. [2] N. Gillis and S. A. Vavasis, "Fast and robust recursive algorithms for separable
   nonnegative matrix factorization", IEEE TPAMI 36(4):698-714, 2014 (``spa``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .metrics import nonnegative_fit

_RANK_TOL = 1e-9


def spread(X: np.ndarray, n_keys: int, *, axes: np.ndarray | None = None) -> np.ndarray:
    """Frames with the largest and smallest projection on each principal component in turn.

    Parameters
    ----------
    X : (n_frames, n_features) float
    n_keys : int, <= n_frames
    axes : (rank, n_features) float, optional, keyword-only
        The principal axes of ``X`` if already known (see ``principal_axes``).

    Returns
    -------
    (n_keys,) int, distinct rows of ``X``
    """
    axes = principal_axes(X) if axes is None else axes
    proj = (X - X.mean(axis=0)) @ axes.T
    chosen: list[int] = []
    for j in range(proj.shape[1]):
        if len(chosen) >= n_keys:
            break
        for order in (np.argsort(-proj[:, j], kind="stable"), np.argsort(proj[:, j], kind="stable")):
            pick = next((int(i) for i in order if i not in chosen), None)
            if pick is not None and len(chosen) < n_keys:
                chosen.append(pick)
    return _farthest_points(X, chosen, np.arange(len(X)), n_keys)


def hull(X: np.ndarray, n_keys: int, *, n_components: int = 3, axes: np.ndarray | None = None) -> np.ndarray:
    """Vertices of the convex hull of the leading principal projections.

    The hull vertices are ranked greedily by spanned volume: each next vertex maximises
    the volume of the simplex it forms with the neutral (the origin) and the vertices
    already taken, i.e. has the largest residual after projecting out their span; once
    they span the projection space, by farthest-point order. If the hull has too few vertices, its vertices are peeled off
    and the hull of the remaining frames supplies the next ones ("onion peeling").

    Parameters
    ----------
    X : (n_frames, n_features) float
    n_keys : int, <= n_frames
    n_components : int, keyword-only
        Hull dimension (reduced to the rank of ``X``).
    axes : (rank, n_features) float, optional, keyword-only
        The principal axes of ``X`` if already known (see ``principal_axes``).

    Returns
    -------
    (n_keys,) int, distinct rows of ``X``
    """
    axes = principal_axes(X) if axes is None else axes
    proj = X @ axes[:n_components].T  # rows, not centred: the neutral stays at the origin
    chosen: list[int] = []
    remaining = np.arange(len(X))
    while len(chosen) < n_keys and remaining.size:
        layer = remaining[_hull_vertices(proj[remaining])]
        chosen = list(_volume_then_farthest(proj, chosen, layer, min(n_keys, len(chosen) + layer.size)))
        remaining = np.setdiff1d(remaining, layer)
    return np.array(chosen[:n_keys], dtype=int)


def spa(X: np.ndarray, n_keys: int) -> np.ndarray:
    """Successive projection algorithm (Gillis & Vavasis 2014, Algorithm 1).

    Repeatedly take the row of largest residual norm, then project every residual onto
    the orthogonal complement of it: ``R ← R (I - u uᵀ)``, ``u = r_j / |r_j|``.

    Parameters
    ----------
    X : (n_frames, n_features) float
    n_keys : int, <= n_frames

    Returns
    -------
    (n_keys,) int, distinct rows of ``X``; once ``X`` is exhausted (residual ~ 0),
    topped up by farthest-point order.
    """
    residual = np.array(X, dtype=float)
    norms = (residual**2).sum(axis=1)
    floor = _RANK_TOL * max(norms.max(initial=0.0), 1e-300)
    chosen: list[int] = []
    while len(chosen) < n_keys:
        norms[chosen] = -np.inf
        j = int(np.argmax(norms))
        if norms[j] <= floor:
            break
        u = residual[j] / np.sqrt(norms[j])
        residual -= np.outer(residual @ u, u)
        chosen.append(j)
        norms = (residual**2).sum(axis=1)
    return _farthest_points(X, chosen, np.arange(len(X)), n_keys)


def spa_refined(X: np.ndarray, n_keys: int) -> np.ndarray:
    """SPA, then exchanges (``refine_swaps``); never worse than ``spread`` or ``hull``.

    The exchange search is local. If, started from the SPA set, it ends with a larger
    non-negative fitting error than the better of the ``spread`` and ``hull`` sets, it
    is run again from that set and the better result is kept.

    Parameters
    ----------
    X : (n_frames, n_features) float
    n_keys : int, <= n_frames

    Returns
    -------
    (n_keys,) int, distinct rows of ``X``
    """
    max_swaps = 2 * n_keys
    best = refine_swaps(X, spa(X, n_keys), max_swaps=max_swaps)
    axes = principal_axes(X)
    seeds = [spread(X, n_keys, axes=axes), hull(X, n_keys, axes=axes)]
    seed_errors = [fit_error(X, rows) for rows in seeds]
    seed = seeds[int(np.argmin(seed_errors))]
    if fit_error(X, best) >= min(seed_errors):
        again = refine_swaps(X, seed, max_swaps=max_swaps)
        best = again if fit_error(X, again) < fit_error(X, best) else best
    return best


def fit_error(X: np.ndarray, rows: np.ndarray) -> float:
    """Exact ``Σ_f min_{w >= 0} |x_f - wᵀ X_rows|²`` (Lawson-Hanson per frame)."""
    weights = nonnegative_fit(X, X[rows])
    return float(((X - weights @ X[rows]) ** 2).sum())


def principal_axes(X: np.ndarray) -> np.ndarray:
    """Principal axes ``(rank, n_features)`` of ``X (n_frames, n_features)`` (PCA about the mean).

    Rows are unit vectors in order of decreasing variance; axes of ~zero variance are dropped.
    """
    if not X.size:
        return np.zeros((0, X.shape[1]))
    _, sv, vt = np.linalg.svd(X - X.mean(axis=0), full_matrices=False)
    rank = int((sv > _RANK_TOL * max(sv.max(initial=0.0), 1e-300)).sum())
    return vt[:rank]


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    """Indices of the convex hull vertices of ``points (n, m)``; all points if too few."""
    n, m = points.shape
    if m == 0:
        return np.arange(n)
    if m == 1:
        return np.unique([np.argmin(points[:, 0]), np.argmax(points[:, 0])])
    if n <= m + 1:
        return np.arange(n)
    try:
        return np.sort(ConvexHull(points).vertices)
    except QhullError:  # flat point set: joggle it
        return np.sort(ConvexHull(points, qhull_options="QJ").vertices)


def _volume_then_farthest(points: np.ndarray, chosen, pool: np.ndarray, n_keys: int) -> np.ndarray:
    """Extend ``chosen`` from ``pool`` by greedy simplex volume, then farthest points.

    The volume of the simplex {0} ∪ chosen ∪ {p} grows with the distance of ``p`` from
    the span of the chosen rows, so each pick is the pool row of largest residual after
    projecting that span out (Gram-Schmidt), as long as the residual is not ~0.
    """
    chosen = [int(i) for i in chosen]
    pool = np.setdiff1d(pool, chosen)
    basis = np.linalg.qr(points[chosen].T)[0] if chosen else np.zeros((points.shape[1], 0))
    residual = points[pool] - (points[pool] @ basis) @ basis.T
    norms = (residual**2).sum(axis=1)
    floor = 1e-6 * max((points[pool] ** 2).sum(axis=1).max(initial=0.0), 1e-300)
    while len(chosen) < n_keys and pool.size and norms.max() > floor:
        j = int(np.argmax(norms))
        u = residual[j] / np.sqrt(norms[j])
        residual -= np.outer(residual @ u, u)
        chosen.append(int(pool[j]))
        norms = (residual**2).sum(axis=1)
        norms[np.isin(pool, chosen)] = -np.inf
    return _farthest_points(points, chosen, pool, n_keys)


def _farthest_points(points: np.ndarray, chosen, pool: np.ndarray, n_keys: int) -> np.ndarray:
    """Extend ``chosen`` from ``pool`` to ``n_keys`` rows, farthest-point first.

    Distances are Euclidean in ``points (n, m)``; the origin (the neutral) counts as
    already chosen, so the first pick is the row of largest norm.
    """
    chosen = [int(i) for i in chosen]
    pool = np.setdiff1d(pool, chosen)
    dist = (points[pool] ** 2).sum(axis=1)
    for i in chosen:
        dist = np.minimum(dist, ((points[pool] - points[i]) ** 2).sum(axis=1))
    while len(chosen) < n_keys and pool.size:
        j = int(np.argmax(dist))
        chosen.append(int(pool[j]))
        dist = np.minimum(dist, ((points[pool] - points[pool[j]]) ** 2).sum(axis=1))
        dist[j] = -np.inf
    return np.array(chosen, dtype=int)


def refine_swaps(X: np.ndarray, chosen: np.ndarray, *, max_swaps: int, patience: int = 6) -> np.ndarray:
    """Improve a key set by exchanges that lower the non-negative fitting error.

    The objective is ``E(S) = Σ_f min_{w >= 0} |x_f - Σ_{k in S} w_k x_k|²`` over all rows.
    Each step proposes a row to add, alternately the one of largest first-order gain
    (``_addition_gain``) and the worst-explained one; fits the keys plus that row; and
    tries dropping each of the least important keys (smallest ``G_kk Σ_f w_fk²``, the
    cost of zeroing ``w_k``). The best exchange is kept if it lowers ``E``. A proposal
    that fails is not proposed again until the next exchange; the search stops after
    ``patience`` failures in a row or ``max_swaps`` exchanges. All fits work on the Gram
    matrix ``H = X Xᵀ`` with batched coordinate descent.

    Parameters
    ----------
    X : (n_frames, n_features) float
    chosen : (n_keys,) int, distinct rows of ``X``
    max_swaps : int, keyword-only
    patience : int, keyword-only

    Returns
    -------
    (n_keys,) int, distinct rows of ``X`` with ``E`` no larger than for ``chosen``.
    """
    gram = X @ X.T
    keys, tabu = [int(i) for i in chosen], set()
    weights = _cd_nnls(gram[np.ix_(keys, keys)], gram[:, keys], np.zeros((len(X), len(keys))), 200)
    cost = _costs(gram, keys, weights)
    swaps = fails = 0
    tol = 1e-9 * np.trace(gram)
    while swaps < max_swaps and fails < patience:
        # Alternate two proposals: the largest first-order gain, the worst-explained frame.
        score = _addition_gain(gram, keys, weights) if fails % 2 == 0 else cost.copy()
        score[keys + sorted(tabu)] = -1.0
        new = int(np.argmax(score))
        if score[new] <= tol:
            break
        trial = _best_exchange(gram, keys, weights, new)
        if trial[2].sum() < cost.sum() - tol:
            (keys, weights, cost), swaps, fails, tabu = trial, swaps + 1, 0, set()
        else:
            tabu.add(new)
            fails += 1
    return np.array(keys, dtype=int)


def _addition_gain(gram: np.ndarray, keys, weights: np.ndarray) -> np.ndarray:
    """First-order gain of adding each row as a key, ``(n_frames,)``.

    With the other weights fixed, the best non-negative weight of a new key ``c`` in frame
    ``f`` lowers that frame's error by ``max(0, -g_fc)² / H_cc``, where
    ``g_fc = Σ_k w_fk H_kc - H_fc`` is the gradient; the gain sums this over frames.
    """
    grad = weights @ gram[keys] - gram  # (n_frames, n_candidates)
    return (np.minimum(grad, 0.0) ** 2).sum(axis=0) / np.maximum(np.diag(gram), 1e-300)


def _best_exchange(gram, keys, weights, new, n_trials: int = 4, sweeps: int = 12):
    """Best set ``keys - {k} + {new}`` over the ``n_trials`` least important ``k``.

    Warm-started from ``weights (n_frames, n_keys)``, only the frames whose optimum can
    change are refitted: adding ``new`` matters only where its gradient is negative,
    removing ``k`` only where ``w_k > 0`` (elsewhere the old weights stay optimal).
    Returns ``(keys, weights, per-frame costs)`` of the best trial.
    """
    grown = keys + [new]
    w = np.column_stack([weights, np.zeros(len(gram))])
    rows = np.flatnonzero(weights @ gram[keys, new] - gram[:, new] < 0)
    w[rows] = _cd_nnls(gram[np.ix_(grown, grown)], gram[np.ix_(rows, grown)], w[rows], sweeps)
    importance = np.diag(gram)[keys] * (w[:, :-1] ** 2).sum(axis=0)
    drops = np.argsort(importance, kind="stable")[:n_trials]
    sets = [[k for i, k in enumerate(grown) if i != d] for d in drops]
    w_trials = np.stack([np.delete(w, d, axis=1) for d in drops])  # (n_trials, n_frames, n_keys)
    rows = np.flatnonzero((w[:, drops] > 0).any(axis=1))
    idx = np.array(sets)  # (n_trials, n_keys)
    g = gram[idx[:, :, None], idx[:, None, :]]  # (n_trials, n_keys, n_keys)
    c = np.moveaxis(gram[rows][:, idx], 1, 0)  # (n_trials, n_rows, n_keys)
    w_trials[:, rows] = _cd_nnls(g, c, w_trials[:, rows], sweeps)
    costs = np.stack([_costs(gram, s, wt) for s, wt in zip(sets, w_trials)])
    best = int(np.argmin(costs.sum(axis=1)))
    return sets[best], w_trials[best], costs[best]


def _cd_nnls(gram_keys: np.ndarray, cross: np.ndarray, weights: np.ndarray, sweeps: int) -> np.ndarray:
    """Batched coordinate descent for ``min_{w >= 0} ½ wᵀ G w - cᵀ w`` (HALS-type updates).

    Parameters
    ----------
    gram_keys : (..., n_keys, n_keys) float, ``G``
    cross : (..., n_frames, n_keys) float, ``c`` per frame
    weights : (..., n_frames, n_keys) float, the warm start
    sweeps : int

    Returns
    -------
    (..., n_frames, n_keys) float, >= 0
    """
    w = np.array(weights, dtype=float)
    diag = np.maximum(np.diagonal(gram_keys, axis1=-2, axis2=-1), 1e-300)
    for _ in range(sweeps):
        for k in range(w.shape[-1]):
            grad = (w @ gram_keys[..., :, k, None])[..., 0] - cross[..., k]
            w[..., k] = np.maximum(0.0, w[..., k] - grad / diag[..., k, None])
    return w


def _costs(gram: np.ndarray, keys, weights: np.ndarray) -> np.ndarray:
    """Per-row squared errors ``|x_f - wᵀ X_S|² = H_ff - 2 wᵀ H_fS + wᵀ H_SS w``, ``(n_frames,)``."""
    cross = gram[:, keys]
    quad = np.einsum("fk,kl,fl->f", weights, gram[np.ix_(keys, keys)], weights)
    return np.maximum(np.diag(gram) - 2 * (weights * cross).sum(axis=1) + quad, 0.0)
