"""Compiled loops of the visibility-weighted smoothed solve (:mod:`keyshape.decompose._weighted`).

Compiled with the decorator of :mod:`keyshape.decompose._kernels`, where numba is imported. The
weighted QP has one Gram matrix per frame, ``G_t = Aᵀ V_t A`` (zero in a gap), so its Hessian
``P = blockdiag(G_t) + μ LᵀL ⊗ I`` is block pentadiagonal without the shared eigenbasis of the
unweighted one: these kernels build and apply it directly, frame-major (``x[t·K + k] = w_t[k]``).

Every kernel works on a sorted list of frames ``rows`` of the take (all of them, or windows
around the changes of an active-set step) and costs only those: a step on a few windows of a
long take costs the windows. A face's system is built on its free variables only, numbered
frame-major (:func:`number_face`), packed as its lower envelope (:func:`fill_face`) and factored
by the envelope Cholesky factorisation of :mod:`keyshape.decompose._kernels_face`, the one the
unweighted solve uses, each frame filled just before the elimination reaches it and the
forward substitution on the way (:func:`forward_face`, :func:`backward_face`,
:func:`solve_face`): each column costs its own reach, so a frame with few free variables costs
little, where a band costs its widest frame everywhere.
"""

from __future__ import annotations

import numpy as np

from ._kernels import jit, with_neighbours
from ._kernels_face import lay_out
from ._kernels_nnls import FREE, KKT_TOL, LOWER, UPPER, _subspace_minimiser, pivot_row


@jit
def _box_qp(G, c, upper, bounded, s, x, L, rhs, idx):
    """``min ½xᵀGx − cᵀx`` s.t. ``0 ≤ x ≤ u`` by block principal pivoting from the state ``s``
    (updated in place), as :func:`keyshape.decompose._kernels_nnls.block_pivoting` does for one
    row, on the caller's work arrays; ``x`` gets the last subspace minimiser (clipped). True
    if it meets the KKT conditions (to ``1e-11`` of the row's scale); a row where the exchanges
    stall keeps where it stopped (a start for the take's QP all the same)."""
    K = c.shape[0]
    g_max = 0.0
    for i in range(K):
        for j in range(K):
            g_max = max(g_max, abs(G[i, j]))
    solved = pivot_row(G, g_max, c, upper, bounded, s, x, L, rhs, idx, idx)  # idx marks the exchanges
    for i in range(K):
        x[i] = min(max(x[i], 0.0), upper[i])
    return solved


@jit
def _active_finish(G, c, upper, bounded, s, x, L, rhs, idx, z):
    """Primal active-set iterations (Nocedal & Wright 2006, Alg. 16.3) for ``min ½xᵀGx − cᵀx``,
    ``0 ≤ x ≤ u``, from the feasible ``x`` (its state ``s`` consistent with it), in place:
    monotone, so it ends where block principal pivoting stalls (degenerate rows: near-duplicate
    keys). True at the optimum (to ``1e-11`` of the row's scale); False on a singular free block
    or when out of iterations."""
    K = c.shape[0]
    g_max, c_max = 0.0, 0.0
    for i in range(K):
        c_max = max(c_max, abs(c[i]))
        for j in range(K):
            g_max = max(g_max, abs(G[i, j]))
    for _ in range(10 * K + 20):
        if not _subspace_minimiser(G, c, upper, s, z, L, rhs, idx):
            return False
        alpha, block = 1.0, -1
        for i in range(K):
            if s[i] != FREE:
                continue
            if z[i] < 0.0 and z[i] < x[i]:
                a = x[i] / (x[i] - z[i])
                if a < alpha:
                    alpha, block = a, i
            elif bounded and z[i] > upper[i] and z[i] > x[i]:
                a = (upper[i] - x[i]) / (z[i] - x[i])
                if a < alpha:
                    alpha, block = a, i
        for i in range(K):
            x[i] += alpha * (z[i] - x[i])
        if block >= 0:  # a free variable reached its bound first: it joins the bounds
            if x[block] <= 0.5 * upper[block] or not bounded:
                s[block], x[block] = LOWER, 0.0
            else:
                s[block], x[block] = UPPER, upper[block]
            continue
        scale = 1.0
        for i in range(K):
            scale = max(scale, 1.0 + abs(x[i]))
        tol_y = KKT_TOL * (c_max + g_max * scale)
        worst, size = -1, tol_y
        for i in range(K):  # at the face's minimiser: the bound with the most wrong-signed multiplier leaves
            if s[i] == FREE:
                continue
            y = -c[i]
            for j in range(K):
                y += G[i, j] * x[j]
            wrong = -y if s[i] == LOWER else y
            if wrong > size:
                worst, size = i, wrong
        if worst < 0:
            return True
        s[worst] = FREE
    return False


