"""Compiled loops of the visibility-weighted smoothed solve (:mod:`keyshape.decompose._weighted`).

Compiled with the decorator of :mod:`keyshape.decompose._kernels`, where numba is imported. The
weighted QP has one Gram matrix per frame, ``G_t = Aᵀ V_t A`` (zero in a gap), so its Hessian
``P = blockdiag(G_t) + μ LᵀL ⊗ I`` is block pentadiagonal without the shared eigenbasis of the
unweighted one: these kernels build and apply it directly, frame-major (``x[t·K + k] = w_t[k]``).

Every kernel works on a sorted list of frames ``rows`` of the take (all of them, or windows
around the changes of an active-set step) and costs only those: a step on a few windows of a
long take costs the windows. A face's system is built on its free variables only, numbered in
order (:func:`compact_index`, :func:`compact_band`), as a band that LAPACK's banded Cholesky
(``dpbtrf``) factors: 2–3 times the speed of a compiled loop on a band ``2K`` wide.
"""

from __future__ import annotations

import numpy as np

from ._kernels import jit
from ._kernels_nnls import FREE, KKT_TOL, LOWER, UPPER, _subspace_minimiser


@jit
def hessian_at(G, mu, d0, d1, d2, X, rows, out):
    """``out[i] = (P X)_t = G_t x_t + μ (LᵀL X)_t`` for the frames ``t = rows[i]``.

    ``G (T, K, K)``, ``X (T, K)``; ``d0, d1, d2 (T,)`` the diagonals of ``LᵀL``, zero-padded.
    """
    T, K = X.shape
    for i in range(rows.shape[0]):
        t = rows[i]
        for k in range(K):
            s = 0.0
            for m in range(K):
                s += G[t, k, m] * X[t, m]
            r = d0[t] * X[t, k]
            if t >= 1:
                r += d1[t - 1] * X[t - 1, k]
            if t >= 2:
                r += d2[t - 2] * X[t - 2, k]
            if t + 1 < T:
                r += d1[t] * X[t + 1, k]
            if t + 2 < T:
                r += d2[t] * X[t + 2, k]
            out[i, k] = s + mu * r


@jit
def violations(X, g, state, upper, x_scale, g_scale, out):
    """Dimensionless KKT violations ``out`` of the face solution ``X`` with ``g = c − P X`` (all
    ``(n, K)``, rows of the same frames); positive where the variable changes side in a
    primal–dual active-set step. ``state``: 0 at the lower bound, 1 free, 2 at the upper one.
    """
    n, K = X.shape
    for i in range(n):
        for k in range(K):
            s = state[i, k]
            if s == 1:  # free: out of its box
                out[i, k] = max(-X[i, k], X[i, k] - upper[k]) / x_scale
            elif s == 0:  # at 0, pulled up (∇F/2 = −g < 0)
                out[i, k] = g[i, k] / g_scale
            else:  # at its bound, pulled down
                out[i, k] = -g[i, k] / g_scale


@jit
def _box_qp(G, c, upper, bounded, s, x, L, rhs, idx):
    """``min ½xᵀGx − cᵀx`` s.t. ``0 ≤ x ≤ u`` by block principal pivoting from the state ``s``
    (updated in place), as :func:`keyshape.decompose._kernels_nnls.block_pivoting` does for one
    row, on the caller's work arrays; ``x`` gets the last subspace minimiser (clipped). A start
    for the QP of the take, not a solution: a row where the exchanges stall keeps where it stopped."""
    K = c.shape[0]
    g_max, c_max = 0.0, 0.0
    for i in range(K):
        c_max = max(c_max, abs(c[i]))
        for j in range(K):
            g_max = max(g_max, abs(G[i, j]))
    best, budget = K + 1, 3
    for _ in range(2 * K + 10):
        if not _subspace_minimiser(G, c, upper, s, x, L, rhs, idx):
            break
        scale = 1.0
        for i in range(K):
            scale = max(scale, 1.0 + abs(x[i]))
        tol_x, tol_y = KKT_TOL * scale, KKT_TOL * (c_max + g_max * scale)
        n_bad = 0
        for i in range(K):  # the exchange: rhs[i] marks a variable that changes side
            if s[i] == FREE:
                b = x[i] < -tol_x or (bounded and x[i] > upper[i] + tol_x)
            else:
                y = -c[i]
                for j in range(K):
                    y += G[i, j] * x[j]
                b = y > tol_y if s[i] == UPPER else y < -tol_y
            idx[i] = 1 if b else 0
            n_bad += b
        if n_bad == 0:
            break
        if n_bad < best:
            best, budget = n_bad, 3
        else:
            budget -= 1
            if budget < 0:
                break
        for i in range(K):
            if idx[i]:
                if s[i] == FREE:
                    s[i] = LOWER if x[i] < 0.0 else UPPER
                else:
                    s[i] = FREE
    for i in range(K):
        x[i] = min(max(x[i], 0.0), upper[i])


