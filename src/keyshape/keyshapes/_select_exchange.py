"""Exchange search for :mod:`keyshape.keyshapes._select`: improve a key set by swaps that lower ``E_u``.

:func:`refine` proposes a row to add (largest first-order gain, or worst explained), fits
the keys plus that row, and drops the least important key when that lowers the error.
Every fit works on the Gram matrix ``H = X Xᵀ`` of the region's data matrix, with batched
coordinate descent (:func:`_cd_nnls`) warm-started from the current weights and run only on
the frames whose optimum can change; no fit touches ``X`` itself.

References
----------
.. [1] C. L. Lawson and R. J. Hanson, *Solving Least Squares Problems*, 1974, ch. 23.
"""

from __future__ import annotations

import numpy as np

__all__ = ["refine"]

_BLOCK = 256  # columns of H-sized temporaries computed at a time


def fit_added(gram, keys, weights, new, bound, sweeps: int = 12):
    """Weights and costs of ``keys + [new]``, refitting only where ``new`` can help."""
    grown = [*keys, new]
    w = np.column_stack([weights, np.zeros(len(gram))])
    rows = np.flatnonzero(weights @ gram[keys, new] - gram[:, new] < 0)
    w[rows] = _cd_nnls(gram[np.ix_(grown, grown)], gram[np.ix_(rows, grown)], w[rows], sweeps, bound)
    return w, _costs(gram, grown, w)


def refine(gram: np.ndarray, keys: list[int], weights: np.ndarray, cost: np.ndarray, *,
           bound: float = np.inf, max_swaps: int, patience: int = 4,
           allowed: np.ndarray | None = None):
    """Improve a key set by exchanges that lower ``E_u`` (``u = bound``).

    Each step proposes a row to add, alternately the one of largest first-order gain
    (``addition_gain``) and the worst-explained one; fits the keys plus that row; and
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
        score = addition_gain(gram, keys, weights, bound) if fails % 2 == 0 else cost.copy()
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


def addition_gain(gram: np.ndarray, keys, weights: np.ndarray, bound: float) -> np.ndarray:
    """First-order gain in ``E_u`` of adding each row as a key, ``(n_frames,)``.

    With the other weights fixed, the best weight of a new key ``c`` in frame ``f`` is
    ``a = clip(-g_fc / H_cc, 0, u)``, where ``g_fc = Σ_k w_fk H_kc - H_fc`` is the gradient,
    and it lowers that frame's error by ``a (-2 g_fc - a H_cc)``; the gain sums this over frames.
    """
    grad = weights @ gram[keys]  # (n_frames, n_candidates); in place from here: one more H-sized array
    grad -= gram
    diag = np.maximum(np.diag(gram), 1e-300)
    np.minimum(grad, 0.0, out=grad)  # only a negative gradient can gain
    if not np.isfinite(bound):  # a = -g / H_cc: the gain is g² / H_cc
        return np.einsum("fc,fc->c", grad, grad) / diag
    gain = np.empty(len(diag))
    for cols in column_blocks(grad.shape[1]):  # the step a and the gain by blocks of columns
        g, d = grad[:, cols], diag[cols]
        step = np.minimum(g / -d, bound)
        gain[cols] = np.einsum("fc,fc->c", step, -2 * g - step * d)
    return gain


def column_blocks(n: int, size: int = _BLOCK) -> list[slice]:
    """Slices of at most ``size`` columns covering ``0 … n − 1``."""
    return [slice(start, min(start + size, n)) for start in range(0, n, size)]


def _best_exchange(gram, keys, weights, new, bound, n_trials: int = 4, sweeps: int = 12):
    """Best set ``keys - {k} + {new}`` over the ``n_trials`` least important ``k``.

    Warm-started from ``weights (n_frames, n_keys)``, only the frames whose optimum can
    change are refitted: adding ``new`` matters only where its gradient is negative,
    removing ``k`` only where ``w_k > 0`` (elsewhere the old weights stay optimal).
    Returns ``(keys, weights, per-frame costs)`` of the best trial.
    """
    grown = [*keys, new]
    w, _ = fit_added(gram, keys, weights, new, bound, sweeps)
    importance = np.diag(gram)[keys] * (w[:, :-1] ** 2).sum(axis=0)
    drops = np.argsort(importance, kind="stable")[:n_trials]
    sets = [[k for i, k in enumerate(grown) if i != d] for d in drops]
    w_trials = np.stack([np.delete(w, d, axis=1) for d in drops])  # (n_trials, n_frames, n_keys)
    rows = np.flatnonzero((w[:, drops] > 0).any(axis=1))
    idx = np.array(sets)  # (n_trials, n_keys)
    g = gram[idx[:, :, None], idx[:, None, :]]  # (n_trials, n_keys, n_keys)
    c = np.moveaxis(gram[rows[:, None, None], idx[None]], 1, 0)  # (n_trials, n_rows, n_keys)
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
