"""Weights of a whole sequence at once: data fit plus a second-difference smoothness term.

For one region, with ``G = AᵀA`` (K × K), ``c_t = Aᵀ b_t`` and ``δ_t = 1`` where frame ``t`` has
data (0 in a gap), the solver minimises

.. math::

    F(W) = \\sum_t δ_t \\lVert A w_t - b_t \\rVert^2
         + μ \\sum_t \\lVert w_{t+1} - 2 w_t + w_{t-1} \\rVert^2
    \\quad\\text{s.t.}\\quad 0 \\le w_t \\le u, \\;\\; (\\mathbf 1^T w_t \\le 1),

a convex QP whose Hessian ``P = blockdiag(δ_t G) + μ LᵀL ⊗ I_K`` (``L`` the second-difference
operator) is block pentadiagonal. Nothing is filtered, so there is no lag: every frame's weights
are fitted with the frames on both sides. The solver has four parts:

1. *ADMM* (Boyd et al. 2011, §5; over-relaxation α = 1.8) on ``W = Z``, ``Z`` in the constraint
   set, with a per-frame penalty ``ρ_t`` (:func:`admm_rho`). Its linear step
   ``(P + diag(ρ_t) ⊗ I)⁻¹`` decouples in the eigenbasis of ``G`` (``G = QΛQᵀ``):
   ``(I_T ⊗ Q)(blockdiag(δ_t Λ + ρ_t I) + μ LᵀL ⊗ I)(I_T ⊗ Qᵀ)``, i.e. ``K`` independent
   pentadiagonal systems of size ``T``, factored once (``LDLᵀ``) and solved in ``O(T·K)`` per
   iteration; the projection is a clip (or a capped-simplex projection), frame by frame. The
   sweeps are compiled (:mod:`keyshape.decompose._kernels`); the two rotations by ``Q`` are BLAS calls.
   ADMM starts from the unconstrained smooth fit ``P⁻¹c`` (clipped) and converges linearly, so
   the observed rate places each certificate where the target should be met; on typical
   problems ADMM alone proves ``rtol`` in 20–60 iterations.
2. *Primal–dual active set* (Hintermüller, Ito & Kunisch 2003, a semismooth Newton method)
   from ADMM's active set, where ADMM stalls (long gaps, where only the smoothness term
   holds the weights), and from the per-frame solution where ADMM would crawl from the
   start (keys that are near-copies of each other, as a key and its mirror image on a
   symmetric face: ``cond(G)`` in the tens of thousands, forecast by :func:`admm_iterations`):
   the bound variables are fixed, the free ones solve the reduced system by one Cholesky
   factorisation over the free variables only, numbered frame-major (a variable band of at
   most ``2K``; :mod:`keyshape.decompose._kernels_face`); active ``Σw = 1`` rows are added
   by the method of multipliers on the same factorisation. Each step lands on the exact
   minimiser of its face; once few variables still change side, windows around them finish
   (:func:`keyshape.decompose._activeset.newton`); should the exchanges cycle (degenerate
   problems) they are damped, and a monotone primal active-set method (Nocedal & Wright,
   Alg. 16.3) finishes. Where ADMM has converged but
   around long gaps, these steps run first on windows around them only, with the other frames
   fixed (:func:`keyshape.decompose._activeset.local_finish`): a few hundred frames per gap
   instead of the take, one exact small solve per gap; the steps on the whole take remain
   the fallback, from ADMM's own active set.
3. A take of at least twice :data:`_PIECE_FRAMES` frames is solved in overlapping pieces,
   one per core (:func:`solve_pieces`), joined, and certified as a whole.
4. A *duality-gap certificate* stops every part: for multipliers ``y`` the Lagrangian dual
   ``q(y) = const − (c − y)ᵀP⁻¹(c − y) − 2σ_C(y)`` (one solve with the pentadiagonal factors of
   ``P``) bounds ``F*`` from below, so ``F(Z) − q(y) ≤ rtol·F(Z)`` proves that ``Z`` is within
   ``rtol`` of the optimum (``rtol = 1e-7`` by default).

Memory is linear in ``T``: ADMM holds a few ``(T, K)`` arrays; a face factorisation, when
one is needed, holds the band, ``(2K + 1)·T·K`` numbers.

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

import contextlib
import os
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..exceptions import ConvergenceWarning
from . import _kernels
from ._activeset import decay_margin, local_finish, newton
from ._nnls import Gram, cap_sum, nnls_gram
from ._sequence import Best, EigenSolver, Sequence, project

_NEWTON_COST = 100  # ADMM iterations the active-set Newton steps cost, all of them from an ADMM point
_PIECE_FRAMES = 20_000  # a take of at least twice this many frames is solved in pieces, one per core
_ADMM_LIMIT = 400  # forecast ADMM iterations (admm_iterations) beyond which the Newton steps go first
_MAX_ROUND = 30  # ADMM iterations between certificates at most: the rate estimate can be pessimistic
_WARN_GAP = 1e-4  # degenerate problems (rank-deficient keys, extreme smoothing) may stop short of
# the 1e-7 target; only a certified gap above this is reported as a ConvergenceWarning


# --------------------------------------------------------------------------- ADMM


def admm(seq: Sequence, solver: EigenSolver, rho, Z, U, n_iter: int, alpha: float = 1.8):
    """``n_iter`` over-relaxed ADMM iterations on ``W = Z`` from ``(Z, U)`` (U scaled dual).

    ``rho``: ``(T,)`` per-frame penalties, the ones ``solver`` was factored with.

    ``W ← (P + ρI)⁻¹ (c + ρ(Z − U))``; ``Ŵ = αW + (1 − α)Z``; ``Z ← Π_C(Ŵ + U)``;
    ``U ← U + Ŵ − Z`` (Boyd et al. 2011, Eq. 3.5–3.7 and §3.4.3). The update after the
    linear step is one compiled pass (:func:`keyshape.decompose._kernels.admm_step`).
    """
    Z, U = np.array(Z, dtype=float, order="C"), np.array(U, dtype=float, order="C")
    rho = np.ascontiguousarray(rho, dtype=float)
    C = np.ascontiguousarray(seq.C)
    R = C + rho[:, None] * (Z - U)
    W = np.empty_like(Z)
    for _ in range(n_iter):
        solver.solve(R, out=W)
        _kernels.admm_step(W, Z, U, C, rho, seq.upper, alpha, seq.convex)
        R, W = W, R  # admm_step left the next right-hand side in W
    return Z, U


def admm_rho(seq: Sequence, lam: np.ndarray) -> np.ndarray:
    """(T,) ADMM penalties: ``√(λ_min (λ_max + 4μ))`` on data frames, ``4μ (π / (L + 3))²``
    (at most that) in a gap of ``L`` frames.

    Ghadimi et al. (2015) show ``ρ* = √(λ_min λ_max)`` of the Hessian for QPs; the
    smoothness adds up to ``16μ`` at high frequencies, of which a quarter is counted.
    Frames without data have only the smoothness curvature: the same rule applied to the
    gap's block of ``μ LᵀL`` gives about 2.5× the value used, which was the fastest of the
    rules tried (on isolated gaps of 3–30 frames and on a tracker's dropouts).
    """
    rho = np.full(seq.n_frames, np.sqrt(max(lam[0], 1e-300) * (lam[-1] + 4.0 * seq.mu)))
    data = np.concatenate([[1], (seq.delta > 0).astype(np.int8), [1]])
    edges = np.flatnonzero(np.diff(data))  # a gap starts and stops at alternate edges
    for start, stop in zip(edges[::2], edges[1::2]):  # runs of frames without data
        rho[start:stop] = min(rho[0], 4.0 * seq.mu * (np.pi / (stop - start + 3)) ** 2)
    return rho


# --------------------------------------------------------------------------- driver


def solve_sequence(seq: Sequence, *, rtol: float = 1e-7, max_admm: int = 400, switch: float = 1e-4,
                   max_newton: int = 40):
    """Minimiser ``W (T, K)`` of ``F`` to relative accuracy ``rtol`` (certified by duality).

    ADMM starts from the unconstrained minimiser ``P⁻¹c``, clipped into the constraint set, and
    converges linearly, its certified gap falling by a steady factor per iteration (about
    100× per 10 on typical problems). After 20 iterations and then after each certified
    round, that factor predicts how many more iterations reach ``rtol``, and the next
    certificate is placed there (at most :data:`_MAX_ROUND` iterations on). Where ADMM
    stalls, or would need more iterations than the active-set Newton steps cost
    (:data:`_NEWTON_COST`) once its gap is below ``switch`` (before that, ADMM has not yet
    settled away from long gaps, where the windows of :func:`local_finish` need it to),
    primal–dual active-set steps finish (:func:`newton`). Keys so
    alike that ADMM would crawl from the start (:func:`admm_iterations` above
    :data:`_ADMM_LIMIT`: a key set with near-copies, such as a key and its mirror image) go to
    the Newton steps at once, from the per-frame solution.

    Returns
    -------
    W : (T, K) float, feasible
    gap : float, the certified relative gap ``(F(W) − max q) / F(W)``
    """
    lam = np.linalg.eigvalsh(seq.G)
    exact = EigenSolver(seq, 0.0)
    # start from the unconstrained smooth fit P⁻¹c, clipped: near the optimum wherever the bounds
    # are idle, above all across gaps, whose slow modes ADMM would otherwise have to build up
    start = project(exact.solve(seq.C), seq.upper, seq.convex)
    if admm_iterations(seq, lam, rtol) > _ADMM_LIMIT:
        data = seq.delta > 0
        first = start.copy()
        first[data] = nnls_gram(seq.G, seq.C[data], seq.upper, seq.convex)  # where the frames have data
        best = Best(seq, exact, first)
        with contextlib.suppress(np.linalg.LinAlgError):  # a face singular to rounding: ADMM's way instead
            newton(seq, best, rtol=rtol, max_newton=max_newton)
        if best.gap <= rtol:
            return best.Z, best.gap
    rho = admm_rho(seq, lam)
    solver = EigenSolver(seq, rho)
    done, rounds = 20, 10
    Z, U = admm(seq, solver, rho, start, np.zeros(seq.C.shape), done)
    best = Best(seq, exact, Z)
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
        rounds = int(np.clip(np.ceil(1.25 * need) + 1, 2, _MAX_ROUND))  # a missed certificate costs more
    handed = best.Z
    if best.gap > rtol:  # ADMM has converged but where only the smoothness holds the weights
        local_finish(seq, best, rtol=rtol, max_newton=max_newton)
    if best.gap > rtol:  # from ADMM's active set: the windows' may be the worse start elsewhere
        newton(seq, best, rtol=rtol, max_newton=max_newton, start=handed)
    return best.Z, best.gap


def admm_iterations(seq: Sequence, lam: np.ndarray, rtol: float) -> float:
    """A pessimistic forecast of ADMM's iterations to ``rtol``: ``ln rtol / ln(1 − 2/√κ)``, the
    rate of the stiffest against the softest curvature, ``κ = (λ_max + 4μ) / λ_min`` (the
    data's eigenvalues ``lam`` and the smoothness that :func:`admm_rho` counts; the
    contraction ``|h − ρ| / (h + ρ)`` of a free coordinate at ``ρ = √(λ_min (λ_max + 4μ))``).
    Measured, ADMM needs 3–4× fewer (38 against 147, about 440 against 1,307 on the demo
    clip's two regions), so the forecast only separates the crawling problems from the rest.
    """
    if not lam[0] > 0.0:
        return 0.0  # singular keys: the faces can be singular too, so ADMM's way
    kappa = (lam[-1] + 4.0 * seq.mu) / lam[0]
    if kappa <= 4.0:
        return 1.0
    return float(np.log(rtol) / np.log1p(-2.0 / np.sqrt(kappa)))


# --------------------------------------------------------------------------- entry point


def solve_pieces(seq: Sequence, sq: np.ndarray, *, rtol: float, n_pieces: int, max_newton: int = 40):
    """:func:`solve_sequence`'s result, from ``n_pieces`` overlapping pieces of the take solved at
    once on as many threads, then joined.

    The smoothness couples a frame to two on either side only, and the optimum's response to a
    change falls off geometrically with distance (by ``10⁻⁶`` over the margin of
    :func:`keyshape.decompose._activeset.decay_margin`). So each piece is solved on its own with
    twice that margin of the neighbouring pieces on either side, of which only its own frames
    are kept. The certificate of the whole take decides; should it fall short, active-set
    steps on the whole take finish from the joined point. (Solving the seams' frames again
    with the rest fixed was tried: the joined pieces were already certified on every test
    problem and on the demo clip's take tiled to 100,000 frames, and where a seam window ran
    anyway it could lower the objective yet loosen the certificate.)

    ``sq (T,)``: ``‖b_t‖²`` per frame (any value in gaps), for each piece's own constant.
    """
    n = seq.n_frames
    lam = np.linalg.eigvalsh(seq.G)
    margin = decay_margin(seq, lam)
    edges = np.linspace(0, n, n_pieces + 1).astype(int)
    data_sq = np.where(seq.delta > 0, sq, 0.0)

    def piece(i: int) -> np.ndarray:
        lo, hi = max(edges[i] - 2 * margin, 0), min(edges[i + 1] + 2 * margin, n)
        frames = slice(lo, hi)
        sub = Sequence(seq.G, np.ascontiguousarray(seq.C[frames]), seq.delta[frames], seq.mu, seq.upper, seq.convex,
                       float(data_sq[frames].sum()))
        return solve_sequence(sub, rtol=rtol, max_newton=max_newton)[0][edges[i] - lo : edges[i + 1] - lo]

    with ThreadPoolExecutor(max_workers=n_pieces) as pool:
        Z = np.concatenate(list(pool.map(piece, range(n_pieces))))
    best = Best(seq, EigenSolver(seq, 0.0), Z)
    if best.gap > rtol:
        newton(seq, best, rtol=rtol, max_newton=max_newton)
    return best.Z, best.gap


def _pieces(n_frames: int) -> int:
    """How many pieces :func:`spacetime_gram` cuts a take of ``n_frames`` into: one per core, each
    at least :data:`_PIECE_FRAMES` long."""
    return max(1, min(os.cpu_count() or 1, n_frames // _PIECE_FRAMES))


def spacetime_gram(G, C, valid, sq, mu, upper, convex, *, rtol=1e-7) -> np.ndarray:
    """Solve one region's spacetime QP; frames outside the first..last valid frame are NaN.

    A long take (at least two :data:`_PIECE_FRAMES`) is solved in pieces on a thread per core
    (:func:`solve_pieces`): the same optimum, to the same certificate.

    Parameters
    ----------
    G : (K, K) float, ``AᵀA``
    C : (n_frames, K) float, ``Aᵀ b_t`` (any value where ``valid`` is False)
    valid : (n_frames,) bool, frames with data
    sq : (n_frames,) float, ``‖b_t‖²`` (any value where ``valid`` is False)
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
    const = float(sq[valid].sum())
    seq = Sequence(gram.G, np.ascontiguousarray(C[span] * delta[:, None]), delta, mu, upper, convex, const)
    n_pieces = _pieces(len(delta))
    if n_pieces > 1:
        W, gap = solve_pieces(seq, sq[span], rtol=rtol, n_pieces=n_pieces)
    else:
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
