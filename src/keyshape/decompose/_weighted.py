"""The solve with hidden landmarks: weighted least squares, weight = visibility.

A frame ``t`` whose landmarks have weights ``v_t`` in [0, 1] (:attr:`keyshape.Track.visibility`,
repeated over the coordinates) fits

.. math::

    \\sum_t \\lVert V_t^{1/2} (A w_t - b_t) \\rVert^2 + μ \\sum_t \\lVert w_{t+1} - 2 w_t + w_{t-1} \\rVert^2,
    \\qquad V_t = \\operatorname{diag}(v_t),

so a hidden landmark (a hand over the mouth) stops pulling the weights and a fully hidden
region is carried by the smoothness term from the frames around it, as a gap is.

* Frames whose region keeps less than ``HIDDEN`` of its weight have no data term: they are
  gaps (NaN rows), bridged exactly by the smoothed solve (NaN weights without smoothing).
* Without smoothing, every partly hidden frame is solved exactly on its own Gram matrix
  ``Aᵀ V_t A``.
* With smoothing (and no ``Σw ≤ 1``), the QP is solved exactly by primal–dual active-set steps
  (Hintermüller, Ito & Kunisch 2003) from the unweighted solution's active set: the Hessian
  ``blockdiag(Aᵀ V_t A) + μ LᵀL ⊗ I`` is banded (bandwidth ``2K``, frames in order), so each step
  is one banded Cholesky factorisation of its free variables (:func:`_active_set_solve`); the
  steps stop when the active set repeats, which is the optimum. On the embedded clip, where
  MediaPipe's landmarks read a few percent hidden in almost every frame, that is 3–6 steps.
* Otherwise, or should those steps cycle (they need not converge on every QP; then from where
  they stopped), majorise-minimise (Kiers 1997; Srebro & Jaakkola
  2003): as ``V_t ⪯ I``, ``‖V_t^{1/2}(A w − b_t)‖² ≤ ‖A w − \\tilde b_t‖² + const`` with the
  hidden part filled in from the current fit, ``\\tilde b_t = v_t ⊙ b_t + (1 − v_t) ⊙ A w_t^{(k)}``;
  each step is the unweighted solve on ``\\tilde B`` (the shared Gram matrix, the compiled
  kernels) and the objective never increases (up to 160 solves on the clip).

Frames with every landmark seen are not touched: a track without visibility, or an all-visible
region, takes the unweighted path unchanged.

References
----------
Kiers, H. A. L. (1997). Weighted least squares fitting using ordinary least squares algorithms.
*Psychometrika* 62(2), 251–266.
Srebro, N. & Jaakkola, T. (2003). Weighted low-rank approximations. *ICML*.
O'Donoghue, B. & Candès, E. (2015). Adaptive restart for accelerated gradient schemes.
*Found. Comput. Math.* 15, 715–732.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from ..exceptions import ConvergenceWarning
from ._nnls import nnls_gram
from ._sequence import second_difference_gram

__all__ = ["HIDDEN", "coordinate_weights", "solve_weighted"]

HIDDEN = 0.02  # a frame whose region keeps less of its weight (mean visibility) has no data term
MAX_STEPS = 500  # majorise-minimise steps of the smoothed solve
STEP_TOL = 1e-5  # ... until no weight moves by more than this


def coordinate_weights(seen: np.ndarray, n_dims: int) -> np.ndarray:
    """(n_frames, n_region_landmarks · n_dims): each landmark's visibility on its coordinates."""
    # rows of B are flattened (landmark, dimension) pairs, landmark-major
    return np.repeat(np.asarray(seen, dtype=float), n_dims, axis=1)


def solve_weighted(A: np.ndarray, B: np.ndarray, weight: np.ndarray, solve: Callable[[np.ndarray], np.ndarray], *,
                   smoothness: float, upper: np.ndarray, convex: bool, mu: float | None = None) -> np.ndarray:
    """(n_frames, K) weights of one region with per-frame, per-coordinate data weights.

    Parameters
    ----------
    A : (m, K) float
    B : (n_frames, m) float, NaN rows are frames without a face
    weight : (n_frames, m) float in [0, 1]
    solve : the unweighted solve of the region, ``B (n_frames, m) -> (n_frames, K)`` (NaN rows gaps)
    smoothness : float, 0 for per-frame solves
    upper : (K,) float; convex : bool (for the exact per-frame solves)
    mu : float, optional
        The smoothness term's weight ``μ`` that ``solve`` uses; with it (and not ``convex``) the
        smoothed problem is solved exactly by active-set steps, else by majorise-minimise.
    """
    B = np.array(B, dtype=float)
    gone = weight.mean(axis=1) < HIDDEN
    B[gone] = np.nan
    partial = np.flatnonzero(np.isfinite(B).all(axis=1) & (weight < 1.0).any(axis=1))
    start = None
    if partial.size and smoothness > 0.0 and mu is not None and mu > 0.0 and not convex:
        found = _active_set_solve(A, B, weight, None, mu, np.asarray(upper, dtype=float))
        if found is not None and found[1]:
            return found[0]
        start = None if found is None else found[0]  # cycling: majorise-minimise finishes from here
    if start is not None:
        return _majorise(A, B, weight[partial], partial, start, solve)
    W = solve(B)
    if not partial.size:
        return W
    if smoothness == 0.0:
        for t in partial:
            Av = A * weight[t][:, None]  # V_t A
            W[t] = nnls_gram(Av.T @ A, (B[t] @ Av)[None], upper, convex)[0]
        return W
    return _majorise(A, B, weight[partial], partial, W, solve)


