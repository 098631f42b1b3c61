"""One region's spacetime QP (:mod:`keyshape.decompose._spacetime`): its data, the Hessian and its
eigenbasis solver, the constraint set and the duality certificate.

``Sequence`` holds ``F(W) = Σ_t δ_t ‖A w_t − b_t‖² + μ ‖L W‖²`` in Gram form; :class:`EigenSolver`
applies ``(P + ρI)⁻¹``; :func:`project` and :func:`support` describe the constraint set ``C``;
:func:`multipliers`, :func:`lower_bound` and :class:`Best` turn any feasible point into a proof
of how far it is from the optimum (weak Lagrangian duality).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from . import _kernels
from ._kernels_nnls import LOWER, UPPER  # the state of a variable on a face of C


@dataclass(frozen=True, eq=False)
class Sequence:
    """One region's spacetime QP, frame-major.

    Attributes
    ----------
    G : (K, K) float, symmetric positive definite
    C : (T, K) float, ``δ_t c_t`` (zero in gaps)
    delta : (T,) float, 1 where the frame has data, 0 in a gap
    mu : float, smoothness weight ``μ > 0``
    upper : (K,) float, ``inf`` where unbounded
    convex : bool, whether ``Σ w_t ≤ 1`` holds in every frame
    const : float, ``Σ_t δ_t ‖b_t‖²``, so that :func:`objective` is ``F`` itself
    """

    G: np.ndarray
    C: np.ndarray
    delta: np.ndarray
    mu: float
    upper: np.ndarray
    convex: bool
    const: float

    @functools.cached_property
    def gram(self):
        """``(d0, d1, d2)``, each ``(T,)``: the diagonals of ``LᵀL``, off-diagonals zero-padded."""
        return _padded_gram(self.n_frames)

    n_frames = property(lambda self: self.C.shape[0])
    n_keys = property(lambda self: self.C.shape[1])


# --------------------------------------------------------------------------- operators


def second_difference_gram(n_frames: int):
    """Diagonals ``(d0, d1, d2)`` of ``LᵀL`` for the ``(T − 2) × T`` second-difference ``L``."""
    d0, d1, d2 = np.zeros(n_frames), np.zeros(max(n_frames - 1, 0)), np.ones(max(n_frames - 2, 0))
    if n_frames >= 3:  # each row of L is (1, −2, 1) at (r, r + 1, r + 2)
        d0[:-2] += 1.0
        d0[1:-1] += 4.0
        d0[2:] += 1.0
        d1[:-1] -= 2.0
        d1[1:] -= 2.0
    return d0, d1, d2


def hessian_mul(seq: Sequence, X: np.ndarray) -> np.ndarray:
    """``P X`` for ``X (T, K)``: ``δ_t G x_t + μ (LᵀL X)_t``."""
    X = np.ascontiguousarray(X, dtype=float)
    Y = X @ seq.G
    _kernels.add_smoothness(Y, X, seq.delta, float(seq.mu), *seq.gram)
    return Y


def objective(seq: Sequence, X: np.ndarray, PX: np.ndarray | None = None) -> float:
    """``F(X) = Σ δ_t ‖A x_t − b_t‖² + μ ‖L X‖² = ⟨X, PX − 2C⟩ + const`` (``PX`` if known)."""
    PX = hessian_mul(seq, X) if PX is None else PX
    return float(np.einsum("tk,tk->", X, PX - 2.0 * seq.C) + seq.const)


class EigenSolver:
    """``(P + ρI)⁻¹`` as ``K`` pentadiagonal solves in the eigenbasis of ``G``."""

    def __init__(self, seq: Sequence, rho: float | np.ndarray):
        """``rho``: a number, or ``(T,)`` per-frame penalties (``ρ_t I_K`` still commutes
        with the eigenbasis, and a per-frame metric keeps the projection a per-frame one)."""
        self.lam, self.Q = np.linalg.eigh(seq.G)
        d0, d1, d2 = seq.gram
        a0 = seq.delta[:, None] * self.lam + np.reshape(rho, (-1, 1)) + seq.mu * d0[:, None]
        self.factor = tuple(np.empty_like(a0) for _ in range(3))
        if not _kernels.penta_factor(a0, seq.mu * d1, seq.mu * d2, *self.factor):
            raise np.linalg.LinAlgError("pentadiagonal factorisation failed: not positive definite")

    def solve(self, R: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``(P + ρI)⁻¹ R`` for ``R (T, K)``, C order (into ``out`` if given)."""
        Y = R @ self.Q  # row t: Qᵀ r_t, the eigen-coordinates
        _kernels.penta_solve(*self.factor, Y)
        return np.dot(Y, self.Q.T, out=out)