@jit
def frames_solve(G, C, upper, bounded, valid, X, stalled):
    """Every frame's own box QP, ``min ½wᵀG_t w − c_tᵀw``, ``0 ≤ w ≤ u``, equilibrated, by block
    principal pivoting from all free, finished by primal active-set iterations where the
    exchanges stall: ``X (T, K)``; ``stalled (T,)`` marks the frames (with data) that even
    those did not finish, for the caller. Frames without data are left."""
    T, K = C.shape
    L = np.zeros((K, K))
    rhs, idx = np.empty(K), np.empty(K, np.int64)
    state = np.empty(K, np.int8)
    H, c, u, d, x, z = np.empty((K, K)), np.empty(K), np.empty(K), np.empty(K), np.empty(K), np.empty(K)
    for t in range(T):
        stalled[t] = False
        if not valid[t]:
            continue
        for k in range(K):  # equilibrated, w = D v with D = diag(G_t)^(-1/2), as nnls_gram does
            state[k] = FREE
            d[k] = 1.0 / np.sqrt(G[t, k, k]) if G[t, k, k] > 0.0 else 1.0
        for a in range(K):
            c[a] = C[t, a] * d[a]
            u[a] = upper[a] / d[a]
            for b in range(K):
                H[a, b] = d[a] * G[t, a, b] * d[b]
        if not _box_qp(H, c, u, bounded, state, x, L, rhs, idx):  # stalled: the monotone finish
            for k in range(K):
                state[k] = LOWER if x[k] <= 0.0 else (UPPER if x[k] >= u[k] else FREE)
            stalled[t] = not _active_finish(H, c, u, bounded, state, x, L, rhs, idx, z)
        for k in range(K):
            X[t, k] = min(x[k] * d[k], upper[k])


@jit
def start(G, C, mu, d0, d1, d2, upper, bounded, valid, state, X, n_sweeps):
    """A first point ``X (T, K)`` and its active set ``state`` (FREE on entry).

    Every frame's own box QP first (no smoothness), ``min ½wᵀG_t w − c_tᵀw``, by block
    principal pivoting (a frame without data takes the frame's before it); then ``n_sweeps``
    symmetric block Gauss–Seidel sweeps over the frames of the whole QP: each frame's box QP
    ``min wᵀ(G_t + μ d0_t I)w − 2 wᵀ(c_t − μ Σ_s (LᵀL)_{ts} w_s)``, its neighbours ``s`` at their
    latest values, forward, then backward. Monotone in the objective, and a sweep carries a
    change along the whole take, where active-set steps move the edge of a run of free weights
    by about a frame per step. A start, not a solution.
    """
    T, K = C.shape
    L = np.zeros((K, K))
    rhs, idx = np.empty(K), np.empty(K, np.int64)
    for t in range(T):
        if not valid[t]:
            for k in range(K):
                state[t, k] = state[t - 1, k] if t > 0 else FREE
                X[t, k] = X[t - 1, k] if t > 0 else 0.0
            continue
        if t > 0:  # from the frame before's active set: neighbouring frames share most of it
            for k in range(K):
                state[t, k] = state[t - 1, k]
        _box_qp(G[t], C[t], upper, bounded, state[t], X[t], L, rhs, idx)
    sweep_rows(G, C, mu, d0, d1, d2, upper, bounded, np.arange(T), state, X, n_sweeps)


