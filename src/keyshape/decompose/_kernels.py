"""Compiled inner loops of the smoothed solve (:mod:`keyshape.decompose._spacetime`), through numba.

numba is imported here and nowhere else. Every kernel works on frame-major ``(T, K)`` arrays
(frame ``t``, key ``k``) in C order, so a sweep over frames touches memory in order and the
inner loop over keys vectorises. Compiled code is cached on disk (``cache=True``): the first
call in a fresh install compiles for a few seconds, later processes load it. Large arrays are allocated by the
callers (numpy), so that every big buffer shows in Python's memory accounting.

Kernels
-------
* :func:`penta_factor` / :func:`penta_solve` — ``K`` independent symmetric pentadiagonal
  systems of size ``T`` (one per key column), ``A = L D Lᵀ`` with unit lower ``L`` (Golub & Van
  Loan 2013, §4.3.6, banded ``LDLᵀ``). LAPACK's ``dpbtrs`` spends ~10× longer per unknown on a
  bandwidth of 2 than this loop does, because its inner kernels are built for wide bands.
* :func:`admm_step` — the relaxation, projection and dual update of one ADMM iteration, and
  the right-hand side of the next, in one pass over the data.
* :func:`project_rows` — Euclidean projection of each row on ``{0 ≤ w ≤ u, Σ w ≤ 1}``.
The other compiled kernels use this module's decorator: the per-frame solver's (block principal
pivoting) in :mod:`keyshape.decompose._kernels_nnls`, the factorisation of a face of the QP over
its free variables in :mod:`keyshape.decompose._kernels_face`, the weighted solve's in
:mod:`keyshape.decompose._kernels_weighted`.

References
----------
Golub, G. H. & Van Loan, C. F. (2013). *Matrix Computations*, 4th ed., §4.3. Johns Hopkins.
"""

from __future__ import annotations

import numba
import numpy as np

jit = numba.njit(cache=True, nogil=True)


# --------------------------------------------------------------------------- pentadiagonal


@jit
def penta_factor(a0, a1, a2, dinv, e, f):
    """``LDLᵀ`` of ``K`` symmetric pentadiagonal systems, one per column, whose
    off-diagonals are shared by all columns.

    Parameters
    ----------
    a0 : (T, K) float, the diagonals ``A[t, t]``
    a1 : (T,) float, ``A[t + 1, t]`` (entry ``T − 1`` unused)
    a2 : (T,) float, ``A[t + 2, t]`` (entries ``T − 2``, ``T − 1`` unused)

    dinv, e, f : (T, K) float each, filled with ``1 / D[t]``, ``L[t + 1, t]`` and
        ``L[t + 2, t]`` (allocated by the caller, so that memory shows in Python's accounting)

    Returns
    -------
    bool, False if a pivot is not positive (the matrix is not positive definite).
    """
    T, K = a0.shape
    e[:, :] = 0.0
    f[:, :] = 0.0
    d = np.zeros(K)  # D[t − 1]
    dd = np.zeros(K)  # D[t − 2]
    for t in range(T):
        for k in range(K):
            p = a0[t, k]
            if t >= 1:
                p -= e[t - 1, k] * e[t - 1, k] * d[k]
            if t >= 2:
                p -= f[t - 2, k] * f[t - 2, k] * dd[k]
            if not p > 0.0:
                return False
            if t + 1 < T:
                q = a1[t]
                if t >= 1:
                    q -= f[t - 1, k] * e[t - 1, k] * d[k]
                e[t, k] = q / p
            if t + 2 < T:
                f[t, k] = a2[t] / p
            dinv[t, k] = 1.0 / p
            dd[k] = d[k]
            d[k] = p
    return True


