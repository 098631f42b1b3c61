"""Compiled factorisation of one face of the smoothed QP (:mod:`keyshape.decompose._activeset`).

On a face the bound variables are fixed, and the free ones solve ``P_FF x = r``, ``P`` block
pentadiagonal (``blockdiag(δ_t G) + μ LᵀL ⊗ I_K``). Numbering only the free variables, frame
by frame, keeps ``P_FF`` banded (a free variable couples to the free ones of its own frame and
to itself in the next two frames) and drops the fixed ones from the factorisation entirely:
at the solutions of these problems about half of the variables sit at a bound, and a band
over all ``T·K`` variables with identity rows for the fixed ones costs several times more.

The factorisation is Cholesky on a *variable* band (an envelope; Golub & Van Loan 2013,
§4.3.5 and §10.3 of George & Liu 1981): column ``j`` of the factor has no nonzero below row
``last[j] = max_{k ≤ j} (last nonzero row of column k of P_FF)``, since fill-in stays inside the
envelope, so each column's elimination runs over its own reach instead of the widest one.
A frame with few free variables then costs little.

* :func:`number_free` — compressed indices of the free variables and each column's reach;
* :func:`fill_face` — the lower band of ``P_FF (+ ρ_s Σ_{active t} 1 1ᵀ)``;
* :func:`factor_face` / :func:`solve_face` — ``P_FF = L Lᵀ`` in place, and ``L Lᵀ x = r``.

References
----------
George, A. & Liu, J. W. (1981). *Computer Solution of Large Sparse Positive Definite Systems*.
Prentice-Hall (envelope methods, ch. 4).
Golub, G. H. & Van Loan, C. F. (2013). *Matrix Computations*, 4th ed., §4.3. Johns Hopkins.
"""

from __future__ import annotations

import numpy as np

from ._kernels import jit


@jit
def number_free(free, index, reach):
    """Number the free variables frame-major; returns ``(n_free, width)``.

    ``free (T, K)`` bool; ``index (T, K)`` int64 receives each free variable's number (−1 when
    fixed); ``reach (T·K,)`` int64 receives, for the first ``n_free`` entries, how far below the
    diagonal column ``j`` of the factor reaches (its envelope); ``width`` is the largest reach.
    """
    T, K = free.shape
    n = 0
    for t in range(T):
        for i in range(K):
            if free[t, i]:
                index[t, i] = n
                n += 1
            else:
                index[t, i] = -1
    low = 0  # max over the columns so far of their last nonzero row (absolute)
    width = 0
    for t in range(T):
        last_here = -1  # the frame's last free variable: the within-frame couplings reach it
        for i in range(K):
            if index[t, i] >= 0:
                last_here = index[t, i]
        for i in range(K):
            j = index[t, i]
            if j < 0:
                continue
            deepest = last_here
            if t + 1 < T and index[t + 1, i] >= 0:
                deepest = max(deepest, index[t + 1, i])
            if t + 2 < T and index[t + 2, i] >= 0:
                deepest = max(deepest, index[t + 2, i])
            low = max(low, deepest)
            reach[j] = low - j
            width = max(width, low - j)
    return n, width


@jit
def fill_face(G, delta, mu, d0, d1, d2, index, sums, rho_s, band):
    """Fill ``band (n_free, width + 1)`` (any values on entry): ``band[j, o] = M[j + o, j]`` for the
    free rows and columns of ``M = P + ρ_s Σ_{active t} 1 1ᵀ`` (``d0, d1, d2 (T,)`` the diagonals
    of ``LᵀL``; ``sums (T,)`` the active rows), zero elsewhere."""
    T, K = index.shape
    for t in range(T):
        pen = rho_s if sums[t] else 0.0
        for i in range(K):
            j = index[t, i]
            if j < 0:
                continue
            for o in range(band.shape[1]):
                band[j, o] = 0.0
            for i2 in range(i, K):
                j2 = index[t, i2]
                if j2 >= 0:
                    band[j, j2 - j] = delta[t] * G[i2, i] + pen
            band[j, 0] += mu * d0[t]
            if t + 1 < T and index[t + 1, i] >= 0:
                band[j, index[t + 1, i] - j] = mu * d1[t]
            if t + 2 < T and index[t + 2, i] >= 0:
                band[j, index[t + 2, i] - j] = mu * d2[t]


@jit
def factor_face(band, reach):
    """Cholesky ``M = L Lᵀ`` in place on the band of :func:`fill_face`, column ``j`` over
    ``reach[j]`` rows below the diagonal (right-looking); False if not positive definite."""
    n = band.shape[0]
    for j in range(n):
        p = band[j, 0]
        if not p > 0.0:
            return False
        p = np.sqrt(p)
        band[j, 0] = p
        col = band[j]
        last = reach[j] + 1
        for o in range(1, last):
            col[o] /= p
        for a in range(1, last):
            la = col[a]
            if la == 0.0:
                continue
            row = band[j + a]
            for b in range(a, last):  # contiguous: row[b − a] is M[j + b, j + a]
                row[b - a] -= col[b] * la
    return True


@jit
def solve_face(band, reach, x):
    """Solve ``L Lᵀ y = x`` in place for ``x (n_free,)`` with the factor of :func:`factor_face`."""
    n = band.shape[0]
    for j in range(n):
        xj = x[j] / band[j, 0]
        x[j] = xj
        for o in range(1, reach[j] + 1):
            x[j + o] -= band[j, o] * xj
    for j in range(n - 1, -1, -1):
        s = x[j]
        for o in range(1, reach[j] + 1):
            s -= band[j, o] * x[j + o]
        x[j] = s / band[j, 0]