@jit
def sweep_rows(G, C, mu, d0, d1, d2, upper, bounded, rows, state, X, n_sweeps):
    """``n_sweeps`` symmetric block Gauss–Seidel sweeps over the frames ``rows`` (the others
    held): each frame's box QP ``min wᵀ(G_t + μ d0_t I)w − 2 wᵀ(c_t − μ Σ_s (LᵀL)_{ts} w_s)`` by
    block principal pivoting from its ``state``, forward, then backward; then ``state`` of
    ``rows`` read off ``X`` (at a bound or free). Monotone in the objective (see :func:`start`)."""
    K = C.shape[1]
    L = np.zeros((K, K))
    rhs, idx = np.empty(K), np.empty(K, np.int64)
    H = np.empty((K, K))
    r = np.empty(K)
    n = rows.shape[0]
    for sweep in range(2 * n_sweeps):
        for i in range(n):
            t = rows[i] if sweep % 2 == 0 else rows[n - 1 - i]
            for a in range(K):
                r[a] = C[t, a] - mu * with_neighbours(0.0, X, d1, d2, t, a)
                for b in range(K):
                    H[a, b] = G[t, a, b]
                H[a, a] += mu * d0[t]
            _box_qp(H, r, upper, bounded, state[t], X[t], L, rhs, idx)
    for i in range(n):
        t = rows[i]
        for k in range(K):
            state[t, k] = LOWER if X[t, k] <= 0.0 else (UPPER if X[t, k] >= upper[k] else FREE)


@jit
def _product(G, mu, d0, d1, d2, X, t, k):
    """``(P X)_{t,k} = (G_t x_t)_k + μ (LᵀL X)_{t,k}``."""
    K = X.shape[1]
    s = 0.0
    for m in range(K):
        s += G[t, k, m] * X[t, m]
    return s + mu * with_neighbours(d0[t] * X[t, k], X, d1, d2, t, k)


@jit
def hessian_at(G, mu, d0, d1, d2, X, rows, out):
    """``out[i] = (P X)_t`` for the frames ``t = rows[i]``; ``G (T, K, K)``, ``X (T, K)``;
    ``d0, d1, d2 (T,)`` the diagonals of ``LᵀL``, zero-padded."""
    for i in range(rows.shape[0]):
        for k in range(X.shape[1]):
            out[i, k] = _product(G, mu, d0, d1, d2, X, rows[i], k)


@jit
def number_face(state, rows, pos, reach, offset):
    """Number the free variables of the frames ``rows`` (sorted) frame-major and lay out the
    envelope of their face system: returns ``(n_free, size)``.

    ``state (T, K)`` int8; ``pos (len(rows), K)`` int64 receives each free variable's number
    (−1 where fixed); for the first ``n_free`` entries ``reach`` and ``offset`` (int64, at least
    ``len(rows)·K`` long) receive how far below the diagonal column ``j`` of the Cholesky factor
    reaches and where it starts in the packed storage, ``size`` numbers in all, as
    :func:`keyshape.decompose._kernels_face.number_free` lays them out. A free variable couples
    to the free ones of its frame and to its key in the next two frames, when those are among
    ``rows`` (the others are held), so the envelope is that of :mod:`._kernels_face` on runs of
    consecutive frames.
    """
    n = rows.shape[0]
    K = state.shape[1]
    p = 0
    for i in range(n):
        t = rows[i]
        for a in range(K):
            if state[t, a] == FREE:
                pos[i, a] = p
                p += 1
            else:
                pos[i, a] = -1
    return p, lay_out(pos, rows, reach, offset)


@jit
def _hold(top, state, X, rows):
    """The bound variables of the frames ``rows`` of ``X`` at their bounds (``top``: the upper
    bounds, 0 where there are none), the free ones at 0."""
    K = X.shape[1]
    for i in range(rows.shape[0]):
        t = rows[i]
        for a in range(K):
            X[t, a] = top[a] if state[t, a] == UPPER else 0.0