@jit
def penta_solve(dinv, e, f, y):
    """Solve ``L D Lᵀ x = y`` in place for ``y (T, K)`` (factors from :func:`penta_factor`).

    The forward sweep solves ``L z = y`` and stores ``D⁻¹ z``; the backward sweep ``Lᵀ x = D⁻¹ z``.
    """
    T, K = y.shape
    z1 = np.zeros(K)  # z[t − 1]
    z2 = np.zeros(K)  # z[t − 2]
    for t in range(T):
        for k in range(K):
            z = y[t, k]
            if t >= 1:
                z -= e[t - 1, k] * z1[k]
            if t >= 2:
                z -= f[t - 2, k] * z2[k]
            y[t, k] = z * dinv[t, k]
            z2[k] = z1[k]
            z1[k] = z
    for t in range(T - 2, -1, -1):
        for k in range(K):
            s = y[t, k] - e[t, k] * y[t + 1, k]
            if t + 2 < T:
                s -= f[t, k] * y[t + 2, k]
            y[t, k] = s


@jit
def add_smoothness(Y, X, delta, mu, d0, d1, d2):
    """``Y ← δ_t Y_t + μ (LᵀL X)_t`` in place: with ``Y = X G`` on entry, the Hessian product
    ``P X``. ``d0, d1, d2 (T,)``: the diagonals of ``LᵀL`` (``d1, d2`` padded)."""
    T, K = X.shape
    for t in range(T):
        for k in range(K):
            Y[t, k] = delta[t] * Y[t, k] + mu * with_neighbours(d0[t] * X[t, k], X, d1, d2, t, k)


@jit
def with_neighbours(s, X, d1, d2, t, k):
    """``s`` plus the off-diagonal terms of ``(LᵀL X)_{t,k}`` (frames ``t ± 1``, ``t ± 2``), added
    in that order; ``d1, d2 (T,)`` the padded off-diagonals of ``LᵀL``."""
    T = X.shape[0]
    if t >= 1:
        s += d1[t - 1] * X[t - 1, k]
    if t >= 2:
        s += d2[t - 2] * X[t - 2, k]
    if t + 1 < T:
        s += d1[t] * X[t + 1, k]
    if t + 2 < T:
        s += d2[t] * X[t + 2, k]
    return s


# --------------------------------------------------------------------------- projection


@jit
def _sum_at(v, u, tau):
    """``s(τ) = Σ_i clip(v_i − τ, 0, u_i)``."""
    s = 0.0
    for i in range(v.shape[0]):
        s += min(max(v[i] - tau, 0.0), u[i])
    return s


@jit
def _insert(sorted_, n, value):
    """Insert ``value`` into ``sorted_[:n]`` (ascending); returns ``n + 1``."""
    j = n
    while j > 0 and sorted_[j - 1] > value:
        sorted_[j] = sorted_[j - 1]
        j -= 1
    sorted_[j] = value
    return n + 1


@jit
def _capped_simplex_row(v, u, out, work):
    """``out ← argmin ‖z − v‖`` over ``{0 ≤ z ≤ u, Σ z ≤ 1}`` for one row (length ``K``).

    If clipping leaves the sum above 1, the answer is ``clip(v − τ, 0, u)`` with ``τ > 0``
    such that the sum is 1 (the KKT conditions of the projection). The sum ``s(τ)`` falls
    piecewise linearly with breakpoints at ``v_i`` and ``v_i − u_i``: a bisection over the
    sorted positive breakpoints (``work``, ``2K`` long) finds the piece, and ``τ`` is
    interpolated on it, exactly.
    """
    K = v.shape[0]
    s = 0.0
    for i in range(K):
        out[i] = min(max(v[i], 0.0), u[i])
        s += out[i]
    if s <= 1.0:
        return
    n = 0
    for i in range(K):
        if v[i] > 0.0:
            n = _insert(work, n, v[i])
        if v[i] - u[i] > 0.0:  # never for u = inf
            n = _insert(work, n, v[i] - u[i])
    lo, hi = -1, n - 1  # s(τ) > 1 at τ = 0 (lo = −1); s = 0 at the largest breakpoint, max v
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if _sum_at(v, u, work[mid]) > 1.0:
            lo = mid
        else:
            hi = mid
    ta = 0.0 if lo < 0 else work[lo]
    sa = s if lo < 0 else _sum_at(v, u, ta)
    tb = work[hi]
    sb = _sum_at(v, u, tb)
    tau = ta + (sa - 1.0) * (tb - ta) / (sa - sb) if sa > sb else tb
    for i in range(K):
        out[i] = min(max(v[i] - tau, 0.0), u[i])


