"""Compiled loops of the visibility-weighted smoothed solve (:mod:`keyshape.decompose._weighted`).

Compiled with the decorator of :mod:`keyshape.decompose._kernels`, where numba is imported. The
weighted QP has one Gram matrix per frame, ``G_t = Aᵀ V_t A`` (zero in a gap), so its Hessian
``P = blockdiag(G_t) + μ LᵀL ⊗ I`` is block pentadiagonal without the shared eigenbasis of the
unweighted one: these kernels build and apply it directly, frame-major (``x[t·K + k] = w_t[k]``).

Every kernel works on a sorted list of frames ``rows`` of the take (all of them, or windows
around the changes of an active-set step) and costs only those: a step on a few windows of a
long take costs the windows. The band it fills is the layout of
:func:`keyshape.decompose._kernels.band_factor` and :func:`keyshape.decompose._kernels.band_solve`
(``band[j, o] = M[j + o, j]``, row ``j = i·K + k`` for frame ``rows[i]``), which factor and solve
it skipping fixed variables.
"""

from __future__ import annotations

import numpy as np

from ._kernels import jit
from ._kernels_nnls import block_pivoting


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
def face_band(G, mu, d0, d1, d2, free, rows, band):
    """The lower band ``(len(rows)·K, 2K + 1)`` of the face system on the frames ``rows``.

    ``free (len(rows), K)``: free rows and columns hold ``P`` (couplings to frames not in
    ``rows`` dropped: they are held), a fixed variable gets ``1`` on the diagonal and no free
    row or column refers to it.
    """
    n, K = free.shape
    W = 2 * K + 1
    for i in range(n):
        t = rows[i]
        near = i + 1 < n and rows[i + 1] == t + 1
        far = i + 2 < n and rows[i + 2] == t + 2
        for a in range(K):
            j = i * K + a
            for o in range(W):
                band[j, o] = 0.0
            if not free[i, a]:
                band[j, 0] = 1.0
                continue
            for o in range(K - a):
                if free[i, a + o]:
                    band[j, o] = G[t, a + o, a]
            band[j, 0] += mu * d0[t]
            if near and free[i + 1, a]:
                band[j, K] = mu * d1[t]
            if far and free[i + 2, a]:
                band[j, 2 * K] = mu * d2[t]


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
def frame_states(G, C, upper, bounded, valid, state):
    """The active set of every frame's own box QP (no smoothness), ``min ½wᵀG_t w − c_tᵀw``:
    ``state (T, K)`` (FREE on entry) by block principal pivoting, frame by frame; a frame
    without data takes the state of the frame before it. A guess to start from: a frame where
    pivoting stalls keeps where it stopped."""
    T, K = C.shape
    X = np.empty((1, K))
    for t in range(T):
        if not valid[t]:
            if t > 0:
                for k in range(K):
                    state[t, k] = state[t - 1, k]
            continue
        block_pivoting(G[t], C[t : t + 1], upper, bounded, state[t : t + 1], X)


@jit
def compact_index(free, pos):
    """Number the free variables of ``free (T, K)`` frame-major into ``pos`` (−1 where fixed);
    returns ``(n_free, kd)``, ``kd`` the half-bandwidth of the face system in that order (a free
    variable is coupled to the free ones of its frame and to its key in the next two frames)."""
    T, K = free.shape
    p = 0
    for t in range(T):
        for a in range(K):
            if free[t, a]:
                pos[t, a] = p
                p += 1
            else:
                pos[t, a] = -1
    kd = 0
    for t in range(T):
        last = -1
        for a in range(K):
            if pos[t, a] > last:
                last = pos[t, a]
        for a in range(K):
            q = pos[t, a]
            if q < 0:
                continue
            reach = last
            if t + 1 < T and pos[t + 1, a] > reach:
                reach = pos[t + 1, a]
            if t + 2 < T and pos[t + 2, a] > reach:
                reach = pos[t + 2, a]
            if reach - q > kd:
                kd = reach - q
    return p, kd


@jit
def compact_band(G, mu, d0, d1, d2, pos, band):
    """The face system of the whole take on its free variables only (``pos (T, K)``, their
    index, −1 where fixed): ``band (n_free, kd + 1)`` with ``band[p, o] = M[p + o, p]`` (its
    transpose is LAPACK's lower band storage, for ``dpbtrf``)."""
    T, K = pos.shape
    W = band.shape[1]
    for t in range(T):
        for a in range(K):
            p = pos[t, a]
            if p < 0:
                continue
            for o in range(W):
                band[p, o] = 0.0
            band[p, 0] = G[t, a, a] + mu * d0[t]
            for b in range(a + 1, K):
                q = pos[t, b]
                if q >= 0:
                    band[p, q - p] = G[t, b, a]
            if t + 1 < T and pos[t + 1, a] >= 0:
                band[p, pos[t + 1, a] - p] = mu * d1[t]
            if t + 2 < T and pos[t + 2, a] >= 0:
                band[p, pos[t + 2, a] - p] = mu * d2[t]
