"""Selection kernels for :mod:`keyshape.keyshapes`.

Each kernel takes the data matrix ``X (n_frames, n_features)`` of one region, rows being
candidate frames minus the neutral frame, and returns ``(n_keys,)`` distinct row indices.
They know nothing about tracks or regions.

The quality of a key set ``S`` is the error of the best blend of its keys in every frame,

.. math::

    E_u(S) = \\sum_f \\min_{0 \\le w \\le u} \\lVert x_f - \\textstyle\\sum_{k \\in S} w_k x_k \\rVert^2,

with ``u = ∞`` for plain non-negative least squares (the paper) or ``u = 1`` when weights
are bounded as the product solves them. Under a bound a key close to the neutral is of
little use (it can only be reached at ``w ≤ u``), so ``spa`` picks strong expressions.

References
----------
.. [1] E. Chuang and C. Bregler, "Performance driven facial animation using blendshape
   interpolation", Stanford CS-TR-2002-02, 2002: extremes along principal components
   (``spread``) and the convex hull of the leading components (``hull``).
.. [2] N. Gillis and S. A. Vavasis, "Fast and robust recursive algorithms for separable
   nonnegative matrix factorization", IEEE TPAMI 36(4):698-714, 2014 (``spa``).
.. [3] C. L. Lawson and R. J. Hanson, *Solving Least Squares Problems*, 1974, ch. 23.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator
from itertools import islice

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .decompose import solve_nnls

_RANK_TOL = 1e-9
_PATIENCE = 4
MIN_STRENGTH = 0.25  # spa keys: delta at least this fraction of the region's 95th-percentile delta


class Objective:
    """The exact error ``E_u(S)`` of key sets ``S`` (rows of ``X``), each set fitted once.

    Fits are exact batched bounded NNLS (:func:`keyshape.decompose.solve_nnls`). Errors are
    cached by the set, so the selection and the error-vs-K table share them; the weights
    only for the last few sets (they take ``n_frames × n_keys`` floats each).

    Parameters
    ----------
    X : (n_frames, n_features) float
    upper : float or None
        Upper bound ``u`` of the weights; None for none.

    Attributes
    ----------
    gram : (n_frames, n_frames) float, ``X Xᵀ``
    bound : float, ``u`` (``inf`` when None)
    """

    _KEPT = 4  # sets whose weights are kept

    def __init__(self, X: np.ndarray, upper: float | None = None):
        self.X = np.asarray(X, dtype=float)
        self.upper = None if upper is None else float(upper)
        self.bound = np.inf if upper is None else float(upper)
        self.gram = self.X @ self.X.T
        self._errors: dict[tuple[int, ...], float] = {}
        self._fits: OrderedDict[tuple[int, ...], tuple[np.ndarray, np.ndarray]] = OrderedDict()

    def fit(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """``(weights (n_frames, n_keys) in the order of rows, squared errors (n_frames,))``."""
        rows = np.asarray(rows, dtype=int)
        order = np.argsort(rows, kind="stable")
        key = tuple(rows[order].tolist())
        if key not in self._fits:
            basis = self.X[list(key)]
            w = solve_nnls(basis.T, self.X, upper=self.upper)
            self._fits[key] = (w, ((self.X - w @ basis) ** 2).sum(axis=1))
            self._errors[key] = float(self._fits[key][1].sum())
            if len(self._fits) > self._KEPT:
                self._fits.popitem(last=False)
        self._fits.move_to_end(key)
        w, cost = self._fits[key]
        out = np.empty_like(w)
        out[:, order] = w
        return out, cost

    def __call__(self, rows) -> float:
        """``E_u(rows)``."""
        key = tuple(sorted(int(i) for i in rows))
        return self._errors[key] if key in self._errors else float(self.fit(rows)[1].sum())


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


def steps(X: np.ndarray, method: str, *, upper: float | None = None,
          objective: Objective | None = None) -> Iterator[np.ndarray]:
    """The key sets of ``method`` for ``K = 1, 2, …, n_frames``.

    ``spread`` and ``hull`` sets are computed afresh for every ``K`` (from one PCA);
    ``spa`` sets grow one from the other (:func:`spa_steps`).

    Parameters
    ----------
    X : (n_frames, n_features) float
    method : {"spa", "spread", "hull"}
    upper : float or None, keyword-only
        Bound of the weights in ``E_u`` (``spa`` only; the paper's methods ignore it).
    objective : Objective, optional, keyword-only
        A shared :class:`Objective` of ``X``.

    Yields
    ------
    (K,) int, distinct rows of ``X``
    """
    if method == "spa":
        yield from spa_steps(X, upper=upper, objective=objective)
        return
    kernel = spread if method == "spread" else hull
    axes = principal_axes(X)
    for k in range(1, len(X) + 1):
        yield kernel(X, k, axes=axes)


def spa(X: np.ndarray, n_keys: int, *, upper: float | None = None,
        objective: Objective | None = None, min_strength: float | None = None) -> np.ndarray:
    """Successive projection grown one key at a time, each set refined by exchanges.

    The ``n_keys``-th set of :func:`spa_steps`.

    Parameters
    ----------
    X : (n_frames, n_features) float
    n_keys : int, 1 <= n_keys <= n_frames
    upper : float or None, keyword-only
        Bound ``u`` of the weights in the objective ``E_u``; None for none.
    objective : Objective, optional, keyword-only
        A shared :class:`Objective` of ``X`` (then ``upper`` is its own).
    min_strength : float, keyword-only
        See :func:`spa_steps`.

    Returns
    -------
    (n_keys,) int, distinct rows of ``X``
    """
    steps = spa_steps(X, upper=upper, objective=objective, min_strength=min_strength)
    return next(islice(steps, n_keys - 1, None))


def spa_steps(X: np.ndarray, *, upper: float | None = None, objective: Objective | None = None,
              min_strength: float | None = None) -> Iterator[np.ndarray]:
    """Key sets for ``K = 1, 2, …, n_frames``, each grown from the one before.

    Keys are *strong* rows: ``|x| ≥ min_strength · q95``, with ``q95`` the 95th percentile
    of ``|x|`` over the rows (a robust range of motion). A frame near the neutral could
    lower ``E_u`` a little (it explains small deviations of the many resting frames, and
    without a bound it can be scaled up several times), but as a key shape it is useless
    to an artist. Only when every strong row is a key does the next strongest row qualify.

    1. ``K = 1``: the row that alone gives the smallest ``E_u``.
    2. ``K → K + 1``: three candidate rows are fitted with the keys and the best is added:
       the successive-projection choice (Gillis & Vavasis 2014, Algorithm 1: the row
       farthest from the span of the keys), the row of largest first-order gain in ``E_u``
       (``_addition_gain``) and the worst-explained row.
    3. The set is refined by exchanges that lower ``E_u`` (``refine``).
    4. If the paper's ``spread`` or ``hull`` set of the same size (when it has only strong
       rows) has an exact error no larger, the exchanges are run from the better of them
       too and the better set kept, so ``spa`` is never worse than those sets.

    Parameters
    ----------
    X : (n_frames, n_features) float
    upper : float or None, keyword-only
    objective : Objective, optional, keyword-only
    min_strength : float, optional, keyword-only
        Default ``MIN_STRENGTH`` (0.25); 0 lets every row be a key.

    Yields
    ------
    (K,) int, distinct rows of ``X``
    """
    obj = objective if objective is not None else Objective(X, upper)
    if not len(obj.X):
        return
    axes = principal_axes(obj.X)  # as in steps(), so the seeds' fits are shared
    strength = np.sqrt(np.diag(obj.gram))
    floor = (MIN_STRENGTH if min_strength is None else min_strength) * np.quantile(strength, 0.95)
    allowed = strength >= floor
    keys = [_best_single(obj.gram, obj.bound, allowed)]
    weights, cost = obj.fit(keys)
    while True:
        k = len(keys)
        keys, weights, cost = refine(obj.gram, keys, weights, cost, bound=obj.bound, max_swaps=k,
                                     patience=_PATIENCE, allowed=allowed)
        seeds = [s for s in (spread(obj.X, k, axes=axes), hull(obj.X, k, axes=axes)) if allowed[s].all()]
        keys, weights, cost = _against_seeds(obj, keys, seeds, allowed)
        yield np.array(keys, dtype=int)
        if k == len(obj.X):
            return
        if allowed.sum() <= k:  # every strong row is a key: admit the next strongest
            allowed[np.argmax(np.where(allowed, -np.inf, strength))] = True
        keys, weights, cost = _grow(obj, keys, weights, cost, allowed)


def _best_single(gram: np.ndarray, bound: float, allowed: np.ndarray) -> int:
    """The allowed row ``c`` minimising ``Σ_f min_{0 ≤ a ≤ u} |x_f − a x_c|²`` (all at once)."""
    diag = np.maximum(np.diag(gram), 1e-300)
    a = np.clip(gram / diag, 0.0, bound)  # a_fc, the best weight of c in frame f
    return int(np.argmin(np.where(allowed, (a * (a * diag - 2 * gram)).sum(axis=0), np.inf)))


def _grow(obj: Objective, keys: list[int], weights: np.ndarray, cost: np.ndarray, allowed: np.ndarray):
    """Add the best of three proposed rows (see :func:`spa_steps`); ``(keys, weights, cost)``."""
    gram, taken = obj.gram, ~allowed
    taken[keys] = True
    basis = np.linalg.qr(obj.X[keys].T)[0]  # orthonormal span of the keys
    far = np.diag(gram) - ((obj.X @ basis) ** 2).sum(axis=1)  # squared distance to the span
    scores = (far, _addition_gain(gram, keys, weights, obj.bound), cost)
    proposals = list(dict.fromkeys(int(np.argmax(np.where(taken, -np.inf, s))) for s in scores))
    trials = [_fit_added(gram, keys, weights, new, obj.bound) for new in proposals]
    best = int(np.argmin([c.sum() for _, c in trials]))
    return [*keys, proposals[best]], *trials[best]


def _fit_added(gram, keys, weights, new, bound, sweeps: int = 12):
    """Weights and costs of ``keys + [new]``, refitting only where ``new`` can help."""
    grown = [*keys, new]
    w = np.column_stack([weights, np.zeros(len(gram))])
    rows = np.flatnonzero(weights @ gram[keys, new] - gram[:, new] < 0)
    w[rows] = _cd_nnls(gram[np.ix_(grown, grown)], gram[np.ix_(rows, grown)], w[rows], sweeps, bound)
    return w, _costs(gram, grown, w)


def _against_seeds(obj: Objective, keys: list[int], seeds: list[np.ndarray], allowed: np.ndarray):
    """Keep ``keys`` unless exchanges from the best seed set reach a lower exact ``E_u``."""
    errors = [obj(s) for s in seeds]
    if errors and obj(keys) >= min(errors):
        seed = [int(i) for i in seeds[int(np.argmin(errors))]]
        again = refine(obj.gram, seed, *obj.fit(seed), bound=obj.bound, max_swaps=2 * len(seed),
                       allowed=allowed)[0]
        keys = again if obj(again) < obj(keys) else keys
    return keys, *obj.fit(keys)


def refine(gram: np.ndarray, keys: list[int], weights: np.ndarray, cost: np.ndarray, *,
           bound: float = np.inf, max_swaps: int, patience: int = 4,
           allowed: np.ndarray | None = None):
    """Improve a key set by exchanges that lower ``E_u`` (``u = bound``).

    Each step proposes a row to add, alternately the one of largest first-order gain
    (``_addition_gain``) and the worst-explained one; fits the keys plus that row; and
    tries dropping each of the least important keys (smallest ``G_kk Σ_f w_fk²``, the
    cost of zeroing ``w_k``). The best exchange is kept if it lowers ``E_u``. A proposal
    that fails is not proposed again until the next exchange; the search stops after
    ``patience`` failures in a row or ``max_swaps`` exchanges. All fits work on the Gram
    matrix ``H = X Xᵀ`` with batched coordinate descent.

    Parameters
    ----------
    gram : (n_frames, n_frames) float, ``H``
    keys : list of int, distinct rows
    weights : (n_frames, n_keys) float, feasible weights of ``keys``
    cost : (n_frames,) float, the squared errors they give
    bound : float, keyword-only
    max_swaps, patience : int, keyword-only
    allowed : (n_frames,) bool, optional, keyword-only
        The rows that may become keys (default: all).

    Returns
    -------
    (keys, weights, cost), with ``Σ cost`` no larger than given.
    """
    keys, tabu = [int(i) for i in keys], set()
    swaps = fails = 0
    tol = 1e-9 * np.trace(gram)
    while swaps < max_swaps and fails < patience:
        score = _addition_gain(gram, keys, weights, bound) if fails % 2 == 0 else cost.copy()
        score[keys + sorted(tabu)] = -1.0
        if allowed is not None:
            score[~allowed] = -1.0
        new = int(np.argmax(score))
        if score[new] <= tol:
            break
        trial = _best_exchange(gram, keys, weights, new, bound)
        if trial[2].sum() < cost.sum() - tol:
            (keys, weights, cost), swaps, fails, tabu = trial, swaps + 1, 0, set()
        else:
            tabu.add(new)
            fails += 1
    return keys, weights, cost


def _addition_gain(gram: np.ndarray, keys, weights: np.ndarray, bound: float) -> np.ndarray:
    """First-order gain in ``E_u`` of adding each row as a key, ``(n_frames,)``.

    With the other weights fixed, the best weight of a new key ``c`` in frame ``f`` is
    ``a = clip(-g_fc / H_cc, 0, u)``, where ``g_fc = Σ_k w_fk H_kc - H_fc`` is the gradient,
    and it lowers that frame's error by ``a (-2 g_fc - a H_cc)``; the gain sums this over frames.
    """
    grad = weights @ gram[keys] - gram  # (n_frames, n_candidates)
    diag = np.maximum(np.diag(gram), 1e-300)
    np.minimum(grad, 0.0, out=grad)  # only a negative gradient can gain
    if not np.isfinite(bound):  # a = -g / H_cc: the gain is g² / H_cc
        return np.einsum("fc,fc->c", grad, grad) / diag
    step = np.minimum(grad / -diag, bound)
    return np.einsum("fc,fc->c", step, -2 * grad - step * diag)


def _best_exchange(gram, keys, weights, new, bound, n_trials: int = 4, sweeps: int = 12):
    """Best set ``keys - {k} + {new}`` over the ``n_trials`` least important ``k``.

    Warm-started from ``weights (n_frames, n_keys)``, only the frames whose optimum can
    change are refitted: adding ``new`` matters only where its gradient is negative,
    removing ``k`` only where ``w_k > 0`` (elsewhere the old weights stay optimal).
    Returns ``(keys, weights, per-frame costs)`` of the best trial.
    """
    grown = [*keys, new]
    w, _ = _fit_added(gram, keys, weights, new, bound, sweeps)
    importance = np.diag(gram)[keys] * (w[:, :-1] ** 2).sum(axis=0)
    drops = np.argsort(importance, kind="stable")[:n_trials]
    sets = [[k for i, k in enumerate(grown) if i != d] for d in drops]
    w_trials = np.stack([np.delete(w, d, axis=1) for d in drops])  # (n_trials, n_frames, n_keys)
    rows = np.flatnonzero((w[:, drops] > 0).any(axis=1))
    idx = np.array(sets)  # (n_trials, n_keys)
    g = gram[idx[:, :, None], idx[:, None, :]]  # (n_trials, n_keys, n_keys)
    c = np.moveaxis(gram[rows][:, idx], 1, 0)  # (n_trials, n_rows, n_keys)
    w_trials[:, rows] = _cd_nnls(g, c, w_trials[:, rows], sweeps, bound)
    costs = np.stack([_costs(gram, s, wt) for s, wt in zip(sets, w_trials)])
    best = int(np.argmin(costs.sum(axis=1)))
    return sets[best], w_trials[best], costs[best]


def _cd_nnls(gram_keys: np.ndarray, cross: np.ndarray, weights: np.ndarray, sweeps: int,
             bound: float = np.inf) -> np.ndarray:
    """Batched coordinate descent for ``min_{0 <= w <= u} ½ wᵀ G w - cᵀ w`` (HALS-type updates).

    Parameters
    ----------
    gram_keys : (..., n_keys, n_keys) float, ``G``
    cross : (..., n_frames, n_keys) float, ``c`` per frame
    weights : (..., n_frames, n_keys) float, the warm start
    sweeps : int
    bound : float, ``u``

    Returns
    -------
    (..., n_frames, n_keys) float, in ``[0, u]``
    """
    w = np.array(weights, dtype=float)
    diag = np.maximum(np.diagonal(gram_keys, axis1=-2, axis2=-1), 1e-300)[..., None, :]
    scaled = gram_keys / diag  # column k of G over G_kk: (w @ scaled)_k = (grad_k + c_k) / G_kk
    target = cross / diag
    for _ in range(sweeps):
        for k in range(w.shape[-1]):
            step = w[..., k] - (w @ scaled[..., :, k, None])[..., 0] + target[..., k]
            np.maximum(step, 0.0, out=step)
            w[..., k] = step if bound == np.inf else np.minimum(step, bound)
    return w


def _costs(gram: np.ndarray, keys, weights: np.ndarray) -> np.ndarray:
    """Per-row squared errors ``|x_f - wᵀ X_S|² = H_ff - 2 wᵀ H_fS + wᵀ H_SS w``, ``(n_frames,)``."""
    cross = gram[:, keys]
    quad = ((weights @ gram[np.ix_(keys, keys)]) * weights).sum(axis=1)
    return np.maximum(np.diag(gram) - 2 * (weights * cross).sum(axis=1) + quad, 0.0)


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