@jit
def _fill_frame(G, C, mu, d0, d1, d2, X, rows, pos, reach, offset, packed, rhs, i):
    """The packed columns and right-hand side of the free variables of frame ``rows[i]`` (see
    :func:`fill_face`)."""
    n = rows.shape[0]
    K = X.shape[1]
    t = rows[i]
    near = i + 1 < n and rows[i + 1] == t + 1
    far = i + 2 < n and rows[i + 2] == t + 2
    for a in range(K):
        j = pos[i, a]
        if j < 0:
            continue
        col = offset[j]
        for o in range(reach[j] + 1):
            packed[col + o] = 0.0
        packed[col] = G[t, a, a] + mu * d0[t]
        for b in range(a + 1, K):
            j2 = pos[i, b]
            if j2 >= 0:
                packed[col + j2 - j] = G[t, b, a]
        if near and pos[i + 1, a] >= 0:
            packed[col + pos[i + 1, a] - j] = mu * d1[t]
        if far and pos[i + 2, a] >= 0:
            packed[col + pos[i + 2, a] - j] = mu * d2[t]
        rhs[j] = C[t, a] - _product(G, mu, d0, d1, d2, X, t, a)


@jit
def fill_face(G, C, mu, d0, d1, d2, top, state, X, rows, pos, reach, offset, packed, rhs):
    """The face of the frames ``rows`` (the other frames held at ``X``) on its free variables,
    numbered by :func:`number_face`: ``P_FF`` packed as the lower envelope
    (``packed[offset[j] + o] = P_FF[j + o, j]`` for ``o ≤ reach[j]``, any values on entry, as
    :func:`keyshape.decompose._kernels_face.factor_face` reads it) and ``rhs[: n_free]`` with
    ``c_F − P_{F,·} X`` for ``X`` with the bound variables of ``rows`` at their bounds (``top``:
    the upper bounds, 0 where there are none) and the free ones at 0 (``X`` set so, in place).
    ``G (T, K, K)`` per frame, so unlike the unweighted face every frame has its own block.
    """
    _hold(top, state, X, rows)
    for i in range(rows.shape[0]):
        _fill_frame(G, C, mu, d0, d1, d2, X, rows, pos, reach, offset, packed, rhs, i)


@jit
def forward_face(G, C, mu, d0, d1, d2, state, X, rows, pos, reach, offset, packed, rhs):
    """The face of the frames ``rows`` factored and its forward substitution done, in one pass
    over the envelope: returns the number of free variables, −1 if the face is not positive
    definite. ``X`` must hold the face's fixed values (read only: see :func:`solve_face`).

    The free variables are numbered by :func:`number_face`; the Cholesky factorisation
    ``P_FF = L Lᵀ`` is that of :func:`keyshape.decompose._kernels_face.factor_face`
    (right-looking, column after column, the same operations in the same order), with each
    frame's columns filled (:func:`fill_face`) only just before the first column whose reach
    gets to them, and ``L y = r`` solved on each column as soon as it is final: the envelope
    is written, factored and read while it is in the cache, instead of three passes over
    memory. The column being eliminated is copied out first: its updates of the next columns
    then run over a separate array (about 1.3 times the speed). ``rhs[: n_free]`` receives
    ``y``.
    """
    n_free = number_face(state, rows, pos, reach, offset)[0]
    K = X.shape[1]
    here = np.empty(2 * K + 1)  # the column being eliminated, apart from the packed ones it updates
    filled, frame = 0, 0  # columns filled so far, the next frame to fill
    for j in range(n_free):
        last = reach[j] + 1
        while filled < j + last:  # every column this one updates is filled first
            _fill_frame(G, C, mu, d0, d1, d2, X, rows, pos, reach, offset, packed, rhs, frame)
            for a in range(K):
                filled += pos[frame, a] >= 0
            frame += 1
        c0 = offset[j]
        p = packed[c0]
        if not p > 0.0:
            return -1
        p = np.sqrt(p)
        packed[c0] = p
        for o in range(1, last):
            v = packed[c0 + o] / p
            packed[c0 + o] = v
            here[o] = v
        for a in range(1, last):
            la = here[a]
            if la == 0.0:
                continue
            row = packed[offset[j + a] : offset[j + a] + last - a]  # row[b − a] is M[j + b, j + a]
            col = here[a:last]
            for b in range(last - a):
                row[b] -= col[b] * la
        yj = rhs[j] / p  # L y = r, column j final
        rhs[j] = yj
        for o in range(1, last):
            rhs[j + o] -= here[o] * yj
    return n_free


