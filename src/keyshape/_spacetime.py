"""Weights of a whole sequence at once: data fit plus a second-difference smoothness term.

For one region, with ``G = AᵀA`` (K × K), ``c_t = Aᵀ b_t`` and ``δ_t = 1`` where frame ``t`` has
data (0 in a gap), the solver minimises

.. math::

    F(W) = \\sum_t δ_t \\lVert A w_t - b_t \\rVert^2
         + μ \\sum_t \\lVert w_{t+1} - 2 w_t + w_{t-1} \\rVert^2
    \\quad\\text{s.t.}\\quad 0 \\le w_t \\le u, \\;\\; (\\mathbf 1^T w_t \\le 1),

a convex QP whose Hessian ``P = blockdiag(δ_t G) + μ LᵀL ⊗ I_K`` (``L`` the second-difference
operator) is block pentadiagonal. Nothing is filtered, so there is no lag: every frame's weights
are fitted with the frames on both sides. The solver has three parts:

1. *ADMM* (Boyd et al. 2011, §5; over-relaxation α = 1.8) on ``W = Z``, ``Z`` in the constraint
   set, with a per-frame penalty ``ρ_t``. Its linear step ``(P + diag(ρ_t) ⊗ I)⁻¹`` decouples in
   the eigenbasis of ``G`` (``G = QΛQᵀ``): ``(I_T ⊗ Q)(blockdiag(δ_t Λ + ρ_t I) + μ LᵀL ⊗ I)
   (I_T ⊗ Qᵀ)``, i.e. ``K`` independent pentadiagonal systems of size ``T``, factored once
   (LAPACK ``pbtrf``) and solved in ``O(T·K)`` per iteration. The projection is a clip (or a
   capped-simplex projection), frame by frame.
2. *Primal–dual active set* (Hintermüller, Ito & Kunisch 2003, a semismooth Newton method) from
   ADMM's active set: the bound variables are fixed, the free ones solve the reduced system by
   one banded Cholesky factorisation of bandwidth ``2K`` (``pbtrf`` on the ``T·K`` band,
   variables ordered frame-major); active ``Σw = 1`` rows are added by the method of
   multipliers on the same factorisation. Each step lands on the exact minimiser of its face;
   a few steps find the optimal face. Should the exchanges cycle (degenerate problems) they are
   damped, and a monotone primal active-set method (Nocedal & Wright, Alg. 16.3) finishes.
3. A *duality-gap certificate* stops every part: for multipliers ``y`` the Lagrangian dual
   ``q(y) = const − (c − y)ᵀP⁻¹(c − y) − 2σ_C(y)`` (one solve with the pentadiagonal factors of
   ``P``) bounds ``F*`` from below, so ``F(Z) − q(y) ≤ rtol·F(Z)`` proves that ``Z`` is within
   ``rtol`` of the optimum (``rtol = 1e-7`` by default).

Memory is linear in ``T``: the band holds ``(2K + 1)·T·K`` numbers, the rest ``O(T·K)``.

References
----------
Boyd, S., Parikh, N., Chu, E., Peleato, B. & Eckstein, J. (2011). Distributed optimization and
statistical learning via the alternating direction method of multipliers. *Found. Trends Mach.
Learn.* 3(1), 1–122.
Ghadimi, E., Teixeira, A., Shames, I. & Johansson, M. (2015). Optimal parameter selection for
the ADMM: quadratic problems. *IEEE Trans. Autom. Control* 60(3), 644–658.
Hintermüller, M., Ito, K. & Kunisch, K. (2003). The primal-dual active set strategy as a
semismooth Newton method. *SIAM J. Optim.* 13(3), 865–888.
Nocedal, J. & Wright, S. J. (2006). *Numerical Optimization*, 2nd ed., §16.5. Springer.
Stellato, B. et al. (2020). OSQP: an operator splitting solver for quadratic programs. *Math.
Prog. Comp.* 12, 637–672 (solution polishing from ADMM's active set).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass

import numpy as np
from . import _kernels
from ._nnls import Gram, cap_sum, nnls_gram
from .exceptions import ConvergenceWarning

LOWER, FREE, UPPER = 0, 1, 2
_ALM_STEPS = 30  # method-of-multipliers steps per Newton step for active Σw = 1 rows
_NEWTON_COST = 40  # ADMM iterations that one active-set Newton step costs (measured, K = 12)
_WARN_GAP = 1e-4  # degenerate problems (rank-deficient keys, extreme smoothing) may stop short of
# the 1e-7 target; only a certified gap above this is reported as a ConvergenceWarning


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
        self.factor = _kernels.penta_factor(a0, seq.mu * d1, seq.mu * d2)
        if not np.isfinite(self.factor[0][0, 0]):
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
        return _kernels.point_multipliers(g, np.ascontiguousarray(Z), seq.upper, seq.convex)
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


# --------------------------------------------------------------------------- ADMM


def admm(seq: Sequence, solver: EigenSolver, rho, Z, U, n_iter: int, alpha: float = 1.8):
    """``n_iter`` over-relaxed ADMM iterations on ``W = Z`` from ``(Z, U)`` (U scaled dual).

    ``rho``: ``(T,)`` per-frame penalties, the ones ``solver`` was factored with.

    ``W ← (P + ρI)⁻¹ (c + ρ(Z − U))``; ``Ŵ = αW + (1 − α)Z``; ``Z ← Π_C(Ŵ + U)``;
    ``U ← U + Ŵ − Z`` (Boyd et al. 2011, Eq. 3.5–3.7 and §3.4.3). The update after the
    linear step is one compiled pass (:func:`keyshape._kernels.admm_step`).
    """
    Z, U = np.array(Z, dtype=float, order="C"), np.array(U, dtype=float, order="C")
    rho = np.broadcast_to(np.asarray(rho, dtype=float), (seq.n_frames,)).copy()
    C = np.ascontiguousarray(seq.C)
    R = C + rho[:, None] * (Z - U)
    W = np.empty_like(Z)
    for _ in range(n_iter):
        solver.solve(R, out=W)
        _kernels.admm_step(W, Z, U, C, rho, seq.upper, alpha, seq.convex)
        R, W = W, R  # admm_step left the next right-hand side in W
    return Z, U


def admm_rho(seq: Sequence, lam: np.ndarray, *, gap_factor: float = 0.1) -> np.ndarray:
    """(T,) ADMM penalties: ``√(λ_min (λ_max + 4μ))`` on data frames, smaller in gaps.

    Ghadimi et al. (2015) show ``ρ* = √(λ_min λ_max)`` of the Hessian for QPs; the
    smoothness adds up to ``16μ`` at high frequencies, of which a quarter is counted.
    Frames without data have only the smoothness curvature, hence a smaller penalty.
    """
    rho = np.sqrt(max(lam[0], 1e-300) * (lam[-1] + 4.0 * seq.mu))
    return np.where(seq.delta > 0, rho, gap_factor * rho)


# --------------------------------------------------------------------------- active-set Newton


def classify(seq: Sequence, Z: np.ndarray):
    """Variable states (LOWER / FREE / UPPER) and active-sum rows of a feasible ``Z``."""
    state = np.where(Z <= 0.0, LOWER, np.where(Z >= seq.upper, UPPER, FREE)).astype(np.int8)
    sums = (Z.sum(axis=1) >= 1.0 - 1e-12) if seq.convex else np.zeros(len(Z), bool)
    return state, sums


def face_band(seq: Sequence, free: np.ndarray, sums: np.ndarray, rho_s: float) -> np.ndarray:
    """Lower band ``(T·K, 2K + 1)`` of the face system, frame-major (see
    :func:`keyshape._kernels.face_band`): free rows and columns hold
    ``P + ρ_s Σ_{active t} 1 1ᵀ``, fixed ones the identity."""
    return _kernels.face_band(seq.G, seq.delta, float(seq.mu), *seq.gram, free, sums, float(rho_s))


def face_solve(seq: Sequence, state: np.ndarray, sums: np.ndarray):
    """Minimiser ``X (T, K)`` of ``F`` on a face, and the multipliers ``ν (T,)`` of its sums.

    Bound variables sit at their bounds; free ones solve ``P_FF x_F = c_F − P_FN x_N``, with
    ``Σ_t w_t = 1`` on the ``sums`` rows enforced by the method of multipliers (Hestenes 1969)
    on one banded Cholesky factorisation of ``P_FF + ρ_s Σ 1 1ᵀ``.
    """
    free = state == FREE
    fixed = np.where(state == UPPER, np.where(np.isfinite(seq.upper), seq.upper, 0.0), 0.0)
    # ρ_s ≈ 10 λ_max(P): the multiplier error then shrinks ≥ 10-fold per step
    rho_s = 10.0 * (float(np.abs(seq.G).sum(axis=1).max()) + 16.0 * seq.mu) if sums.any() else 0.0
    factor, mask = face_band(seq, free, sums, rho_s), free.ravel()
    if not _kernels.band_factor(factor, mask):
        raise np.linalg.LinAlgError("banded Cholesky failed on the face: not positive definite")
    rhs = seq.C - hessian_mul(seq, fixed)
    room = 1.0 - fixed.sum(axis=1)  # what the free variables of an active row must add up to
    nu = np.zeros(len(state))
    for _ in range(_ALM_STEPS if sums.any() else 1):
        r = (rhs - np.where(sums, nu - rho_s * room, 0.0)[:, None]) * free
        x = np.ascontiguousarray(r).reshape(-1)
        _kernels.band_solve(factor, mask, x)
        X = x.reshape(state.shape) * free
        excess = np.where(sums, X.sum(axis=1) - room, 0.0)
        nu += rho_s * excess
        if np.abs(excess).max() <= 1e-13:
            break
    return X + fixed, nu


def exchange(seq: Sequence, state, sums, X, nu, limit=None):
    """Primal–dual active-set update: the new ``(state, sums)`` and how many changed.

    Every variable that breaks its KKT condition on the current face changes side (free and
    out of bounds → bound; bound with a wrong-signed multiplier → free); likewise the sum
    rows (over-full → active; negative multiplier → inactive). With ``limit``, only that many
    of the largest (dimensionless) violations change, which damps the cycling a plain
    primal–dual active-set step can fall into on degenerate problems.
    """
    grad = hessian_mul(seq, X) - seq.C + np.where(sums, nu, 0.0)[:, None]  # ∇(F/2) + ν·1
    x_scale = 1.0 + np.abs(X).max()
    g_scale = (np.abs(seq.C).max() + np.abs(seq.G).max() + seq.mu) * x_scale
    primal = np.maximum(-X, X - seq.upper) / x_scale  # > 0: a free variable out of its box
    dual = np.where(state == LOWER, -grad, grad) / g_scale  # > 0: a bound one pulled inside
    size = np.where(state == FREE, primal, dual)
    rows = np.full(len(X), -np.inf)
    if seq.convex:
        rows = np.where(sums, -nu / g_scale, (X.sum(axis=1) - 1.0) / x_scale)
    if limit is not None:
        cut = np.sort(np.concatenate([size.ravel(), rows]))[-limit]
        size, rows = np.where(size >= cut, size, 0.0), np.where(rows >= cut, rows, 0.0)
    move, flip = size > 1e-11, rows > 1e-11
    to_bound = np.where(X < 0.0, LOWER, UPPER)
    new = np.where(move, np.where(state == FREE, to_bound, FREE), state).astype(np.int8)
    return new, sums ^ flip, int(move.sum() + flip.sum())


# --------------------------------------------------------------------------- driver


def solve_sequence(seq: Sequence, *, rtol: float = 1e-7, max_admm: int = 400, switch: float = 1e-4,
                   max_newton: int = 40):
    """Minimiser ``W (T, K)`` of ``F`` to relative accuracy ``rtol`` (certified by duality).

    ADMM converges linearly here, its certified gap falling by a steady factor per iteration
    (about 100× per 10 on typical problems). After 20 iterations and then after each
    certified round, that factor predicts how many more iterations reach ``rtol``, and the
    next certificate is placed there. Where ADMM stalls, or would need more iterations than
    an active-set Newton step costs (:data:`_NEWTON_COST`) once its gap is below ``switch``,
    primal–dual active-set steps finish, each certified by the dual bound of its face; when
    the exchanges stop shrinking they are damped (:func:`exchange`).

    Returns
    -------
    W : (T, K) float, feasible
    gap : float, the certified relative gap ``(F(W) − max q) / F(W)``
    """
    lam = np.linalg.eigvalsh(seq.G)
    rho = admm_rho(seq, lam)
    solver, exact = EigenSolver(seq, rho), EigenSolver(seq, 0.0)
    done, rounds = 20, 10
    Z, U = admm(seq, solver, rho, np.zeros(seq.C.shape), np.zeros(seq.C.shape), done)
    best = _Best(seq, exact, Z)
    while best.gap > rtol and done + rounds <= max_admm:
        before = best.gap
        Z, U = admm(seq, solver, rho, Z, U, rounds)
        done += rounds
        best.offer(Z)
        if best.gap <= rtol:
            break
        rate = (best.gap / before) ** (1.0 / rounds)  # per iteration
        if not rate < 0.98:  # stalled
            break
        need = np.log(rtol / best.gap) / np.log(rate)
        if need > _NEWTON_COST and best.gap <= switch:
            break
        rounds = int(np.clip(np.ceil(need) + 1, 2, 50))
    state, sums = classify(seq, best.Z)
    history, limit = [], None
    for _ in range(max_newton):
        if best.gap <= rtol:
            break
        X, nu = face_solve(seq, state, sums)
        best.offer(project(X, seq.upper, seq.convex), multipliers(seq, X, state, np.where(sums, nu, 0.0)))
        state, sums, changed = exchange(seq, state, sums, X, nu, limit)
        history.append(changed)
        if changed == 0:
            break
        if len(history) > 3 and changed >= history[-4]:  # no progress: damp the exchanges
            limit = max(1, (limit or changed) // 2)
            history.clear()
        if limit == 1:
            break
    if best.gap > rtol:  # one face per step: bounded by the problem size
        active_set(seq, best, max_steps=int(np.clip(2e6 // seq.C.size, 20, 200)))
    return best.Z, best.gap


def active_set(seq: Sequence, best: _Best, *, max_steps: int) -> None:
    """Primal active-set finish from ``best.Z`` (Nocedal & Wright 2006, Alg. 16.3).

    Monotone: each step moves to the face minimiser, or as far as the first blocking
    constraint allows and adds it; at a face minimiser the most wrong-signed multiplier
    leaves. Slow (one face per change) but sure where the active-set exchanges cycle.
    """
    x = best.Z
    state, sums = classify(seq, x)
    for _ in range(max_steps):
        X, nu = face_solve(seq, state, sums)
        nu = np.where(sums, nu, 0.0)
        p = X - x
        if np.abs(p).max() <= 1e-12 * (1.0 + np.abs(x).max()):
            best.offer(x, multipliers(seq, X, state, nu))
            if not _release(seq, state, sums, X, nu) or best.gap <= 0.0:
                return
            continue
        alpha, block = _ratio_test(seq, x, p, state, sums)
        x = project(x + alpha * p, seq.upper, seq.convex)
        if block is not None:
            _add(seq, state, sums, block, p)
        best.offer(x, multipliers(seq, X, state, nu) if block is None else None)


def _ratio_test(seq, x, p, state, sums):
    """Largest step ``α ≤ 1`` along ``p`` that stays feasible, and what blocks it."""
    free = state == FREE
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(free & (p < 0), -x / p, np.inf)
        a = np.minimum(a, np.where(free & (p > 0), (seq.upper - x) / p, np.inf))
        rows = np.full(len(x), np.inf)
        if seq.convex:
            rise = p.sum(axis=1)
            rows = np.where(~sums & (rise > 0), (1.0 - x.sum(axis=1)) / rise, np.inf)
    i = np.unravel_index(np.argmin(a), a.shape)
    t = int(np.argmin(rows))
    alpha = min(1.0, float(a[i]), float(rows[t]))
    if alpha >= 1.0:
        return 1.0, None
    return max(alpha, 0.0), (("row", t) if rows[t] <= a[i] else ("var", i))


def _add(seq, state, sums, block, p):
    kind, where = block
    if kind == "row":
        sums[where] = True
    else:
        state[where] = LOWER if p[where] < 0 else UPPER


def _release(seq, state, sums, X, nu) -> bool:
    """Free the constraint with the most wrong-signed multiplier; False if none is wrong."""
    grad = hessian_mul(seq, X) - seq.C + nu[:, None]
    wrong = np.where(state == LOWER, -grad, np.where(state == UPPER, grad, 0.0))
    rows = np.where(sums, -nu, 0.0)
    tol = 1e-11 * (np.abs(seq.C).max() + np.abs(seq.G).max() + seq.mu) * (1.0 + np.abs(X).max())
    i = np.unravel_index(np.argmax(wrong), wrong.shape)
    t = int(np.argmax(rows))
    if max(wrong[i], rows[t]) <= tol:
        return False
    if rows[t] > wrong[i]:
        sums[t] = False
    else:
        state[i] = FREE
    return True


class _Best:
    """The best feasible point seen and the best dual bound: their relative gap certifies it."""

    def __init__(self, seq, exact, Z):
        self.seq, self.exact = seq, exact
        self.Z, self.F, self.q = Z, np.inf, -np.inf
        self.offer(Z)

    def offer(self, Z, Y=None) -> _Best:
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


# --------------------------------------------------------------------------- entry point


def spacetime_gram(G, C, valid, const, mu, upper, convex, *, rtol=1e-7) -> np.ndarray:
    """Solve one region's spacetime QP; frames outside the first..last valid frame are NaN.

    Parameters
    ----------
    G : (K, K) float, ``AᵀA``
    C : (n_frames, K) float, ``Aᵀ b_t`` (any value where ``valid`` is False)
    valid : (n_frames,) bool, frames with data
    const : float, ``Σ_valid ‖b_t‖²``
    mu : float > 0
    upper : (K,) float, ``inf`` where unbounded
    convex : bool

    Returns
    -------
    (n_frames, K) float
    """
    n, k = C.shape
    out = np.full((n, k), np.nan)
    rows = np.flatnonzero(valid)
    if not len(rows):
        return out
    span = slice(rows[0], rows[-1] + 1)  # gaps inside are bridged, the ends are not extrapolated
    delta = valid[span].astype(float)
    gram = Gram.from_matrix(G)
    if len(delta) < 3:
        out[span] = nnls_gram(G, C[span], upper, convex)
        return out
    seq = Sequence(gram.G, np.ascontiguousarray(C[span] * delta[:, None]), delta, mu, upper, convex, const)
    W, gap = solve_sequence(seq, rtol=rtol)
    if gap > max(_WARN_GAP, 100.0 * rtol):
        warnings.warn(
            f"the smoothed solve stopped at a certified relative gap of {gap:.1e} (asked: {rtol:.0e})",
            ConvergenceWarning,
            stacklevel=3,
        )
    W = np.clip(W, 0.0, upper)
    out[span] = cap_sum(W) if convex else W
    return out
