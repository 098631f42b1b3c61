"""The paper's selection kernels for :mod:`keyshape._select`: ``spread`` and ``hull``.

Both work on the principal components of the data matrix ``X (n_frames, n_features)`` of
one region (rows: candidate frames minus the neutral) and return distinct row indices:
``spread`` takes the extremes along each component in turn, ``hull`` the vertices of the
convex hull of the leading projections, ranked by spanned volume. Both fill up with
farthest points when they run short. ``spa`` (:func:`keyshape._select.spa_steps`) uses
their sets as seeds.

References
----------
.. [1] E. Chuang and C. Bregler, "Performance driven facial animation using blendshape
   interpolation", Stanford CS-TR-2002-02, 2002: extremes along principal components
   (``spread``) and the convex hull of the leading components (``hull``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

__all__ = ["hull", "principal_axes", "spread"]

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
