"""Reduced systems of the per-frame solver (:mod:`keyshape.decompose._nnls`), many rows at once.

Row ``t`` solves ``G_FF z_F = r_F`` on its own free set ``F``: rows are bucketed by ``|F|`` and
each bucket's small systems factored together (batched Cholesky), or, with few fixed
variables, solved through ``H = G⁻¹`` and a Schur complement (Golub & Van Loan 2013, §3.4).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ._nnls import Gram

KKT_TOL = 1e-11  # relative tolerance of the KKT tests of the per-frame solver (_nnls, _kernels_nnls)
LOWER, FREE, UPPER = 0, 1, 2  # the state of a variable: at 0, free, at its upper bound

_CHUNK = 2**22  # elements per batched factorisation: bounds the (f, f, n) stack to 32 MB
_SMALL_BATCH = 48  # below this many systems of one size, LAPACK per system is cheaper


def free_solve(gram: Gram, free: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``z`` with ``z_F = G_FF⁻¹ rhs_F`` and ``z = 0`` off the free set ``F``, row by row.

    A row with few free variables is solved directly on ``G_FF``. A row with few *fixed*
    variables ``N`` uses ``H = G⁻¹`` and the Schur complement instead,
    ``z = H r − H_{:N} H_NN⁻¹ (H r)_N`` with ``r`` the right-hand side zeroed on ``N``
    (Golub & Van Loan §3.4), so no system solved has more than ``K/2`` unknowns.

    Parameters
    ----------
    gram : Gram, the shared ``G`` and ``H = G⁻¹``, each (K, K)
    free : (n, K) bool
    rhs : (n, K) float

    Returns
    -------
    (n, K) float
    """
    if not gram.use_inverse:
        return masked_solve(gram.G, free, rhs)
    dual = 2 * free.sum(axis=1) > free.shape[1]
    if dual.all() or not dual.any():
        return _schur_solve(gram, free, rhs) if dual.all() else masked_solve(gram.G, free, rhs)
    z = np.empty(rhs.shape)
    z[~dual] = masked_solve(gram.G, free[~dual], rhs[~dual])
    z[dual] = _schur_solve(gram, free[dual], rhs[dual])
    return z


def _schur_solve(gram, free, rhs):
    """``z = H r − H_{:N} H_NN⁻¹ (H r)_N`` on each row's free set (``r`` zero off it)."""
    z0 = (rhs * free) @ gram.H
    lam = masked_solve(gram.H, ~free, z0)  # H_NN⁻¹ (H r)_N, zero on F
    return (z0 - lam @ gram.H) * free


def masked_solve(G: np.ndarray, free: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``z`` with ``z_F = G_FF⁻¹ rhs_F`` and ``z = 0`` off ``F``, for every row's own ``F``.

    Rows are bucketed by ``|F|``; each bucket's compact ``|F| × |F|`` systems are gathered
    batch-last and solved by a vectorised Cholesky factorisation.

    Parameters
    ----------
    G : (K, K) float, symmetric positive definite
    free : (n, K) bool
    rhs : (n, K) float

    Returns
    -------
    (n, K) float
    """
    k = G.shape[0]
    counts = free.sum(axis=1, dtype=np.uint8)
    order = np.argsort(counts, kind="stable")  # a radix sort on uint8
    edges = np.searchsorted(counts[order], np.arange(k + 2))
    free, rhs, out = free[order], rhs[order], np.zeros(rhs.shape)  # buckets are now slices
    for size in range(1, k + 1):
        lo, hi = edges[size], edges[size + 1]
        if lo < hi:
            cols = np.nonzero(free[lo:hi])[1].reshape(hi - lo, size)  # (n_b, size)
            r = np.take_along_axis(rhs[lo:hi], cols, axis=1)
            np.put_along_axis(out[lo:hi], cols, _compact_solve(G, cols, r), axis=1)
    result = np.empty_like(out)
    result[order] = out
    return result


def _compact_solve(G, cols, rhs):
    """(n_b, f): ``G[c, c]⁻¹ r`` for each row's column set ``c`` and right-hand side ``r``."""
    if cols.shape[1] == G.shape[0]:  # every variable free: one factorisation serves all rows
        return np.linalg.solve(G, rhs.T).T
    if len(cols) < _SMALL_BATCH:
        return np.linalg.solve(G[cols[:, :, None], cols[:, None, :]], rhs[..., None])[..., 0]
    out = np.empty(rhs.shape)
    step = max(1, _CHUNK // cols.shape[1] ** 2)
    for lo in range(0, len(cols), step):
        c = cols[lo : lo + step]
        # gather G[c, c] as (n_c, f, f), then lay it out batch-last for the vectorised kernel
        M = np.ascontiguousarray(G[c[:, :, None], c[:, None, :]].transpose(1, 2, 0))
        out[lo : lo + step] = _batched_cho_solve(_batched_cholesky(M), rhs[lo : lo + step].T).T
    return out


def _batched_cholesky(M):
    """Lower Cholesky factors ``L (f, f, n)`` of a batch-last stack ``M (f, f, n)``."""
    L = np.zeros_like(M)
    for j in range(M.shape[0]):
        # L[j:, j] = (M[j:, j] − L[j:, :j] · L[j, :j]) / L[j, j]   (Golub & Van Loan Alg. 4.2.1)
        col = M[j:, j] - np.einsum("ikn,kn->in", L[j:, :j], L[j, :j]) if j else M[j:, j]
        L[j, j] = np.sqrt(col[0])
        L[j + 1 :, j] = col[1:] / L[j, j]
    return L


def _batched_cho_solve(L, r):
    """``x (f, n)`` with ``L Lᵀ x = r`` for a batch-last stack of factors ``L (f, f, n)``."""
    f = L.shape[0]
    y = np.empty_like(r)
    for i in range(f):  # forward substitution: L y = r
        y[i] = (r[i] - np.einsum("kn,kn->n", L[i, :i], y[:i])) / L[i, i]
    x = np.empty_like(r)
    for i in range(f - 1, -1, -1):  # back substitution: Lᵀ x = y
        x[i] = (y[i] - np.einsum("kn,kn->n", L[i + 1 :, i], x[i + 1 :])) / L[i, i]
    return x