@jit
def frame_states(G, C, upper, bounded, valid, state, X):
    """Every frame's own box QP (no smoothness), ``min ½wᵀG_t w − c_tᵀw``, by block principal
    pivoting: ``state (T, K)`` (FREE on entry) and ``X (T, K)``, its minimiser within the
    bounds; a frame without data takes the frame's before it. A start, not a solution."""
    T, K = C.shape
    L = np.zeros((K, K))
    rhs, idx = np.empty(K), np.empty(K, np.int64)
    for t in range(T):
        if not valid[t]:
            for k in range(K):
                state[t, k] = state[t - 1, k] if t > 0 else FREE
                X[t, k] = X[t - 1, k] if t > 0 else 0.0
            continue
        _box_qp(G[t], C[t], upper, bounded, state[t], X[t], L, rhs, idx)


@jit
def frame_sweeps(G, C, mu, d0, d1, d2, upper, bounded, state, X, rows, n_sweeps):
    """Symmetric block Gauss–Seidel sweeps over the frames ``rows`` of the QP: each frame's box QP
    ``min wᵀ(G_t + μ d0_t I)w − 2 wᵀ(c_t − μ Σ_s (LᵀL)_{ts} w_s)`` (block principal pivoting
    from its ``state``), its neighbours ``s`` at their latest values; forward, then backward.
    Monotone in the objective, and a sweep carries a change along the whole take, where
    active-set steps move the edge of a run of free weights by about a frame per step."""
    T, K = C.shape
    n = rows.shape[0]
    H = np.empty((K, K))
    r = np.empty(K)
    L = np.zeros((K, K))
    rhs, idx = np.empty(K), np.empty(K, np.int64)
    for sweep in range(2 * n_sweeps):
        for i in range(n):
            t = rows[i] if sweep % 2 == 0 else rows[n - 1 - i]
            for a in range(K):
                s = 0.0
                if t >= 1:
                    s += d1[t - 1] * X[t - 1, a]
                if t >= 2:
                    s += d2[t - 2] * X[t - 2, a]
                if t + 1 < T:
                    s += d1[t] * X[t + 1, a]
                if t + 2 < T:
                    s += d2[t] * X[t + 2, a]
                r[a] = C[t, a] - mu * s
                for b in range(K):
                    H[a, b] = G[t, a, b]
                H[a, a] += mu * d0[t]
            _box_qp(H, r, upper, bounded, state[t], X[t], L, rhs, idx)


@jit
def compact_index(free, rows, pos):
    """Number the free variables of ``free (n, K)`` (the frames ``rows``) in order into ``pos``
    (−1 where fixed); returns ``(n_free, kd)``, ``kd`` the half-bandwidth of the face system in
    that order: a free variable is coupled to the free ones of its frame and to its key in the
    next two frames (when those are among ``rows``)."""
    n, K = free.shape
    p = 0
    for i in range(n):
        for a in range(K):
            if free[i, a]:
                pos[i, a] = p
                p += 1
            else:
                pos[i, a] = -1
    kd = 0
    for i in range(n):
        last = -1
        for a in range(K):
            if pos[i, a] > last:
                last = pos[i, a]
        near = i + 1 < n and rows[i + 1] == rows[i] + 1
        far = i + 2 < n and rows[i + 2] == rows[i] + 2
        for a in range(K):
            q = pos[i, a]
            if q < 0:
                continue
            reach = last
            if near and pos[i + 1, a] > reach:
                reach = pos[i + 1, a]
            if far and pos[i + 2, a] > reach:
                reach = pos[i + 2, a]
            if reach - q > kd:
                kd = reach - q
    return p, kd


@jit
def compact_band(G, mu, d0, d1, d2, rows, pos, band):
    """The face system on the free variables of the frames ``rows`` (``pos``, their index from
    :func:`compact_index`; frames not in ``rows`` are held): ``band (n_free, kd + 1)`` with
    ``band[p, o] = M[p + o, p]``, whose transpose is LAPACK's lower band storage (``dpbtrf``)."""
    n, K = pos.shape
    W = band.shape[1]
    for i in range(n):
        t = rows[i]
        near = i + 1 < n and rows[i + 1] == t + 1
        far = i + 2 < n and rows[i + 2] == t + 2
        for a in range(K):
            p = pos[i, a]
            if p < 0:
                continue
            for o in range(W):
                band[p, o] = 0.0
            band[p, 0] = G[t, a, a] + mu * d0[t]
            for b in range(a + 1, K):
                q = pos[i, b]
                if q >= 0:
                    band[p, q - p] = G[t, b, a]
            if near and pos[i + 1, a] >= 0:
                band[p, pos[i + 1, a] - p] = mu * d1[t]
            if far and pos[i + 2, a] >= 0:
                band[p, pos[i + 2, a] - p] = mu * d2[t]