@jit
def forward_tail(n, reach, offset, packed, j0, Y):
    """``L y = v`` in place for every column ``v`` of ``Y (n − j0, m)``, the entries ``j0 …
    n − 1`` of vectors zero before ``j0`` (``L (n, n)`` packed as by :func:`forward_face`): only
    the columns of ``L`` from ``j0`` on are read, and ``y`` is zero before ``j0`` too."""
    for j in range(j0, n):
        col = offset[j]
        for c in range(Y.shape[1]):
            yj = Y[j - j0, c] / packed[col]
            Y[j - j0, c] = yj
            for o in range(1, reach[j] + 1):
                Y[j + o - j0, c] -= packed[col + o] * yj


@jit
def backward_face(n, reach, offset, packed, y):
    """``Lᵀ x = y`` in place for ``y (n,)`` (``L`` packed as by :func:`forward_face`)."""
    for j in range(n - 1, -1, -1):
        c0 = offset[j]
        s = y[j]
        for o in range(1, reach[j] + 1):
            s -= packed[c0 + o] * y[j + o]
        y[j] = s / packed[c0]


@jit
def put_free(X, rows, pos, x):
    """``X[rows[i], a] = x[pos[i, a]]`` for the free variables (``pos ≥ 0``)."""
    K = X.shape[1]
    for i in range(rows.shape[0]):
        t = rows[i]
        for a in range(K):
            j = pos[i, a]
            if j >= 0:
                X[t, a] = x[j]


@jit
def solve_face(G, C, mu, d0, d1, d2, top, state, X, rows, pos, reach, offset, packed, rhs):
    """Frames ``rows`` (sorted) of ``X`` (in place) on the exact minimiser of their face, the
    other frames held: :func:`forward_face`, then ``Lᵀ x = y`` and the free values put back.
    Returns False (the free variables of ``rows`` left at 0) if the face is not positive
    definite. ``packed`` must hold the envelope (at most ``len(rows)·K·(2K + 1)`` numbers: a
    column reaches at most ``2K`` below the diagonal), ``rhs`` ``len(rows)·K``.
    """
    _hold(top, state, X, rows)
    n_free = forward_face(G, C, mu, d0, d1, d2, state, X, rows, pos, reach, offset, packed, rhs)
    if n_free < 0:
        return False
    backward_face(n_free, reach, offset, packed, rhs)
    put_free(X, rows, pos, rhs)
    return True


@jit
def hold(top, state, X, rows):
    """:func:`_hold` for the caller: the bound variables of ``rows`` at their bounds, the free
    ones at 0."""
    _hold(top, state, X, rows)


@jit
def around(frames, reach, n, out):
    """The sorted frames within ``reach`` of any of the sorted ``frames`` and inside ``0 … n − 1``,
    into ``out`` (room for ``len(frames)·(2·reach + 1)``): returns how many. One pass, merging
    each frame's interval with the one before."""
    m = 0
    end = -1  # the last frame written so far
    for i in range(frames.shape[0]):
        lo = max(frames[i] - reach, end + 1, 0)
        hi = min(frames[i] + reach, n - 1)
        for t in range(lo, hi + 1):
            out[m] = t
            m += 1
        end = max(end, hi)
    return m


@jit
def kkt(G, C, mu, d0, d1, d2, X, state, upper, rows, x_scale, g_scale, out):
    """Dimensionless KKT violations ``out (len(rows), K)`` of ``X`` on its face (``state``: 0 at
    the lower bound, 1 free, 2 at the upper one), with ``g = c − P X``: positive where the
    variable changes side in a primal–dual active-set step (a free one out of its box, a bound
    one pulled inside)."""
    K = X.shape[1]
    for i in range(rows.shape[0]):
        t = rows[i]
        for k in range(K):
            s = state[t, k]
            if s == FREE:
                out[i, k] = max(-X[t, k], X[t, k] - upper[k]) / x_scale
            else:
                g = C[t, k] - _product(G, mu, d0, d1, d2, X, t, k)
                out[i, k] = (g if s == LOWER else -g) / g_scale
