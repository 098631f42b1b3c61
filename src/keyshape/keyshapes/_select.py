"""Selection kernels for :mod:`keyshape.keyshapes._search`.

Each kernel takes the data matrix ``X (n_frames, n_features)`` of one region, rows being
candidate frames minus the neutral frame, and returns ``(n_keys,)`` distinct row indices.
They know nothing about tracks or regions.

The quality of a key set ``S`` is the error of the best blend of its keys in every frame,

.. math::

    E_u(S) = \\sum_f \\min_{0 \\le w \\le u} \\lVert x_f - \\textstyle\\sum_{k \\in S} w_k x_k \\rVert^2,

with ``u = ∞`` for plain non-negative least squares (the paper) or ``u = 1`` when weights
are bounded as the product solves them. Under a bound a key close to the neutral is of
little use (it can only be reached at ``w ≤ u``), so ``spa`` picks strong expressions.

This module holds :class:`Objective`, :func:`steps` and ``spa`` (:func:`spa`,
:func:`spa_steps`). The paper's ``spread`` and ``hull`` (with :func:`principal_axes`) are
in :mod:`keyshape.keyshapes._select_pca`, the exchange search :func:`refine` in
:mod:`keyshape.keyshapes._select_exchange`; both are re-exported here.

The search keeps the Gram matrix ``H = X Xᵀ`` (``n_frames²`` floats, and one more array of
that size while it scores additions). For a long ``X``, :func:`pool` picks the rows to
search among (the paper's candidates, successive-projection and farthest-point extremes,
evenly spaced rows) in time and memory linear in ``n_frames``, and :func:`squared_error`
measures a key set on every row block by block.

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

from ..decompose import solve_nnls
from ._select_exchange import addition_gain, column_blocks, fit_added, refine
from ._select_pca import Pool, hull, pool, principal_axes, spread

__all__ = ["MIN_STRENGTH", "Objective", "Pool", "hull", "pool", "principal_axes", "refine", "spa", "spa_steps",
           "spread", "squared_error", "steps"]

_PATIENCE = 4
MIN_STRENGTH = 0.25  # spa keys: delta at least this fraction of the region's 95th-percentile delta


class Objective:
    """The exact error ``E_u(S)`` of key sets ``S`` (rows of ``X``), each set fitted once.

    Fits are exact batched bounded NNLS (:func:`keyshape.decompose._solve.solve_nnls`). Errors are
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


def steps(X: np.ndarray, method: str, *, upper: float | None = None,
          objective: Objective | None = None, axes: np.ndarray | None = None,
          q95: float | None = None) -> Iterator[np.ndarray]:
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
    axes, q95 : keyword-only
        Those of the whole take when ``X`` is a :class:`Pool` of it (see :func:`spa_steps`).

    Yields
    ------
    (K,) int, distinct rows of ``X``
    """
    if method == "spa":
        yield from spa_steps(X, upper=upper, objective=objective, axes=axes, q95=q95)
        return
    kernel = spread if method == "spread" else hull
    axes = principal_axes(X) if axes is None else axes
    for k in range(1, len(X) + 1):
        yield kernel(X, k, axes=axes)


def spa(X: np.ndarray, n_keys: int, *, upper: float | None = None,
        objective: Objective | None = None, min_strength: float | None = None,
        axes: np.ndarray | None = None, q95: float | None = None) -> np.ndarray:
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
    min_strength, axes, q95 : keyword-only
        See :func:`spa_steps`.

    Returns
    -------
    (n_keys,) int, distinct rows of ``X``
    """
    steps = spa_steps(X, upper=upper, objective=objective, min_strength=min_strength, axes=axes, q95=q95)
    return next(islice(steps, n_keys - 1, None))


def spa_steps(X: np.ndarray, *, upper: float | None = None, objective: Objective | None = None,
              min_strength: float | None = None, axes: np.ndarray | None = None,
              q95: float | None = None) -> Iterator[np.ndarray]:
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
       (``addition_gain``) and the worst-explained row.
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
    axes : (rank, n_features) float, optional, keyword-only
        Principal axes for the ``spread`` and ``hull`` seeds; default those of ``X``.
    q95 : float, optional, keyword-only
        The range of motion ``q95``; default that of the rows of ``X``. A :class:`Pool` of a
        long take gives both from all its rows.

    Yields
    ------
    (K,) int, distinct rows of ``X``
    """
    obj = objective if objective is not None else Objective(X, upper)
    if not len(obj.X):
        return
    axes = principal_axes(obj.X) if axes is None else axes  # as in steps(): the seeds' fits are shared
    strength = np.sqrt(np.diag(obj.gram))
    q95 = np.quantile(strength, 0.95) if q95 is None else q95
    floor = (MIN_STRENGTH if min_strength is None else min_strength) * q95
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
    error = np.empty(len(diag))
    for cols in column_blocks(len(diag)):  # by blocks of columns: no second H-sized array
        h, d = gram[:, cols], diag[cols]
        a = np.clip(h / d, 0.0, bound)  # a_fc, the best weight of c in frame f
        error[cols] = (a * (a * d - 2 * h)).sum(axis=0)
    return int(np.argmin(np.where(allowed, error, np.inf)))


def _grow(obj: Objective, keys: list[int], weights: np.ndarray, cost: np.ndarray, allowed: np.ndarray):
    """Add the best of three proposed rows (see :func:`spa_steps`); ``(keys, weights, cost)``."""
    gram, taken = obj.gram, ~allowed
    taken[keys] = True
    basis = np.linalg.qr(obj.X[keys].T)[0]  # orthonormal span of the keys
    far = np.diag(gram) - ((obj.X @ basis) ** 2).sum(axis=1)  # squared distance to the span
    scores = (far, addition_gain(gram, keys, weights, obj.bound), cost)
    proposals = list(dict.fromkeys(int(np.argmax(np.where(taken, -np.inf, s))) for s in scores))
    trials = [fit_added(gram, keys, weights, new, obj.bound) for new in proposals]
    best = int(np.argmin([c.sum() for _, c in trials]))
    return [*keys, proposals[best]], *trials[best]


def _against_seeds(obj: Objective, keys: list[int], seeds: list[np.ndarray], allowed: np.ndarray):
    """Keep ``keys`` unless exchanges from the best seed set reach a lower exact ``E_u``."""
    errors = [obj(s) for s in seeds]
    if errors and obj(keys) >= min(errors):
        seed = [int(i) for i in seeds[int(np.argmin(errors))]]
        again = refine(obj.gram, seed, *obj.fit(seed), bound=obj.bound, max_swaps=2 * len(seed),
                       allowed=allowed)[0]
        keys = again if obj(again) < obj(keys) else keys
    return keys, *obj.fit(keys)


_BLOCK_ROWS = 4096  # rows per block of the exact error of a long X


def squared_error(X: np.ndarray, rows, upper: float | None = None) -> float:
    """``E_u(rows)`` over every row of ``X``, block by block: :class:`Objective`'s value with
    no rows × rows array (memory linear in ``len(X)``, bounded per block)."""
    basis = X[np.asarray(rows, dtype=int)]
    total = 0.0
    for start in range(0, len(X), _BLOCK_ROWS):
        block = X[start:start + _BLOCK_ROWS]
        w = solve_nnls(basis.T, block, upper=upper)
        total += float(((block - w @ basis) ** 2).sum())
    return total
