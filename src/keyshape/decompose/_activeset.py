"""Active-set finish of the spacetime QP (:mod:`keyshape.decompose._spacetime`), for where ADMM stalls.

:func:`face_solve` minimises ``F`` exactly on a face of the constraint set (bound variables
fixed, active ``Σw = 1`` rows enforced) with one banded Cholesky factorisation;
:func:`exchange` is the primal–dual active-set update (Hintermüller, Ito & Kunisch 2003) and
:func:`active_set` the monotone primal active-set method (Nocedal & Wright 2006, Alg. 16.3)
that finishes where the exchanges cycle.
"""

from __future__ import annotations

import numpy as np

from . import _kernels
from ._kernels_nnls import FREE, LOWER, UPPER
from ._sequence import Best, Sequence, hessian_mul, multipliers, project

_ALM_STEPS = 30  # method-of-multipliers steps per Newton step for active Σw = 1 rows


def classify(seq: Sequence, Z: np.ndarray):
    """Variable states (LOWER / FREE / UPPER) and active-sum rows of a feasible ``Z``."""
    state = np.where(Z <= 0.0, LOWER, np.where(Z >= seq.upper, UPPER, FREE)).astype(np.int8)
    sums = (Z.sum(axis=1) >= 1.0 - 1e-12) if seq.convex else np.zeros(len(Z), bool)
    return state, sums


def face_band(seq: Sequence, free: np.ndarray, sums: np.ndarray, rho_s: float) -> np.ndarray:
    """Lower band ``(T·K, 2K + 1)`` of the face system, frame-major (see
    :func:`keyshape.decompose._kernels.face_band`): free rows and columns hold
    ``P + ρ_s Σ_{active t} 1 1ᵀ``, fixed ones the identity."""
    band = np.zeros((free.size, 2 * free.shape[1] + 1))
    _kernels.face_band(seq.G, seq.delta, float(seq.mu), *seq.gram, free, sums, float(rho_s), band)
    return band


def face_solve(seq: Sequence, state: np.ndarray, sums: np.ndarray):
    """Minimiser ``X (T, K)`` of ``F`` on a face, and the multipliers ``ν (T,)`` of its sums.

    Bound variables sit at their bounds; free ones solve ``P_FF x_F = c_F − P_FN x_N``, with
    ``Σ_t w_t = 1`` on the ``sums`` rows enforced by the method of multipliers (Hestenes 1969)
    on one banded Cholesky factorisation of ``P_FF + ρ_s Σ 1 1ᵀ``.
    """
    free = state == FREE
    fixed = np.where(state == UPPER, np.where(np.isfinite(seq.upper), seq.upper, 0.0), 0.0)
    # ρ_s ≈ 10 λ_max(P): the multiplier error then shrinks ≥ 10-fold per step
    rho_s = 10.0 * (float(np.abs(seq.G).sum(axis=1).max()) + 16.0 * seq.mu) if sums.any() else 0.0
    factor, mask = face_band(seq, free, sums, rho_s), free.ravel()
    if not _kernels.band_factor(factor, mask):
        raise np.linalg.LinAlgError("banded Cholesky failed on the face: not positive definite")
    rhs = seq.C - hessian_mul(seq, fixed)
    room = 1.0 - fixed.sum(axis=1)  # what the free variables of an active row must add up to
    nu = np.zeros(len(state))
    for _ in range(_ALM_STEPS if sums.any() else 1):
        r = (rhs - np.where(sums, nu - rho_s * room, 0.0)[:, None]) * free
        x = np.ascontiguousarray(r).reshape(-1)
        _kernels.band_solve(factor, mask, x)
        X = x.reshape(state.shape) * free
        excess = np.where(sums, X.sum(axis=1) - room, 0.0)
        nu += rho_s * excess
        if np.abs(excess).max() <= 1e-13:
            break
    return X + fixed, nu


