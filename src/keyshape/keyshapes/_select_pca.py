"""The paper's selection kernels for :mod:`keyshape.keyshapes._select`: ``spread`` and ``hull``;
and the pool of rows a long take's keys are searched among.

Both kernels work on the principal components of the data matrix ``X (n_frames,
n_features)`` of one region (rows: candidate frames minus the neutral) and return
distinct row indices: ``spread`` takes the extremes along each component in turn,
``hull`` the vertices of the convex hull of the leading projections, ranked by spanned
volume. Both fill up with farthest points when they run short. ``spa``
(:func:`keyshape.keyshapes._select.spa_steps`) uses their sets as seeds.

:func:`pool` keeps, of a long ``X``, the rows these kernels pick on all of it, extremes
found by successive projection (Gillis & Vavasis 2014) and farthest points, and evenly
spaced rows, with the principal axes of all rows (:func:`principal_axes_blocked`): the
search then needs memory bounded in ``n_frames`` but for ``X`` itself.

References
----------
.. [1] E. Chuang and C. Bregler, "Performance driven facial animation using blendshape
   interpolation", Stanford CS-TR-2002-02, 2002: extremes along principal components
   (``spread``) and the convex hull of the leading components (``hull``).
.. [2] N. Gillis and S. A. Vavasis, "Fast and robust recursive algorithms for separable
   nonnegative matrix factorization", IEEE TPAMI 36(4):698-714, 2014 (:func:`pool`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["Pool", "hull", "pool", "principal_axes", "principal_axes_blocked", "scatter", "spread"]

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
    they span the projection space, by farthest-point order. If the hull has too few
    vertices, its vertices are peeled off and the hull of the remaining frames supplies
    the next ones ("onion peeling").

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


def principal_axes_blocked(X: np.ndarray, *, block: int = 4096) -> np.ndarray:
    """:func:`principal_axes` of many rows, in memory linear in their number.

    The scatter matrix ``C = Σ_f (x_f − μ)(x_f − μ)ᵀ`` (``n_features²``) is summed over
    blocks of ``block`` rows and its eigenvectors taken by decreasing eigenvalue ``λ = σ²``:
    the axes of :func:`principal_axes` up to sign and rounding, with no array the size of
    ``X`` besides it. Axes with ``λ ≤ 1e-12 λ_max`` (``σ ≤ 1e-6 σ_max``, the precision of
    an eigenvalue of ``C``) are dropped.
    """
    if not X.size:
        return np.zeros((0, X.shape[1]))
    lam, vec = np.linalg.eigh(scatter(X, X.mean(axis=0), block=block))
    lam, vec = lam[::-1], vec[:, ::-1]
    rank = int((lam > 1e-12 * max(lam[0], 1e-300)).sum())
    return np.ascontiguousarray(vec[:, :rank].T)


def scatter(X: np.ndarray, mean: np.ndarray, *, block: int = 4096) -> np.ndarray:
    """``Σ_f (x_f − mean)(x_f − mean)ᵀ``, ``(n_features, n_features)``, summed over blocks of rows."""
    out = np.zeros((X.shape[1], X.shape[1]))
    for start in range(0, len(X), block):
        centred = X[start:start + block] - mean
        out += centred.T @ centred
    return out


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    """Indices of the convex hull vertices of ``points (n, m)``; all points if too few."""
    n, m = points.shape
    if m == 0:
        return np.arange(n)
    if m == 1:
        return np.unique([np.argmin(points[:, 0]), np.argmax(points[:, 0])])
    if n <= m + 1:
        return np.arange(n)
    from scipy.spatial import ConvexHull, QhullError  # here: a quarter second to import, for one method

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


# --------------------------------------------------------------------------- long takes: a pool of rows

_POOL_AXES = 16  # spread: extremes kept along this many principal axes (K <= 32)
_POOL_DEPTH = 4  # ... this many at each end
_POOL_HULL = 64  # hull: outer layers kept until they hold this many vertices
_POOL_SPA = 64  # successive-projection picks on all rows
_POOL_FAR = 0.25  # share of the pool for extremes; evenly spaced rows fill the rest
_POOL_COMPONENTS = 32  # principal projections the farthest points are measured in


class Pool(NamedTuple):
    """The rows of ``X`` the key search works on, and what it needs to know of all of them.

    Attributes
    ----------
    rows : (n_pool,) int
        Sorted rows of ``X`` (all of them for a short ``X``).
    X : (n_pool, n_features) float
        ``X[rows]``.
    axes : (rank, n_features) float or None
        Principal axes of all of ``X`` (None: the pool is all of ``X``).
    q95 : float or None
        95th percentile of ``|x|`` over all of ``X`` (None: the pool is all of ``X``).
    """

    rows: np.ndarray
    X: np.ndarray
    axes: np.ndarray | None
    q95: float | None

    @property
    def whole(self) -> bool:
        """True when the pool is every row of ``X``."""
        return self.axes is None


def pool(X: np.ndarray, max_rows: int) -> Pool:
    """All rows of ``X``, or for more than ``max_rows`` a well-spread subset of ``max_rows``.

    The key search keeps a rows × rows Gram matrix ``X Xᵀ``, so a long ``X`` is searched
    among ``max_rows`` of its rows (memory bounded by that of ``max_rows`` frames):

    1. the candidates of the paper's methods on all of ``X``: the 4 largest and smallest
       projections on each of the first 16 principal axes (``spread``) and the outer layers
       of the convex hull of the first three projections, at least 64 vertices (``hull``);
       with those axes passed on, ``spread`` and ``hull`` on the pool pick what they pick on
       all of ``X`` (for ``K ≤ 32``, unless they run out of axes or hull vertices);
    2. up to 64 successive-projection picks on all of ``X`` (Gillis & Vavasis 2014): each
       row farthest from the span of those before;
    3. farthest points from the neutral (the origin) and the rows so far, measured in the
       first 32 principal projections, up to a quarter of the pool;
    4. evenly spaced rows (in frame order) for the rest, so the pool's error stays
       representative of the whole take.

    Time and memory are linear in the rows of ``X``; the range of motion ``q95`` and the
    principal axes (:func:`principal_axes_blocked`) are those of all rows.

    Parameters
    ----------
    X : (n_frames, n_features) float
    max_rows : int, >= 1

    Returns
    -------
    Pool
    """
    if len(X) <= max_rows:
        return Pool(np.arange(len(X)), X, None, None)
    axes = principal_axes_blocked(X)
    norms = np.einsum("ij,ij->i", X, X)  # |x|²
    q95 = float(np.quantile(np.sqrt(norms), 0.95))
    rows = _preselect(X, norms, axes, max_rows)
    return Pool(rows, X[rows], axes, q95)


def _preselect(X: np.ndarray, norms: np.ndarray, axes: np.ndarray, n_rows: int) -> np.ndarray:
    """``(n_rows,)`` sorted rows of ``X``: the steps of :func:`pool`."""
    proj = X @ axes[:_POOL_COMPONENTS].T  # (n_frames, p), not centred: the neutral is the origin
    kept: dict[int, None] = {}  # an ordered set
    for j in range(min(_POOL_AXES, proj.shape[1])):
        order = np.argsort(proj[:, j], kind="stable")
        kept.update(dict.fromkeys(np.r_[order[::-1][:_POOL_DEPTH], order[:_POOL_DEPTH]].tolist()))
    kept.update(dict.fromkeys(_hull_layers(proj[:, :3], _POOL_HULL).tolist()))
    kept.update(dict.fromkeys(_projection_picks(X, norms, _POOL_SPA)))
    extremes = min(max(int(_POOL_FAR * n_rows), len(kept)), n_rows)
    chosen = _farthest(proj, list(kept)[:extremes], extremes)
    rest = np.setdiff1d(np.arange(len(X)), chosen)
    fill = n_rows - len(chosen)
    spaced = rest[np.arange(fill) * (len(rest) - 1) // max(fill - 1, 1)] if fill > 0 else rest[:0]
    return np.sort(np.r_[chosen, spaced]).astype(int)


def _hull_layers(points: np.ndarray, n_vertices: int) -> np.ndarray:
    """Vertices of the outer convex-hull layers of ``points (n, m)`` (onion peeling, as
    :func:`hull`), layer after layer until there are ``n_vertices``."""
    if not points.shape[1]:
        return np.zeros(0, dtype=int)
    found, remaining = [], np.arange(len(points))
    while sum(map(len, found)) < n_vertices and remaining.size:
        layer = remaining[_hull_vertices(points[remaining])]
        found.append(layer)
        remaining = np.setdiff1d(remaining, layer)
    return np.concatenate(found)


def _projection_picks(X: np.ndarray, norms: np.ndarray, n_picks: int) -> list[int]:
    """Successive projection (Gillis & Vavasis 2014, Algorithm 1): each pick is the row of
    largest residual after projecting out the span of the picks before; one pass over ``X``
    per pick."""
    residual = norms.copy()
    basis = np.zeros((X.shape[1], 0))
    picks: list[int] = []
    floor = 1e-12 * max(norms.max(initial=0.0), 1e-300)
    for _ in range(min(n_picks, X.shape[1])):
        j = int(np.argmax(residual))
        if residual[j] <= floor:
            break
        u = X[j] - basis @ (basis.T @ X[j])
        u -= basis @ (basis.T @ u)  # twice is enough (Gram-Schmidt)
        u /= np.linalg.norm(u)
        residual -= (X @ u) ** 2
        residual[j] = -np.inf
        basis = np.column_stack([basis, u])
        picks.append(j)
    return picks


def _farthest(points: np.ndarray, chosen: list[int], n_rows: int) -> np.ndarray:
    """Extend ``chosen`` to ``n_rows`` rows of ``points (n, p)``, farthest-point first; the
    origin counts as chosen. Squared distances as ``|y|² + |c|² − 2 y·c``: no ``(n, p)``
    temporaries."""
    sq = np.einsum("ij,ij->i", points, points)
    dist = sq.copy()
    chosen = list(chosen)
    for c in chosen:
        np.minimum(dist, sq + sq[c] - 2 * (points @ points[c]), out=dist)
    dist[chosen] = -np.inf
    while len(chosen) < n_rows:
        c = int(np.argmax(dist))
        chosen.append(c)
        np.minimum(dist, sq + sq[c] - 2 * (points @ points[c]), out=dist)
        dist[c] = -np.inf
    return np.array(chosen, dtype=int)