@jit
def project_rows(V, upper, convex, out):
    """``out ← Π_C(V)`` row by row, ``C = {0 ≤ w ≤ u (, Σ w ≤ 1)}``; ``V, out (T, K)``."""
    T, K = V.shape
    work = np.empty(2 * K)
    for t in range(T):
        if convex:
            _capped_simplex_row(V[t], upper, out[t], work)
        else:
            for k in range(K):
                out[t, k] = min(max(V[t, k], 0.0), upper[k])


@jit
def admm_step(W, Z, U, C, rho, upper, alpha, convex):
    """One ADMM update after the linear step, in place; returns ``‖ΔZ‖²`` and ``‖Ŵ − Z‖²``.

    With ``Ŵ = αW + (1 − α)Z``: ``Z ← Π_C(Ŵ + U)``, ``U ← U + Ŵ − Z``; then ``W`` is
    overwritten with the next right-hand side ``C + ρ_t (Z − U)`` (Boyd et al. 2011,
    Eq. 3.5–3.7 and §3.4.3).

    W, Z, U, C : (T, K) float; rho : (T,) float; upper : (K,) float
    """
    T, K = W.shape
    v = np.empty(K)
    z = np.empty(K)
    work = np.empty(2 * K)
    dz = 0.0
    primal = 0.0
    for t in range(T):
        for k in range(K):
            v[k] = alpha * W[t, k] + (1.0 - alpha) * Z[t, k] + U[t, k]
        if convex:
            _capped_simplex_row(v, upper, z, work)
        else:
            for k in range(K):
                z[k] = min(max(v[k], 0.0), upper[k])
        for k in range(K):
            step = z[k] - Z[t, k]
            dz += step * step
            u = v[k] - z[k]
            r = u - U[t, k]  # Ŵ − Z
            primal += r * r
            Z[t, k] = z[k]
            U[t, k] = u
            W[t, k] = C[t, k] + rho[t] * (z[k] - u)
    return dz, primal


@jit
def point_multipliers(g, Z, upper, convex, Y):
    """Multipliers ``Y (T, K)`` (filled in place) read off a feasible ``Z (T, K)`` and ``g = c − P Z``.

    A variable at 0 keeps ``min(g − ν, 0)``, at its bound ``max(g − ν, 0)``, a free one 0;
    with ``convex``, a full row (``Σ z ≥ 1 − 1e−12``) gets ``ν_t`` = the mean of ``g`` over
    its free variables (at least 0), added to every entry of the row.
    """
    T, K = Z.shape
    for t in range(T):
        nu = 0.0
        if convex:
            total, gsum, nfree = 0.0, 0.0, 0
            for k in range(K):
                total += Z[t, k]
                if 0.0 < Z[t, k] < upper[k]:
                    gsum += g[t, k]
                    nfree += 1
            if total >= 1.0 - 1e-12:
                nu = max(gsum / max(nfree, 1), 0.0)
        for k in range(K):
            r = g[t, k] - nu
            if Z[t, k] <= 0.0:
                r = min(r, 0.0)
            elif Z[t, k] >= upper[k]:
                r = max(r, 0.0)
            else:
                r = 0.0
            Y[t, k] = nu + r


# --------------------------------------------------------------------------- weighted Gram form

_GRAM_FRAMES = 32  # frames of weighted_gram_rows' block: its V b (m × 32) stay in a core's cache


