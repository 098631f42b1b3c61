"""Compiled block principal pivoting for the per-frame solver (:mod:`keyshape.decompose._nnls`).

Compiled with the decorator of :mod:`keyshape.decompose._kernels`, where numba is imported. One frame
at a time: every reduced system is at most ``K × K`` and factored by Cholesky in place, so the
loop allocates nothing per frame.
"""

from __future__ import annotations

import numpy as np

from ._kernels import jit
from ._reduced import FREE, KKT_TOL, LOWER, UPPER  # defined there: _nnls imports numba only to solve


@jit
def _subspace_minimiser(G, c, upper, s, x, L, rhs, idx):
    """``x`` minimising ``½xᵀGx − cᵀx`` with the bound variables of ``s`` at their bounds.

    The free block ``G_FF`` is factored by Cholesky in ``L`` (work, ``(K, K)``); ``rhs`` and
    ``idx`` are work vectors. Returns False if ``G_FF`` is not numerically positive definite.
    """
    K = c.shape[0]
    m = 0
    for i in range(K):
        x[i] = upper[i] if s[i] == UPPER else 0.0
        if s[i] == FREE:
            idx[m] = i
            m += 1
    for a in range(m):
        i = idx[a]
        r = c[i]
        for j in range(K):
            if s[j] == UPPER:
                r -= G[i, j] * upper[j]
        rhs[a] = r
        for b in range(a + 1):
            v = G[i, idx[b]]
            for p in range(b):
                v -= L[a, p] * L[b, p]
            if a == b:
                if not v > 0.0:
                    return False
                L[a, a] = np.sqrt(v)
            else:
                L[a, b] = v / L[b, b]
    for a in range(m):  # L z = rhs, then Lᵀ x_F = z
        v = rhs[a]
        for p in range(a):
            v -= L[a, p] * rhs[p]
        rhs[a] = v / L[a, a]
    for a in range(m - 1, -1, -1):
        v = rhs[a]
        for p in range(a + 1, m):
            v -= L[p, a] * rhs[p]
        rhs[a] = v / L[a, a]
        x[idx[a]] = rhs[a]
    return True


@jit
def block_pivoting(G, C, upper, bounded, state, X):
    """Block principal pivoting (Júdice & Pires 1994; Kim & Park 2011), row by row.

    For every row ``c`` of ``C (n, K)``: minimise ``½xᵀGx − cᵀx`` on the subspace of the
    current classification ``state[row]`` (LOWER / FREE / UPPER, updated in place), test the
    KKT conditions to ``1e-11`` of the row's scale, and exchange every variable that breaks
    one, while the number of such variables falls (or for 3 more sweeps: Kim & Park's
    trigger for their backup rule). ``X (n, K)`` receives the last subspace minimiser.

    Returns
    -------
    (n,) bool, the rows that stalled (or met a singular free block) — the caller finishes
    them with a monotone active-set method.
    """
    n, K = C.shape
    g_max = 0.0
    for i in range(K):
        for j in range(K):
            g_max = max(g_max, abs(G[i, j]))
    stalled = np.zeros(n, np.bool_)
    L = np.zeros((K, K))
    rhs, idx = np.empty(K), np.empty(K, np.int64)
    x, bad = np.empty(K), np.zeros(K, np.bool_)
    for r in range(n):
        solved = pivot_row(G, g_max, C[r], upper, bounded, state[r], x, L, rhs, idx, bad)
        for i in range(K):
            X[r, i] = x[i]
        stalled[r] = not solved
    return stalled


@jit
def pivot_row(G, g_max, c, upper, bounded, s, x, L, rhs, idx, bad):
    """One row of :func:`block_pivoting`: ``min ½xᵀGx − cᵀx`` on ``0 ≤ x ≤ u`` from the state
    ``s`` (updated in place), ``g_max = max |G|``; ``x`` receives the last subspace minimiser,
    ``L, rhs, idx`` are work arrays (as :func:`_subspace_minimiser`'s) and ``bad (K,)`` marks
    the variables that change side (it may be ``idx`` itself: it is read before the next
    subspace solve overwrites it). True if the KKT conditions hold, False if it stalled or
    met a singular free block."""
    K = c.shape[0]
    c_max = 0.0
    for i in range(K):
        c_max = max(c_max, abs(c[i]))
    best, budget = K + 1, 3
    for _ in range(2 * K + 10):
        if not _subspace_minimiser(G, c, upper, s, x, L, rhs, idx):
            return False
        scale = 1.0
        for i in range(K):
            scale = max(scale, 1.0 + abs(x[i]))
        tol_x, tol_y = KKT_TOL * scale, KKT_TOL * (c_max + g_max * scale)
        n_bad = 0
        for i in range(K):
            if s[i] == FREE:
                b = x[i] < -tol_x or (bounded and x[i] > upper[i] + tol_x)
            else:
                y = -c[i]
                for j in range(K):
                    y += G[i, j] * x[j]
                b = y > tol_y if s[i] == UPPER else y < -tol_y
            bad[i] = b
            n_bad += b
        if n_bad == 0:
            return True
        if n_bad < best:
            best, budget = n_bad, 3
        else:
            budget -= 1
            if budget < 0:
                return False
        for i in range(K):
            if bad[i]:
                if s[i] == FREE:
                    s[i] = LOWER if x[i] < 0.0 else UPPER
                else:
                    s[i] = FREE
    return False