def _padded_gram(n_frames: int):
    """:func:`second_difference_gram`, the off-diagonals padded with zeros to length ``T``."""
    d0, d1, d2 = second_difference_gram(n_frames)
    return d0, np.append(d1, np.zeros(n_frames - len(d1))), np.append(d2, np.zeros(n_frames - len(d2)))


# --------------------------------------------------------------------------- constraint set


def project(V: np.ndarray, upper: np.ndarray, convex: bool) -> np.ndarray:
    """Euclidean projection of every row of ``V (T, K)`` on ``{0 ≤ w ≤ u (, Σw ≤ 1)}``."""
    V = np.ascontiguousarray(V, dtype=float)
    out = np.empty_like(V)
    _kernels.project_rows(V, np.asarray(upper, dtype=float), bool(convex), out)
    return out


def support(Y: np.ndarray, upper: np.ndarray, convex: bool) -> float:
    """``σ_C(Y) = max_{Z ∈ C} ⟨Y, Z⟩``, frame by frame (a greedy LP for the capped simplex)."""
    if not convex:
        return float(np.sum(np.maximum(Y, 0.0) * np.where(np.isfinite(upper), upper, 0.0)))
    order = np.argsort(-Y, axis=1)
    y = np.take_along_axis(Y, order, axis=1)
    u = np.minimum(upper[order], 1.0)
    room = 1.0 - np.concatenate([np.zeros((len(Y), 1)), np.cumsum(u, axis=1)[:, :-1]], axis=1)
    z = np.where(y > 0, np.clip(np.minimum(u, room), 0.0, None), 0.0)
    return float(np.sum(y * z))


def multipliers(seq: Sequence, Z: np.ndarray, state=None, nu=None, PZ=None) -> np.ndarray:
    """An estimate ``Y (T, K)`` of the optimal multipliers, in the normal cone of the constraints.

    At the optimum ``c − P z = y`` with ``y`` zero on free variables, ``≤ 0`` at 0, ``≥ 0`` at
    ``u``, plus ``ν_t·1`` (``ν_t ≥ 0``) on an active sum. Given a face (``state``, ``nu``) its
    exact multipliers are used; otherwise they are read off the feasible ``Z``.
    """
    g = seq.C - (hessian_mul(seq, Z) if PZ is None else PZ)
    if state is None:  # read off the point (compiled: it runs on every certificate)
        Y = np.empty_like(g)
        _kernels.point_multipliers(g, np.ascontiguousarray(Z), seq.upper, seq.convex, Y)
        return Y
    nu = np.zeros((len(Z), 1)) if nu is None else np.reshape(nu, (-1, 1))
    r = g - nu
    return nu + np.where(state == LOWER, np.minimum(r, 0.0), np.where(state == UPPER, np.maximum(r, 0.0), 0.0))


def lower_bound(seq: Sequence, exact: EigenSolver, Y: np.ndarray) -> float:
    """Lagrangian dual value ``q(y) ≤ F*`` for any multipliers ``Y (T, K)``.

    ``q(y) = min_W [F(W) + 2⟨y, W⟩] − 2σ_C(y) = const − (c − y)ᵀP⁻¹(c − y) − 2σ_C(y)``
    (weak duality for ``W = Z``, ``Z ∈ C``), one solve with ``P`` itself.
    """
    if not seq.convex:  # σ_C is finite only where the bound is
        Y = np.where(np.isfinite(seq.upper), Y, np.minimum(Y, 0.0))
    R = seq.C - Y
    quad = np.einsum("tk,tk->", R, exact.solve(R))
    return float(seq.const - quad - 2.0 * support(Y, seq.upper, seq.convex))


class Best:
    """The best feasible point seen and the best dual bound: their relative gap certifies it."""

    def __init__(self, seq, exact, Z):
        self.seq, self.exact = seq, exact
        self.Z, self.F, self.q = Z, np.inf, -np.inf
        self.offer(Z)

    def offer(self, Z, Y=None) -> Best:
        """Keep ``Z`` if it is better; raise the bound with ``Y`` (default: read off ``Z``)."""
        PZ = hessian_mul(self.seq, Z)
        F = objective(self.seq, Z, PZ)
        if F < self.F:
            self.Z, self.F = Z, F
        Y = multipliers(self.seq, Z, PZ=PZ) if Y is None else Y
        self.q = max(self.q, lower_bound(self.seq, self.exact, Y))
        return self

    @property
    def gap(self) -> float:
        """``(F − q) / F``; for a near-exact fit relative to ``1e-6 Σ‖b‖²`` instead."""
        floor = max(1e-6 * self.seq.const, np.finfo(float).tiny)
        return max(self.F - self.q, 0.0) / max(abs(self.F), floor)
