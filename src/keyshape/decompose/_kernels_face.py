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

* :func:`number_free` — compressed indices of the free variables, each column's reach and
  where it starts in the packed storage (column after column, each as long as its reach);
* :func:`lay_out` — that layout for numbered free variables of any sorted frames (the
  weighted solve's faces on a few frames use it too);
* :func:`fill_face` — the packed lower envelope of ``P_FF (+ ρ_s Σ_{active t} 1 1ᵀ)``;
* :func:`factor_face` / :func:`solve_face` — ``P_FF = L Lᵀ`` in place, and ``L Lᵀ x = r``.

The visibility-weighted solve (:mod:`keyshape.decompose._weighted`, one ``G_t`` per frame)
factors its faces on the same envelope, in the same storage and with the same column
elimination (:mod:`keyshape.decompose._kernels_weighted`, which fills each frame's columns
just before they are needed); its certificate factors ``P`` with :func:`factor_face` and
solves with :func:`solve_face`.

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
def number_free(free, index, reach, offset):
    """Number the free variables frame-major; returns ``(n_free, size)``.

    ``free (T, K)`` bool; ``index (T, K)`` int64 receives each free variable's number (−1 when
    fixed); for the first ``n_free`` entries, ``reach (T·K,)`` int64 receives how far below the
    diagonal column ``j`` of the factor reaches (its envelope) and ``offset (T·K,)`` int64 where
    the column starts in the packed storage, ``size`` numbers in all.
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
    return n, lay_out(index, np.arange(T), reach, offset)


@jit
def lay_out(index, rows, reach, offset):
    """The envelope of numbered free variables; returns ``size``, the numbers it holds.

    ``index (n, K)`` int64: the free variables' numbers, frame-major (−1 when fixed), of the
    frames ``rows (n,)`` (sorted): a free variable couples to the free ones of its own frame and
    to its key in the next two frames when those are ``rows[i] + 1`` and ``rows[i] + 2`` (frames
    not among ``rows`` are held). Column ``j`` of the Cholesky factor reaches ``reach[j] = last[j]
    − j`` below the diagonal, ``last[j]`` the deepest nonzero row of the columns up to ``j``
    (fill stays inside it), and starts at ``offset[j]`` in the packed storage.
    """
    n, K = index.shape
    low = 0  # max over the columns so far of their last nonzero row (absolute)
    size = 0
    for i in range(n):
        last_here = -1  # the frame's last free variable: the within-frame couplings reach it
        for a in range(K):
            last_here = max(last_here, index[i, a])
        near = i + 1 < n and rows[i + 1] == rows[i] + 1
        far = i + 2 < n and rows[i + 2] == rows[i] + 2
        for a in range(K):
            j = index[i, a]
            if j < 0:
                continue
            deepest = last_here
            if near:
                deepest = max(deepest, index[i + 1, a])
            if far:
                deepest = max(deepest, index[i + 2, a])
            low = max(low, deepest)
            reach[j] = low - j
            offset[j] = size
            size += low - j + 1
    return size


@jit
def fill_face(G, delta, mu, d0, d1, d2, index, sums, rho_s, reach, offset, packed):
    """Fill the packed columns (any values on entry): ``packed[offset[j] + o] = M[j + o, j]`` for
    ``o ≤ reach[j]``, ``M = P + ρ_s Σ_{active t} 1 1ᵀ`` on the free variables (``d0, d1, d2 (T,)``
    the diagonals of ``LᵀL``; ``sums (T,)`` the active rows)."""
    T, K = index.shape
    for t in range(T):
        pen = rho_s if sums[t] else 0.0
        for i in range(K):
            j = index[t, i]
            if j < 0:
                continue
            col = offset[j]
            for o in range(reach[j] + 1):
                packed[col + o] = 0.0
            for i2 in range(i, K):
                j2 = index[t, i2]
                if j2 >= 0:
                    packed[col + j2 - j] = delta[t] * G[i2, i] + pen
            packed[col] += mu * d0[t]
            if t + 1 < T and index[t + 1, i] >= 0:
                packed[col + index[t + 1, i] - j] = mu * d1[t]
            if t + 2 < T and index[t + 2, i] >= 0:
                packed[col + index[t + 2, i] - j] = mu * d2[t]


@jit
def factor_face(n, reach, offset, packed):
    """Cholesky ``M = L Lᵀ`` in place on the packed columns of :func:`fill_face` (right-looking:
    column ``j`` updates the columns of its reach, whose own reach covers the rest of it, as
    the envelope only grows); False if not positive definite."""
    for j in range(n):
        last = reach[j] + 1
        col = packed[offset[j] : offset[j] + last]
        p = col[0]
        if not p > 0.0:
            return False
        p = np.sqrt(p)
        col[0] = p
        for o in range(1, last):
            col[o] /= p
        for a in range(1, last):
            la = col[a]
            if la == 0.0:
                continue
            row = packed[offset[j + a] : offset[j + a] + last - a]  # row[b − a] is M[j + b, j + a]
            for b in range(a, last):
                row[b - a] -= col[b] * la
    return True


@jit
def solve_face(n, reach, offset, packed, x):
    """Solve ``L Lᵀ y = x`` in place for ``x (n_free,)`` with the factor of :func:`factor_face`."""
    for j in range(n):
        col = offset[j]
        xj = x[j] / packed[col]
        x[j] = xj
        for o in range(1, reach[j] + 1):
            x[j + o] -= packed[col + o] * xj
    for j in range(n - 1, -1, -1):
        col = offset[j]
        s = x[j]
        for o in range(1, reach[j] + 1):
            s -= packed[col + o] * x[j + o]
        x[j] = s / packed[col]