@jit
def weighted_gram_rows(points, rotations, translations, scales, face, neutral, seen, columns, A, T,
                       hidden_below, G, C, sq, gone):
    """The weighted Gram form of one region's frames (:class:`keyshape.decompose.GramTake`), in one pass.

    Frame ``f``'s points are brought to the canonical frame, ``y = Rᵀ (x - t) / s`` (as
    :func:`keyshape.alignment.to_canonical`), ``b = y - neutral``, and with ``v`` the region's
    visibility in the frame, ``G_f = Σ_p v_p H_p`` (``H_p`` the landmark's ``Σ_d a aᵀ``),
    ``c_f = Aᵀ V b`` and ``b_fᵀ V b_f`` are written straight into the region's rows: no
    temporary of the frames' size.

    Parameters
    ----------
    points : (n, p, d) float, the region's landmarks (image frame when posed)
    rotations : (n, d, d), translations : (n, d), scales : (n,) float, the frames' poses
        (``x = s R y + t``; the identity for points already aligned)
    face : (n,) bool, the frames with a face (the others get a zero Gram form)
    neutral : (p, d) float, the region's neutral landmarks
    seen : (n, n_seen) float, visibility rows; ``columns (p,)`` int: the region's landmarks in them
    A : (p·d, K) float, the keys' deltas, rows ``(landmark, dimension)``
    T : (p, K (K + 1) / 2) float, each landmark's ``H_p``, its upper triangle row by row
    hidden_below : float, a frame whose mean visibility is below this is gone (no data term)

    G : (n, K, K), C : (n, K), sq : (n,) float, gone : (n,) bool, written

    Returns
    -------
    bool, whether a frame with a face sees a landmark less than fully.
    """
    n, p, d = points.shape
    m, K = A.shape
    g = np.empty(T.shape[1])  # G_f's upper triangle
    vbT = np.empty((m, _GRAM_FRAMES))  # V_f b_f of a block of frames, frame after frame in a row
    cT = np.empty((K, _GRAM_FRAMES))
    S = np.empty((d, d))
    x = np.empty(d)
    hidden = False
    for f0 in range(0, n, _GRAM_FRAMES):
        nb = min(_GRAM_FRAMES, n - f0)
        for j in range(nb):
            f = f0 + j
            total, partial = 0.0, False
            for q in range(p):
                v = seen[f, columns[q]]
                total += v
                partial |= v < 1.0
            out = total / p < hidden_below
            gone[f] = out
            hidden |= partial and face[f]
            if out or not face[f]:  # no data term
                G[f] = 0.0
                sq[f] = 0.0
                vbT[:, j] = 0.0
                continue
            for a in range(d):
                for i in range(d):
                    S[a, i] = rotations[f, a, i] / scales[f]
            g[:] = 0.0
            total = 0.0
            for q in range(p):
                v = np.float64(seen[f, columns[q]])
                if v != 0.0:
                    for r in range(T.shape[1]):
                        g[r] += v * T[q, r]
                for a in range(d):
                    x[a] = points[f, q, a] - translations[f, a]
                here = 0.0
                for i in range(d):
                    y = 0.0
                    for a in range(d):
                        y += x[a] * S[a, i]
                    b = y - neutral[q, i]
                    vb = b * v
                    here += vb * b
                    vbT[q * d + i, j] = vb
                total += here
            sq[f] = total
            r = 0
            for k in range(K):
                for u in range(k, K):
                    G[f, k, u] = g[r]
                    G[f, u, k] = g[r]
                    r += 1
        # c_f = Aᵀ V_f b_f for the block: the innermost loop runs over its frames (no chain of sums)
        cT[:, :nb] = 0.0
        for row in range(m):
            for k in range(K):
                a_ = A[row, k]
                for j in range(nb):
                    cT[k, j] += vbT[row, j] * a_
        for j in range(nb):
            for k in range(K):
                C[f0 + j, k] = cT[k, j]
    return hidden