def exchange(seq: Sequence, state, sums, X, nu, limit=None):
    """Primal–dual active-set update: the new ``(state, sums)`` and how many changed.

    Every variable that breaks its KKT condition on the current face changes side (free and
    out of bounds → bound; bound with a wrong-signed multiplier → free); likewise the sum
    rows (over-full → active; negative multiplier → inactive). With ``limit``, only that many
    of the largest (dimensionless) violations change, which damps the cycling a plain
    primal–dual active-set step can fall into on degenerate problems.
    """
    grad = hessian_mul(seq, X) - seq.C + np.where(sums, nu, 0.0)[:, None]  # ∇(F/2) + ν·1
    x_scale = 1.0 + np.abs(X).max()
    g_scale = (np.abs(seq.C).max() + np.abs(seq.G).max() + seq.mu) * x_scale
    primal = np.maximum(-X, X - seq.upper) / x_scale  # > 0: a free variable out of its box
    dual = np.where(state == LOWER, -grad, grad) / g_scale  # > 0: a bound one pulled inside
    size = np.where(state == FREE, primal, dual)
    rows = np.full(len(X), -np.inf)
    if seq.convex:
        rows = np.where(sums, -nu / g_scale, (X.sum(axis=1) - 1.0) / x_scale)
    if limit is not None:
        cut = np.sort(np.concatenate([size.ravel(), rows]))[-limit]
        size, rows = np.where(size >= cut, size, 0.0), np.where(rows >= cut, rows, 0.0)
    move, flip = size > 1e-11, rows > 1e-11
    to_bound = np.where(X < 0.0, LOWER, UPPER)
    new = np.where(move, np.where(state == FREE, to_bound, FREE), state).astype(np.int8)
    return new, sums ^ flip, int(move.sum() + flip.sum())


def active_set(seq: Sequence, best: Best, *, max_steps: int) -> None:
    """Primal active-set finish from ``best.Z`` (Nocedal & Wright 2006, Alg. 16.3).

    Monotone: each step moves to the face minimiser, or as far as the first blocking
    constraint allows and adds it; at a face minimiser the most wrong-signed multiplier
    leaves. Slow (one face per change) but sure where the active-set exchanges cycle.
    """
    x = best.Z
    state, sums = classify(seq, x)
    for _ in range(max_steps):
        X, nu = face_solve(seq, state, sums)
        nu = np.where(sums, nu, 0.0)
        p = X - x
        if np.abs(p).max() <= 1e-12 * (1.0 + np.abs(x).max()):
            best.offer(x, multipliers(seq, X, state, nu))
            if not _release(seq, state, sums, X, nu) or best.gap <= 0.0:
                return
            continue
        alpha, block = _ratio_test(seq, x, p, state, sums)
        x = project(x + alpha * p, seq.upper, seq.convex)
        if block is not None:
            _add(seq, state, sums, block, p)
        best.offer(x, multipliers(seq, X, state, nu) if block is None else None)


def _ratio_test(seq, x, p, state, sums):
    """Largest step ``α ≤ 1`` along ``p`` that stays feasible, and what blocks it."""
    free = state == FREE
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(free & (p < 0), -x / p, np.inf)
        a = np.minimum(a, np.where(free & (p > 0), (seq.upper - x) / p, np.inf))
        rows = np.full(len(x), np.inf)
        if seq.convex:
            rise = p.sum(axis=1)
            rows = np.where(~sums & (rise > 0), (1.0 - x.sum(axis=1)) / rise, np.inf)
    i = np.unravel_index(np.argmin(a), a.shape)
    t = int(np.argmin(rows))
    alpha = min(1.0, float(a[i]), float(rows[t]))
    if alpha >= 1.0:
        return 1.0, None
    return max(alpha, 0.0), (("row", t) if rows[t] <= a[i] else ("var", i))


def _add(seq, state, sums, block, p):
    kind, where = block
    if kind == "row":
        sums[where] = True
    else:
        state[where] = LOWER if p[where] < 0 else UPPER


def _release(seq, state, sums, X, nu) -> bool:
    """Free the constraint with the most wrong-signed multiplier; False if none is wrong."""
    grad = hessian_mul(seq, X) - seq.C + nu[:, None]
    wrong = np.where(state == LOWER, -grad, np.where(state == UPPER, grad, 0.0))
    rows = np.where(sums, -nu, 0.0)
    tol = 1e-11 * (np.abs(seq.C).max() + np.abs(seq.G).max() + seq.mu) * (1.0 + np.abs(X).max())
    i = np.unravel_index(np.argmax(wrong), wrong.shape)
    t = int(np.argmax(rows))
    if max(wrong[i], rows[t]) <= tol:
        return False
    if rows[t] > wrong[i]:
        sums[t] = False
    else:
        state[i] = FREE
    return True