MAX_EXCHANGES = 50  # active-set steps of the exact smoothed solve before majorise-minimise takes over


def _active_set_solve(A, B, weight, W, mu, upper):
    """The exact minimiser ``(n_frames, K)`` of the weighted smoothed QP by primal–dual active-set
    steps from the active set of ``W`` (None: every variable free, so the first step is the
    unconstrained smooth fit): ``(X, True)``; ``(X, False)`` with a feasible ``X`` near it when
    the exchanges cycle (primal–dual active-set steps need not converge on every QP), None when
    a face is singular.

    Variables are ordered frame-major, ``x[t·K + k] = w_t[k]``; the Hessian ``P`` (half of the
    objective's) is ``G_t = Aᵀ V_t A`` on the diagonal blocks (zero in gaps) plus ``μ LᵀL ⊗ I``,
    lower bandwidth ``2K``. A step fixes the variables at their bounds, solves the free ones
    exactly, then moves each variable by the sign of ``x − (Px − c)/diag P`` against its bounds
    (the semismooth Newton update); an active set that no longer changes is the optimum. Once
    only a few variables change per step, the steps run on windows of ``WINDOW`` frames around
    them, the rest of the take held, and the whole take is checked again after each.
    """
    from scipy.linalg import LinAlgError, cho_solve_banded, cholesky_banded

    n, K = B.shape[0], A.shape[1]
    seen = np.isfinite(B).all(axis=1)
    if n < 3 or not seen.any() or (W is not None and not np.isfinite(W).all()):
        return None
    v = np.where(seen[:, None], weight, 0.0)
    G = np.einsum("mk,tm,ml->tkl", A, v, A)  # (n, K, K)
    c = (v * np.where(seen[:, None], B, 0.0)) @ A  # (n, K)
    d0, d1, d2 = second_difference_gram(n)
    band = np.zeros((2 * K + 1, n * K))  # lower form: band[i, j] = P[j + i, j]
    for i in range(K):  # within a frame: P[tK + k + i, tK + k] = G_t[k + i, k]
        rows = np.zeros((n, K))
        rows[:, : K - i] = np.diagonal(G, offset=-i, axis1=1, axis2=2)
        band[i] += rows.ravel()
    band[0] += mu * np.repeat(d0, K)
    band[K, : (n - 1) * K] += mu * np.repeat(d1, K)
    band[2 * K, : (n - 2) * K] += mu * np.repeat(d2, K)
    diag = band[0].reshape(n, K)
    top = np.broadcast_to(np.where(np.isfinite(upper), upper, np.inf), (n, K))

    def hessian(X, lo=0, hi=n):
        """Rows lo..hi-1 of ``P X``."""
        t = np.arange(lo, hi)
        out = np.einsum("tkl,tl->tk", G[lo:hi], X[lo:hi]) + mu * d0[lo:hi, None] * X[lo:hi]
        for step, diagonal in ((1, d1), (2, d2)):
            back, ahead = t >= step, t + step < n
            out[back] += mu * diagonal[t[back] - step, None] * X[t[back] - step]
            out[ahead] += mu * diagonal[t[ahead], None] * X[t[ahead] + step]
        return out

    def update(X, lo=0, hi=n):
        """The semismooth Newton states of frames lo..hi-1."""
        y = X[lo:hi] - (hessian(X, lo, hi) - c[lo:hi]) / diag[lo:hi]
        # within _SLACK of a bound counts as on it: a weight at 1e-13 with a multiplier of -1e-13
        # would otherwise flip between free and bound for ever (degenerate variables)
        return np.where(y <= _SLACK, -1, np.where(y >= top[lo:hi] - _SLACK, 1, 0))

    def solve_range(X, state, lo, hi):
        """Frames lo..hi-1 of X (in place) on the exact minimiser of their face, the others held."""
        sub = state[lo:hi]
        fixed = np.where(sub == 1, top[lo:hi], 0.0)
        X[lo:hi] = fixed
        free = (sub == 0).ravel()
        rhs = (c[lo:hi] - hessian(X, lo, hi)).ravel()
        face = buffer[:, : (hi - lo) * K]
        np.copyto(face, band[:, lo * K : hi * K])
        for i in range(1, 2 * K + 1):  # no coupling past the range's end
            face[i, face.shape[1] - i :] = 0.0
        face[:, ~free] = 0.0  # fixed columns ...
        for i in range(1, 2 * K + 1):  # ... and rows: P[j + i, j] with j + i fixed
            face[i, : free.size - i][~free[i:]] = 0.0
        face[0, ~free] = 1.0
        factor = cholesky_banded(face, lower=True, overwrite_ab=True, check_finite=False)
        x = cho_solve_banded((factor, True), np.where(free, rhs, 0.0), overwrite_b=True, check_finite=False)
        X[lo:hi] = np.where(free.reshape(-1, K), x.reshape(-1, K), fixed)
        return X

    buffer = np.empty_like(band)  # the face systems, one at a time
    X = np.zeros((n, K)) if W is None else np.clip(W, 0.0, top)
    state = np.zeros((n, K), np.int64) if W is None else np.where(X <= 0.0, -1, np.where(X >= top, 1, 0))
    few = max(8, n * K // FEW)
    least, since = np.inf, 0
    try:
        for _ in range(MAX_EXCHANGES):
            X = solve_range(X, state, 0, n)  # a face of the whole take: exact everywhere
            new = update(X)
            changed = new != state
            state = new
            if not changed.any():
                return X, True
            least, since = (changed.sum(), 0) if changed.sum() < least else (least, since + 1)
            if since >= STALL:  # the exchanges cycle: hand over to majorise-minimise from here
                break
            for _ in range(WINDOW_ROUNDS if changed.sum() <= few else 0):  # few changes: windows around them
                for lo, hi in _windows(np.flatnonzero(changed.any(axis=1)), n):
                    for _ in range(MAX_EXCHANGES):
                        X = solve_range(X, state, lo, hi)
                        new = update(X, lo, hi)
                        inside = (new != state[lo:hi]).any()
                        state[lo:hi] = new
                        if not inside:
                            break
                new = update(X)
                changed = new != state
                state = new
                if not changed.any() or changed.sum() > few:
                    break
    except LinAlgError:
        return None
    return np.clip(X, 0.0, top), False


WINDOW = 40  # frames on either side of a change that a window step re-solves
FEW = 100  # windows once at most 1 in FEW variables changes in a step
STALL = 5  # steps on the whole take without fewer changes than before: the exchanges cycle
_SLACK = 1e-10  # weights (of order 1) this close to a bound are on it
WINDOW_ROUNDS = 8  # sweeps of windows between two steps on the whole take


def _windows(frames: np.ndarray, n: int):
    """Disjoint ranges ``(lo, hi)`` covering ``WINDOW`` frames around each of ``frames``."""
    out = []
    for f in np.sort(frames):
        lo, hi = max(int(f) - WINDOW, 0), min(int(f) + WINDOW + 1, n)
        if out and lo <= out[-1][1] + 2:
            out[-1] = (out[-1][0], hi)
        else:
            out.append((lo, hi))
    return out


def _majorise(A, B, v, partial, W, solve):
    """Majorise-minimise steps from ``W`` until the weights settle (see the module notes).

    Each step is a proximal-gradient step in the metric ``AᵀA`` (the smoothness and the bounds
    are its proximal part), so Nesterov's extrapolation applies: steps from ``Y = W_k + β_k
    (W_k − W_{k−1})``, restarted whenever a step turns back (O'Donoghue & Candès 2015).
    """
    seen, Y, momentum = v * B[partial], W, 1.0
    for _ in range(MAX_STEPS):
        B[partial] = seen + (1.0 - v) * (Y[partial] @ A.T)  # b̃_t = v ⊙ b_t + (1 − v) ⊙ A y_t
        new = solve(B)
        move = new - W
        step = np.nanmax(np.abs(move), initial=0.0)
        if step < STEP_TOL:
            return new
        if np.nansum((Y - new) * move) > 0.0:  # the step turned back: restart the momentum
            momentum = 1.0
        following = (1.0 + np.sqrt(1.0 + 4.0 * momentum**2)) / 2.0
        Y = new + ((momentum - 1.0) / following) * move
        W, momentum = new, following
    warnings.warn(f"the visibility-weighted solve stopped after {MAX_STEPS} steps with weights still moving by "
                  f"{step:.2g}", ConvergenceWarning, stacklevel=4)
    return W
