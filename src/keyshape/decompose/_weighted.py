"""The solve with hidden landmarks: weighted least squares, weight = visibility.

A frame ``t`` whose landmarks have weights ``v_t`` in [0, 1] (:attr:`keyshape.Track.visibility`,
repeated over the coordinates) fits

.. math::

    \\sum_t \\lVert V_t^{1/2} (A w_t - b_t) \\rVert^2 + μ \\sum_t \\lVert w_{t+1} - 2 w_t + w_{t-1} \\rVert^2,
    \\qquad V_t = \\operatorname{diag}(v_t),

so a hidden landmark (a hand over the mouth) stops pulling the weights and a fully hidden
region is carried by the smoothness term from the frames around it, as a gap is.

* Frames whose region keeps less than ``HIDDEN`` of its weight have no data term: they are
  gaps (NaN rows), bridged exactly by the smoothed solve (NaN weights without smoothing).
* Without smoothing, every partly hidden frame is solved exactly on its own Gram matrix
  ``Aᵀ V_t A``, all in one compiled pass (:func:`solve_weighted_frames`).
* With smoothing (and no ``Σw ≤ 1``) the QP is solved exactly in Gram form: ``G_t = Aᵀ V_t A``
  (one matrix product for all frames, :func:`weighted_gram`), ``c_t = Aᵀ V_t b_t`` and
  ``b_tᵀ V_t b_t`` are all it reads of the frames, so a long take is reduced chunk by chunk
  (:class:`keyshape.decompose.GramTake`). :func:`solve_weighted_gram` runs primal–dual
  active-set steps (Hintermüller, Ito & Kunisch 2003) on the banded Hessian
  ``P = blockdiag(G_t) + μ LᵀL ⊗ I`` (bandwidth ``2K``, frames in order): each step fixes the
  variables at their bounds and solves the free ones exactly, one Cholesky factorisation of the
  free variables only (numbered frame-major, on their envelope, :mod:`._kernels_face`, as the
  unweighted solve factors its faces), then moves every variable that breaks a KKT condition
  to the other side. A face of a whole take of at least :data:`SPLIT_FRAMES` frames is
  factored as two halves at once, on two threads, and its middle two frames last (one-way
  dissection: the same face, exactly, :meth:`_Problem._solve_split`).

  - The first active set is every frame's own (its box QP without the smoothness, block
    principal pivoting, each frame from the active set of the frame before), then one
    symmetric block Gauss–Seidel sweep over the frames (each frame's box QP with its
    neighbours held): a sweep carries a change along the whole take. (A second sweep costs
    more than the steps it saves: 1.8 s instead of 2.6 on a 100,000-frame take, K = 14.)
    The frames without data (a gap) start free (:data:`GAPS_FREE`): the first face bridges
    them by the smoothness, where the frame before's bounds, carried along, put whole gaps at
    a bound that the steps then release frame by frame.
    (The unconstrained smooth fit ``P⁻¹c``, clipped, is a far worse start where keys are near
    duplicates: its weights swing far outside the box, eight steps instead of three.)
  - Of a run of free weights of one key past a bound on consecutive frames, a step moves only
    the deepest to the bound (:data:`DEEPEST`, :func:`_deepest`); every other change moves at
    once. The second difference is a fourth-order coupling, without a maximum principle: a face
    solution dips below 0 over whole weakly seen stretches, the optimum touches 0 on far fewer
    frames, and a dip put at the bound all at once was released again about one frame per step
    (the multiplier next to the edge of a run at a bound keeps the right sign until the edge
    moves): 102–105 local steps on each 50,000-frame piece of a hand over the mouth
    (visibility 0.05 on 60 % of a region's landmarks for 170 frames, 40 of them a gap),
    18–29 with it (and :data:`GAPS_FREE`), a quarter of the frames re-solved.
  - Once at most one variable in :data:`FEW` changes, *local* steps re-solve only the frames
    within :data:`SMALL` of the latest changes, the rest held, until none is left, and one
    exact face on the frames within :data:`WINDOW` of every change closes the phase: runs
    whose edges still move cost their frames, not the take's. A variable that goes back and
    forth (:data:`CYCLING` changes) then moves only as the largest violation of its window,
    which breaks the cycles of degenerate faces.
  - The answer is exact: the steps end on a face of the whole take whose solution meets every
    KKT condition (to ``1e-11``, dimensionless). Should they be slow (damped, or past half of
    :data:`MAX_STEPS`), the whole ``P`` is factored once more for a duality bound,
    ``q(y) = const − (c − y)ᵀP⁻¹(c − y) − 2σ_C(y) ≤ F*``, and a relative gap of ``tol``
    (1e-7 by default) ends them as it ends the unweighted solve; above ``max(1e-4, 100 tol)``
    a ConvergenceWarning says so.
  - A take of at least twice :data:`PIECE_FRAMES` frames is cut into overlapping pieces, one
    per core, solved at once on threads (the compiled kernels release the GIL), joined, and
    the steps above go on on the whole take from the joined point's active set
    (:func:`_exact_pieces`): the whole take's face and its KKT conditions decide, so the
    answer is the same optimum to the same certificate (on the takes measured, the joined point
    already was it: one face of the whole take certified it).
* Otherwise (``Σw ≤ 1``, or a ``P`` that is not positive definite), majorise-minimise
  (Kiers 1997; Srebro & Jaakkola 2003): as ``V_t ⪯ I``,
  ``‖V_t^{1/2}(A w − b_t)‖² ≤ ‖A w − \\tilde b_t‖² + const`` with the hidden part filled in from
  the current fit, ``\\tilde b_t = v_t ⊙ b_t + (1 − v_t) ⊙ A w_t^{(k)}``; each step is the
  unweighted solve on ``\\tilde B`` and the objective never increases.

Frames with every landmark seen are not touched: a track without visibility, or an all-visible
region, takes the unweighted path unchanged.

References
----------
Hintermüller, M., Ito, K. & Kunisch, K. (2003). The primal-dual active set strategy as a
semismooth Newton method. *SIAM J. Optim.* 13(3), 865–888.
Nocedal, J. & Wright, S. J. (2006). *Numerical Optimization*, 2nd ed. Springer.
Kiers, H. A. L. (1997). Weighted least squares fitting using ordinary least squares algorithms.
*Psychometrika* 62(2), 251–266.
Srebro, N. & Jaakkola, T. (2003). Weighted low-rank approximations. *ICML*.
O'Donoghue, B. & Candès, E. (2015). Adaptive restart for accelerated gradient schemes.
*Found. Comput. Math.* 15, 715–732.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..exceptions import ConvergenceWarning
from ._nnls import nnls_gram
from ._sequence import second_difference_gram

__all__ = ["HIDDEN", "coordinate_weights", "solve_weighted", "solve_weighted_frames", "solve_weighted_gram",
           "weighted_gram"]

HIDDEN = 0.02  # a frame whose region keeps less of its weight (mean visibility) has no data term
MAX_MM_STEPS = 500  # majorise-minimise steps of the smoothed solve
STEP_TOL = 1e-5  # ... until no weight moves by more than this
_WARN_GAP = 1e-4  # a certified gap above this (and 100x the asked one) is reported, as in _spacetime

_KKT_TOL = 1e-11  # a dimensionless KKT violation below this is none (as in _activeset)
LOWER, FREE, UPPER = 0, 1, 2  # the state of a variable
WINDOW = 40  # frames on either side of the changes of a local phase re-solved exactly at its end
SMALL = 20  # frames on either side of a change re-solved by each step of a local phase
FEW = 100  # a local phase once at most 1 in FEW variables changes on the whole take
MAX_STEPS = 30  # active-set steps on the whole take
MAX_LOCAL = 300  # steps of one local phase
CYCLING = 4  # changes of side after which a variable counts as cycling
SWEEPS = 1  # symmetric block Gauss-Seidel sweeps over the frames before the first step
GAPS_FREE = True  # the first active set leaves the frames without data free (bridged by the first face)
DEEPEST = True  # of a run of free weights past a bound, only the deepest goes to it per step
# a take of at least twice this many frames is solved in pieces, one per core (10,000 frames of the
# benchmark's hand over the mouth: 0.26 s on one thread, 0.18 s of wall clock in two pieces on two cores)
PIECE_FRAMES = 5_000
REACH = 1e-6  # ... overlapping by twice the frames over which a change decays by this
SPLIT_FRAMES = 20_000  # a face of a whole take this long is factored in two halves on two threads


def coordinate_weights(seen: np.ndarray, n_dims: int) -> np.ndarray:
    """(n_frames, n_region_landmarks · n_dims): each landmark's visibility on its coordinates."""
    # rows of B are flattened (landmark, dimension) pairs, landmark-major
    return np.repeat(np.asarray(seen, dtype=float), n_dims, axis=1)


def solve_weighted(A: np.ndarray, B: np.ndarray, weight: np.ndarray, solve: Callable[[np.ndarray], np.ndarray], *,
                   smoothness: float, upper: np.ndarray, convex: bool, mu: float | None = None,
                   tol: float = 1e-7) -> np.ndarray:
    """(n_frames, K) weights of one region with per-frame, per-coordinate data weights.

    Parameters
    ----------
    A : (m, K) float
    B : (n_frames, m) float, NaN rows are frames without a face
    weight : (n_frames, m) float in [0, 1]
    solve : the unweighted solve of the region, ``B (n_frames, m) -> (n_frames, K)`` (NaN rows gaps)
    smoothness : float, 0 for per-frame solves
    upper : (K,) float; convex : bool (for the exact per-frame solves)
    mu : float, optional
        The smoothness term's weight ``μ`` that ``solve`` uses; with it (and not ``convex``) the
        smoothed problem is solved exactly in Gram form (:func:`solve_weighted_gram`), else by
        majorise-minimise.
    tol : float
        The relative duality gap that the exact smoothed solve certifies.
    """
    B = np.asarray(B, dtype=float)
    seen = np.isfinite(B).all(axis=1) & ~(weight.mean(axis=1) < HIDDEN)  # frames with a data term
    partial = np.flatnonzero(seen & (weight < 1.0).any(axis=1))
    if partial.size and smoothness > 0.0 and mu is not None and mu > 0.0 and not convex:
        # G_t, c_t = Aᵀ V_t b_t and b_tᵀ V_t b_t, zero where no data (few whole-take temporaries: their
        # first touch costs as much as the products)
        Bv = weight * B
        Bv[~seen] = 0.0
        sq = np.einsum("fm,fm->f", Bv, B)
        sq[~seen] = 0.0
        G = weighted_gram(A, weight)
        G[~seen] = 0.0
        found = solve_weighted_gram(G, Bv @ A, sq, seen, mu, np.asarray(upper, dtype=float), tol=tol)
        if found is not None:
            return found
    B = np.array(B)
    B[~seen] = np.nan  # frames without a face, or whose region is (nearly) all hidden: gaps
    W = solve(B)
    if not partial.size:
        return W
    if smoothness == 0.0 and not convex:  # every partly hidden frame on its own Gram matrix, at once
        v = weight[partial]
        W[partial] = solve_weighted_frames(weighted_gram(A, v), (v * B[partial]) @ A, np.ones(len(partial), bool),
                                           np.asarray(upper, dtype=float))
        return W
    if smoothness == 0.0:
        for t in partial:
            Av = A * weight[t][:, None]  # V_t A
            W[t] = nnls_gram(Av.T @ A, (B[t] @ Av)[None], upper, convex)[0]
        return W
    return _majorise(A, B, weight[partial], partial, W, solve)


def solve_weighted_frames(G: np.ndarray, C: np.ndarray, valid: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Every frame on its own Gram matrix (no smoothing): ``(n_frames, K)``, NaN where not
    ``valid``. Block principal pivoting frame by frame, compiled (each frame checked against its
    KKT conditions); the rare frame where the exchanges stall is finished exactly by
    :func:`keyshape.decompose._nnls.nnls_gram`."""
    from . import _kernels_weighted

    G, C = np.ascontiguousarray(G, dtype=float), np.ascontiguousarray(C, dtype=float)
    valid = np.asarray(valid, bool)
    X, stalled = np.zeros(C.shape), np.zeros(len(C), bool)
    upper = np.asarray(upper, dtype=float)
    _kernels_weighted.frames_solve(G, C, upper, bool(np.isfinite(upper).any()), valid, X, stalled)
    for t in np.flatnonzero(stalled):
        X[t] = nnls_gram(G[t], C[t][None], upper, False)[0]
    X[~valid] = np.nan
    return X


def solve_weighted_gram(G: np.ndarray, C: np.ndarray, sq: np.ndarray, valid: np.ndarray, mu: float,
                        upper: np.ndarray, *, tol: float = 1e-7) -> np.ndarray | None:
    """The weighted smoothed QP of one region from its Gram form; frames before the first or
    after the last frame with data are NaN (not extrapolated), as in the unweighted solve.

    Parameters
    ----------
    G : (n_frames, K, K) float, ``Aᵀ V_t A`` (any value where not ``valid``)
    C : (n_frames, K) float, ``Aᵀ V_t b_t``
    sq : (n_frames,) float, ``b_tᵀ V_t b_t``
    valid : (n_frames,) bool, frames with a data term
    mu : float > 0
    upper : (K,) float, ``inf`` where unbounded
    tol : float, the relative duality gap certified (a ConvergenceWarning when the steps stop
        above ``max(1e-4, 100 tol)``)

    Returns
    -------
    (n_frames, K) float within the bounds. Should the Hessian not be positive definite
    (rank-deficient keys with frames that see too little), a ridge of ``1e-10 · max |G|`` is
    added to every ``G_t``, as the per-frame solver does; None if even that fails.
    """
    n, K = C.shape
    out = np.full((n, K), np.nan)
    rows = np.flatnonzero(valid)
    if not len(rows):
        return out
    span = slice(rows[0], rows[-1] + 1)  # gaps inside are bridged, the ends are not extrapolated
    seen = valid[span]
    Gs, Cs = np.ascontiguousarray(G[span], dtype=float), np.ascontiguousarray(C[span], dtype=float)
    if not seen.all() and (Gs[~seen].any() or Cs[~seen].any()):  # frames without data: no data term
        Gs, Cs = np.where(seen[:, None, None], Gs, 0.0), np.where(seen[:, None], Cs, 0.0)
    const = float(np.sum(sq[span][seen]))
    if len(seen) < 3:  # no second difference: frame by frame
        for i in range(len(seen)):
            out[span.start + i] = nnls_gram(Gs[i], Cs[i][None], upper, False)[0]
        return out
    found = None
    for ridge in (0.0, 1e-10):  # rank-deficient keys: the smallest-norm blend of the equally good ones
        if ridge:
            Gs = Gs + ridge * float(np.abs(Gs).max()) * np.eye(K)
        try:
            n_pieces = _pieces(len(seen))
            if n_pieces > 1:
                found = _exact_pieces(Gs, Cs, np.where(seen, sq[span], 0.0), mu, upper, tol=tol, valid=seen,
                                      n_pieces=n_pieces)
            else:
                found = _exact(Gs, Cs, const, mu, upper, tol=tol, valid=seen)
        except np.linalg.LinAlgError:
            found = None
        if found is not None:
            break
    if found is None:
        return None
    X, gap = found
    if gap > max(_WARN_GAP, 100.0 * tol):
        warnings.warn(f"the visibility-weighted smoothed solve stopped at a certified relative gap of {gap:.1e} "
                      f"(asked: {tol:.0e})", ConvergenceWarning, stacklevel=3)
    out[span] = X
    return out


def _majorise(A, B, v, partial, W, solve):
    """Majorise-minimise steps from ``W`` until the weights settle (see the module notes).

    Each step is a proximal-gradient step in the metric ``AᵀA`` (the smoothness and the bounds
    are its proximal part), so Nesterov's extrapolation applies: steps from ``Y = W_k + β_k
    (W_k − W_{k−1})``, restarted whenever a step turns back (O'Donoghue & Candès 2015).
    """
    seen, Y, momentum = v * B[partial], W, 1.0
    for _ in range(MAX_MM_STEPS):
        B[partial] = seen + (1.0 - v) * (Y[partial] @ A.T)  # b̃_t = v ⊙ b_t + (1 − v) ⊙ A y_t
        new = solve(B)
        move = new - W
        step = np.nanmax(np.abs(move), initial=0.0)
        if step < STEP_TOL:
            return new
        if np.nansum((Y - new) * move) > 0.0:  # the step turned back: restart the momentum
            momentum = 1.0
        following = (1.0 + np.sqrt(1.0 + 4.0 * momentum**2)) / 2.0
        Y = new + ((momentum - 1.0) / following) * move
        W, momentum = new, following
    warnings.warn(f"the visibility-weighted solve stopped after {MAX_MM_STEPS} steps with weights still moving by "
                  f"{step:.2g}", ConvergenceWarning, stacklevel=4)
    return W


# --------------------------------------------------------------------------- the exact solve in Gram form


def weighted_gram(A: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """``G_t = Aᵀ V_t A`` of every frame, ``(n, K, K)``, as one product: ``G = weight @ H`` with
    ``H_i = a_i a_iᵀ`` the outer product of row ``i`` of ``A`` (rows of one landmark summed
    when ``weight`` repeats each landmark's visibility over its coordinates, as
    :func:`coordinate_weights` does)."""
    m, K = A.shape
    n = weight.shape[0]
    H = (A[:, :, None] * A[:, None, :]).reshape(m, K * K)
    for d in (3, 2):
        if m % d == 0 and m > d and (weight.reshape(n, m // d, d) == weight[:, ::d, None]).all():
            H, weight = H.reshape(m // d, d, K * K).sum(axis=1), weight[:, ::d]
            break
    return np.ascontiguousarray(weight @ H).reshape(n, K, K)


class _Problem:
    """The weighted QP of one region in Gram form: ``G (T, K, K)``, ``C (T, K)``, ``μ``, bounds;
    exact solves of a face on any frames with the others held, and KKT violations."""

    def __init__(self, G, C, mu, upper, split=False):
        from . import _kernels, _kernels_weighted

        n = len(C)
        self.split = bool(split) and n >= SPLIT_FRAMES  # faces of the whole take on two threads
        self.flip = None  # the buffers of the split's second half, made on first use

        self.k0, self.kw = _kernels, _kernels_weighted
        self.G, self.C, self.mu = np.ascontiguousarray(G, dtype=float), np.ascontiguousarray(C, dtype=float), float(mu)
        n, K = self.C.shape
        self.upper = np.asarray(upper, dtype=float)
        self.top = np.where(np.isfinite(self.upper), self.upper, 0.0)
        d0, d1, d2 = second_difference_gram(n)
        self.d = (d0, np.append(d1, np.zeros(n - len(d1))), np.append(d2, np.zeros(n - len(d2))))
        self.every = np.arange(n)
        # the band of the face being solved: room for every variable free, but only the pages a face
        # uses are ever touched (first touch costs a page fault; a buffer allocated anew would pay again)
        self.packed = np.empty(n * K * (2 * K + 1))  # a column of the envelope is at most 2K + 1 long
        self.rhs = np.empty(n * K)
        self.pos, self.reach, self.offset = np.empty((n, K), np.int64), np.empty(n * K, np.int64), np.empty(n * K,
                                                                                                          np.int64)
        diagonal = np.einsum("tkk->tk", self.G)  # |G_ij| <= max(G_ii, G_jj): G_t is positive semi-definite
        self.g_scale = float(np.abs(self.C).max(initial=0.0) + diagonal.max(initial=0.0) + mu)

    def _solve_split(self, X, state):
        """The face of the whole take (frames ``0 … T − 1``, ``X`` and ``state`` in place) on two
        threads: the frames before the middle two, ``A``, and the frames after them, ``B``,
        numbered from the end backwards, are factored at once (:func:`forward_face`, each on
        its own envelope), the middle two frames ``S`` last. ``A`` and ``B`` are coupled only
        through ``S``, so with that order the Cholesky factor of ``P_FF`` is
        ``[[L_A, 0, 0], [0, L_B, 0], [W_Aᵀ, W_Bᵀ, L_S]]``, ``W_A = L_A⁻¹ P_AS`` (nonzero only on
        ``A``'s last two frames, which ``P_AS`` couples to ``S``; likewise ``B``'s first two) and
        ``L_S L_Sᵀ = P_SS − W_AᵀW_A − W_BᵀW_B`` (at most ``2K × 2K``): the same face, exactly,
        factored as two halves and a small dense block (George & Liu 1981, ch. 6, one-way
        dissection)."""
        kw, mu = self.kw, self.mu
        n, K = X.shape
        d0, d1, d2 = self.d
        s = n // 2
        if self.flip is None:  # B seen backwards: the frames reversed, LᵀL's diagonals reversed
            m = n - s - 2
            self.flip = (np.ascontiguousarray(d0[::-1]), np.append(d1[: n - 1][::-1], 0.0),
                         np.append(d2[: n - 2][::-1], [0.0, 0.0]), np.empty((m, K), np.int64),
                         np.empty(m * K, np.int64), np.empty(m * K, np.int64), np.empty(m * K * (2 * K + 1)),
                         np.empty(m * K))
        e0, e1, e2, pos_b, reach_b, offset_b, packed_b, rhs_b = self.flip
        kw.hold(self.top, state, X, self.every)
        rows_a, rows_b = self.every[:s], self.every[: n - s - 2]  # B: u = n − 1 − t for t = n − 1 … s + 2
        pos_a = self.pos[:s]
        Xr, Gr, Cr, Sr = X[::-1], self.G[::-1], self.C[::-1], state[::-1]
        with ThreadPoolExecutor(max_workers=1) as pool:
            other = pool.submit(kw.forward_face, Gr, Cr, mu, e0, e1, e2, Sr, Xr, rows_b, pos_b, reach_b, offset_b,
                                packed_b, rhs_b)
            n_a = kw.forward_face(self.G, self.C, mu, d0, d1, d2, state, X, rows_a, pos_a, self.reach, self.offset,
                                  self.packed, self.rhs)
            n_b = other.result()
        if n_a < 0 or n_b < 0:
            raise np.linalg.LinAlgError("Cholesky factorisation failed on a face: not positive definite")
        middle = np.array([s, s + 1])
        t_s, k_s = np.nonzero(state[middle] == FREE)
        t_s = t_s + s
        r_s = self.C[t_s, k_s] - self.hess(X, middle)[t_s - s, k_s]  # X: the face's fixed values
        same = t_s[:, None] == t_s[None, :]
        P_ss = np.where(same, self.G[t_s[:, None], k_s[:, None], k_s[None, :]], 0.0)
        P_ss[np.diag_indices(len(t_s))] += mu * d0[t_s]
        beside = (t_s[:, None] + 1 == t_s[None, :]) & (k_s[:, None] == k_s[None, :])
        P_ss += mu * d1[s] * (beside | beside.T)
        # the couplings of S to A (frames s − 2, s − 1) and to B (frames s + 2, s + 3), as (frame, coefficient)
        near_a = [(s - 1, np.where(t_s == s, d1[s - 1], d2[s - 1])), (s - 2, np.where(t_s == s, d2[s - 2], 0.0))]
        near_b = [(s + 2, np.where(t_s == s, d2[s], d1[s + 1])), (s + 3, np.where(t_s == s, 0.0, d2[s + 1]))]
        tails = []
        for near, pos, n_h, reach, offset, packed, y, flip in (
                (near_a, pos_a, n_a, self.reach, self.offset, self.packed, self.rhs, lambda t: t),
                (near_b, pos_b, n_b, reach_b, offset_b, packed_b, rhs_b, lambda t: n - 1 - t)):
            idx = [pos[flip(t), k_s] for t, _ in near]
            free = np.concatenate(idx)
            j0 = int(free[free >= 0].min()) if (free >= 0).any() else n_h
            Wt = np.zeros((n_h - j0, len(t_s)))
            for (_, coef), j in zip(near, idx, strict=True):
                hit = j >= 0
                Wt[j[hit] - j0, np.flatnonzero(hit)] = mu * coef[hit]
            kw.forward_tail(n_h, reach, offset, packed, j0, Wt)  # W = L⁻¹ P_{·S} on the tail
            P_ss -= Wt.T @ Wt
            r_s -= Wt.T @ y[j0:n_h]
            tails.append((Wt, j0, n_h))
        L_s = np.linalg.cholesky(P_ss)
        x_s = np.linalg.solve(L_s.T, np.linalg.solve(L_s, r_s))
        for (Wt, j0, n_h), y in zip(tails, (self.rhs, rhs_b), strict=True):
            y[j0:n_h] -= Wt @ x_s
        with ThreadPoolExecutor(max_workers=1) as pool:
            other = pool.submit(kw.backward_face, n_b, reach_b, offset_b, packed_b, rhs_b)
            kw.backward_face(n_a, self.reach, self.offset, self.packed, self.rhs)
            other.result()
        kw.put_free(X, rows_a, pos_a, self.rhs)
        kw.put_free(Xr, rows_b, pos_b, rhs_b)
        X[t_s, k_s] = x_s

    def hess(self, X, rows):
        """``(P X)`` on the frames ``rows``: ``(len(rows), K)``."""
        out = np.empty((len(rows), X.shape[1]))
        self.kw.hessian_at(self.G, self.mu, *self.d, X, rows, out)
        return out

    def solve(self, X, state, rows):
        """Frames ``rows`` (sorted) of ``X`` (in place) on the exact minimiser of their face, the
        other frames held: the free variables numbered frame-major, their system factored by
        the envelope Cholesky factorisation of :mod:`keyshape.decompose._kernels_face`
        (:func:`keyshape.decompose._kernels_weighted.solve_face`), in the problem's buffers."""
        if self.split and len(rows) == len(X):
            self._solve_split(X, state)
            return
        if not self.kw.solve_face(self.G, self.C, self.mu, *self.d, self.top, state, X, rows, self.pos[: len(rows)],
                                  self.reach, self.offset, self.packed, self.rhs):
            raise np.linalg.LinAlgError("Cholesky factorisation failed on a face: not positive definite")

    def violations(self, X, state, rows):
        """Dimensionless KKT violations ``(len(rows), K)`` on the current face (> 0: changes side)."""
        out = np.empty((len(rows), X.shape[1]))
        x_scale = self.x_scale(X)
        args = (self.G, self.C, self.mu, *self.d, X, state, self.upper)
        if self.split and len(rows) == len(X):  # the whole take: each half on a thread
            h = len(rows) // 2
            with ThreadPoolExecutor(max_workers=1) as pool:
                other = pool.submit(self.kw.kkt, *args, rows[h:], x_scale, self.g_scale * x_scale, out[h:])
                self.kw.kkt(*args, rows[:h], x_scale, self.g_scale * x_scale, out[:h])
                other.result()
            return out
        self.kw.kkt(*args, rows, x_scale, self.g_scale * x_scale, out)
        return out

    def x_scale(self, X):
        """``1 + max |x|``: the bounds' when every weight is bounded (cheap on a few frames)."""
        if np.isfinite(self.upper).all():
            return 1.0 + float(self.upper.max(initial=0.0))
        return 1.0 + float(np.abs(X).max(initial=0.0))


class _Certificate:
    """The factor of the whole ``P`` (every variable free) and the duality bound it gives:
    ``q(y) = const − (c − y)ᵀP⁻¹(c − y) − 2σ_C(y) ≤ F*`` for multipliers ``y`` read off a
    feasible point (as :func:`keyshape.decompose._sequence.lower_bound`, with this ``P``)."""

    def __init__(self, problem: _Problem, const: float):
        from . import _kernels_face

        self.problem, self.const, self.kf = problem, float(const), _kernels_face
        n, K = problem.C.shape
        kw = problem.kw
        state = np.full((n, K), FREE, np.int8)
        self.reach, self.offset = np.empty(n * K, np.int64), np.empty(n * K, np.int64)
        pos = np.empty((n, K), np.int64)
        self.n_free, size = kw.number_face(state, problem.every, pos, self.reach, self.offset)
        self.packed = np.empty(size)
        kw.fill_face(problem.G, problem.C, problem.mu, *problem.d, problem.top, state, np.zeros((n, K)), problem.every,
                     pos, self.reach, self.offset, self.packed, np.empty(n * K))
        self.ok = bool(_kernels_face.factor_face(self.n_free, self.reach, self.offset, self.packed))
        self.F, self.q, self.Z = np.inf, -np.inf, None

    def inverse(self, R):
        """``P⁻¹ R`` for ``R (T, K)``."""
        x = np.array(R, dtype=float).ravel()
        self.kf.solve_face(self.n_free, self.reach, self.offset, self.packed, x)
        return x.reshape(R.shape)

    def offer(self, Z):
        """Keep the feasible ``Z`` if it is the best point yet; raise the bound with its
        multipliers; the certified relative gap."""
        p = self.problem
        PZ = p.hess(Z, p.every)
        F = float(np.einsum("tk,tk->", Z, PZ - 2.0 * p.C) + self.const)
        if F < self.F:
            self.F, self.Z = F, Z
        Y = np.empty_like(Z)
        p.k0.point_multipliers(p.C - PZ, Z, p.upper, False, Y)
        Y = np.where(np.isfinite(p.upper), Y, np.minimum(Y, 0.0))
        R = p.C - Y
        support = 2.0 * float(np.sum(np.maximum(Y, 0.0) * p.top))  # 2σ_C(y): the box's
        q = self.const - float(np.einsum("tk,tk->", R, self.inverse(R))) - support
        self.q = max(self.q, q)
        return self.gap

    @property
    def gap(self) -> float:
        """``(F − q) / F`` (for a near-exact fit, relative to ``1e-6 · const`` instead)."""
        return max(self.F - self.q, 0.0) / max(abs(self.F), 1e-6 * self.const, np.finfo(float).tiny)


class _Damping:
    """Should the exchanges stop shrinking, only the largest violations move: half as many
    each time (they cycle on degenerate problems, e.g. near-duplicate keys)."""

    def __init__(self):
        self.limit, self.history = None, []

    def __call__(self, count):
        self.history.append(count)
        if len(self.history) > 3 and count >= self.history[-4]:
            self.limit = max(1, (self.limit or count) // 2)
            self.history.clear()


def _exchange(X, state, rows, viol, limit=None, flips=None):
    """The primal–dual active-set update of ``state`` on ``rows`` (in place): (count of
    violations, (len(rows),) bool rows that had one).

    With :data:`DEEPEST`, of a run of free weights of one key past the same bound on
    consecutive frames only the deepest goes to it (:func:`_deepest`); the variables at a bound
    whose multiplier has the wrong sign are all released, as before. ``limit``: only that many
    of the largest violations move. ``flips (T, K)``: how often each
    variable changed side so far (updated); a variable that went back and forth
    (:data:`CYCLING` changes) moves only if it has the largest violation among such variables
    of its window (runs of ``rows``), which breaks the cycles of degenerate problems locally.
    """
    move = viol > _KKT_TOL
    count = int(move.sum())
    wrong = move.any(axis=1)
    if not count:  # nothing changes side
        return 0, wrong
    if limit is not None and count > limit:
        move &= viol >= np.partition(viol.ravel(), -limit)[-limit]
    sub = state[rows]
    if DEEPEST:
        out = move & (sub == FREE)
        if out.any():
            move &= ~out | _deepest(rows, out, viol, X[rows] < 0.0)
    if flips is not None:
        cycling = move & (flips[rows] >= CYCLING)
        if cycling.any():
            run = np.cumsum(np.append(True, np.diff(rows) > 2 * SMALL + 1)) - 1  # (len(rows),) window
            score = np.where(cycling, viol, -np.inf).max(axis=1)
            top = np.full(run[-1] + 1, -np.inf)
            np.maximum.at(top, run, score)
            keep = cycling & (viol >= top[run][:, None])
            move &= ~cycling | keep
        flips[rows] += move
    state[rows] = np.where(move, np.where(sub == FREE, np.where(X[rows] < 0.0, LOWER, UPPER), FREE), sub)
    return count, wrong


def _deepest(rows, out, viol, below):
    """(len(rows), K) bool: of each run of ``out (len(rows), K)`` (free weights past a bound) on
    consecutive frames of ``rows`` (sorted), one key and one side (``below``: past 0, else past the upper
    bound), the variable with the largest violation ``viol`` (the first of equal ones).

    Why: the smoothness ``μ‖w_{t+1} − 2w_t + w_{t−1}‖²`` is a fourth-order coupling, without
    the maximum principle of a second-order one. Where a stretch has little data (a gap, weakly
    seen frames) a weight's face solution is a smoothing spline that dips below 0 over many
    frames; putting the whole dip at the bound overshoots (the optimum's contact set is far
    smaller: the spline, held at 0 at its deepest point, lifts its neighbours), and the primal–dual
    steps then release it again only about one frame per step (the multiplier of the frame next
    to the edge of a run at a bound has the right sign until that edge moves). Holding only the
    deepest point of each run makes the contact set grow from its middle, as a primal active-set
    method adds the most violated constraint (Nocedal & Wright 2006, § 16.5), while every other
    kind of change still moves at once. The steps end, as before, only on a face whose solution
    meets every KKT condition; the damping and the cycling rule of :func:`_exchange` stay."""
    n, K = out.shape
    t, k = np.nonzero(out)
    order = np.lexsort((t, below[t, k], k))  # by key, side, frame
    t, k = t[order], k[order]
    side = below[t, k]
    frame = rows[t]
    new = np.ones(len(t), bool)
    new[1:] = (k[1:] != k[:-1]) | (side[1:] != side[:-1]) | (frame[1:] != frame[:-1] + 1)
    run = np.cumsum(new) - 1
    v = viol[t, k]
    best = np.full(run[-1] + 1, -np.inf)
    np.maximum.at(best, run, v)
    at = np.flatnonzero(v >= best[run])
    at = at[np.append(True, run[at[1:]] != run[at[:-1]])]  # only the first of equal ones
    keep = np.zeros((n, K), bool)
    keep[t[at], k[at]] = True
    return keep


def _around(frames, reach, n):
    """The sorted frames within ``reach`` of any of the sorted ``frames`` (int64)."""
    from . import _kernels_weighted

    if not len(frames):
        return frames
    out = np.empty(min(len(frames) * (2 * reach + 1), n), np.int64)
    return out[: _kernels_weighted.around(np.asarray(frames, np.int64), reach, n, out)]


def _pieces(n_frames: int) -> int:
    """How many pieces :func:`solve_weighted_gram` cuts a take of ``n_frames`` into: one per
    core, each at least :data:`PIECE_FRAMES` long."""
    return max(1, min(os.cpu_count() or 1, n_frames // PIECE_FRAMES))


def _margin(G, valid, mu, n):
    """Frames over which a change of the optimum decays by :data:`REACH`, for a typical frame:
    the Green's function of ``λ I + μ LᵀL`` falls by ``|z|`` per frame, ``z`` the root inside the
    unit circle of ``(z − 2 + 1/z)² = −λ/μ``, with ``λ`` the smallest eigenvalue of the mean
    ``G_t`` of the frames with data (``G (T, K, K)``). At least :data:`WINDOW`, at most ``n``."""
    count = int(np.count_nonzero(valid))
    mean = np.einsum("t,tij->ij", valid.astype(float), G) / max(count, 1)  # no copy of the frames with data
    lam = float(np.linalg.eigvalsh(mean)[0]) if count else 0.0
    w = 2.0 + 1j * np.sqrt(max(lam, 0.0) / mu)
    z = abs((w - np.sqrt(w * w - 4.0)) / 2.0)
    z = min(z, 1.0 / z) if z > 0.0 else 0.0
    if not 0.0 < z < 1.0:
        return n
    return int(min(max(np.ceil(np.log(REACH) / np.log(z)), WINDOW), n))


def _exact_pieces(G, C, sq, mu, upper, *, tol, valid, n_pieces):
    """:func:`_exact`'s result from ``n_pieces`` overlapping pieces of the take solved at once,
    one thread each (the compiled kernels release the GIL), then joined and finished on the
    whole take.

    The smoothness couples a frame to two on either side, and the optimum's response to a
    change falls off geometrically with distance (:func:`_margin`), so each piece is solved with
    twice that margin of its neighbours on either side, of which only its own frames are kept.
    The joined point is then only a start: :func:`_exact` goes on from its active set on the
    whole take (a face of the whole take, its KKT conditions, local steps around what the join
    got wrong), so the answer carries the same certificate as the whole-take solve.
    ``G (T, K, K)``, ``C (T, K)``, ``sq (T,)`` (0 where not ``valid``), ``valid (T,)`` bool.
    """
    n = len(C)
    reach = 2 * _margin(G, valid, mu, n)
    edges = np.linspace(0, n, n_pieces + 1).astype(int)

    def piece(i):
        lo, hi = max(edges[i] - reach, 0), min(edges[i + 1] + reach, n)
        part = slice(lo, hi)
        X, _ = _exact(G[part], C[part], float(sq[part].sum()), mu, upper, tol=tol, valid=valid[part], certify=False)
        return X[edges[i] - lo : edges[i + 1] - lo]

    try:
        with ThreadPoolExecutor(max_workers=n_pieces) as pool:
            Z = np.concatenate(list(pool.map(piece, range(n_pieces))))
    except np.linalg.LinAlgError:  # a piece too thin in data to be positive definite (a long gap): whole
        Z = None
    return _exact(G, C, float(sq.sum()), mu, upper, tol=tol, valid=valid, start=Z)


def _exact(G, C, const, mu, upper, *, tol=1e-7, valid=None, trace=None, start=None, certify=True):
    """Minimiser ``(T, K)`` of the weighted smoothed QP in Gram form and its certified relative
    gap: 0 when a face of the whole take meets the KKT conditions (the exact optimum), else the
    duality gap (see the module notes); LinAlgError when ``P`` is not positive definite.
    ``valid``: the frames with data (default: those with a nonzero ``G_t``). ``trace``: a list
    that gets one entry per step on the whole take and per local step (for the benchmarks).
    ``start (T, K)``: a first point within the bounds, whose active set the steps start from
    (instead of the frames' own and the Gauss–Seidel sweeps). ``certify=False``: return (with
    a gap of ``inf``) once the first local phase has settled, without the face of the whole take
    that would check it (for a piece of :func:`_exact_pieces`, which the joined take's checks)."""
    problem = _Problem(G, C, mu, upper, split=certify and (os.cpu_count() or 1) > 1)
    n, K = problem.C.shape
    valid = np.abs(problem.G).reshape(n, -1).max(axis=1) > 0.0 if valid is None else np.asarray(valid, bool)
    if start is None:
        state = np.full((n, K), FREE, np.int8)  # each frame's own active set, then Gauss-Seidel sweeps
        X = np.empty((n, K))
        bounded = bool(np.isfinite(problem.upper).any())
        problem.kw.start(problem.G, problem.C, problem.mu, *problem.d, problem.upper, bounded, valid, state, X,
                         SWEEPS)
        if GAPS_FREE:  # the first face bridges a gap by the smoothness, rather than hold the frame before's bounds
            state[~valid] = FREE
    else:
        X = np.array(start, dtype=float)
        state = np.where(X <= 0.0, LOWER, np.where(X >= problem.upper, UPPER, FREE)).astype(np.int8)
    damping, cert = _Damping(), None
    for step in range(MAX_STEPS):
        problem.solve(X, state, problem.every)  # a face of the whole take: exact everywhere
        viol = problem.violations(X, state, problem.every)
        count, wrong = _exchange(X, state, problem.every, viol, damping.limit)
        if count == 0:  # the KKT conditions hold: the optimum (to rounding)
            return np.clip(X, 0.0, problem.upper), 0.0
        if cert is None and (damping.limit is not None or step >= MAX_STEPS // 2):  # slow: a bound to stop on
            cert = _Certificate(problem, const)
            if not cert.ok:
                raise np.linalg.LinAlgError("the weighted smoothed QP is not positive definite")
        gap = np.inf if cert is None else cert.offer(np.clip(X, 0.0, problem.upper))
        if trace is not None:
            trace.append(("whole", count, gap))
        if gap <= tol:
            break
        damping(count)
        if count <= max(8, n * K // FEW):  # few changes: local steps around them
            _local(problem, X, state, np.flatnonzero(wrong), trace)
            if not certify:  # a piece: the whole take's face checks it
                return np.clip(X, 0.0, problem.upper), np.inf
    if cert is None:
        cert = _Certificate(problem, const)
        if not cert.ok:
            raise np.linalg.LinAlgError("the weighted smoothed QP is not positive definite")
    cert.offer(np.clip(X, 0.0, problem.upper))
    return cert.Z, cert.gap


def _local(problem, X, state, hot, trace=None):
    """Active-set steps on the frames within :data:`SMALL` of the latest changes, the rest of
    the take held, until none is left; then one exact face on the frames within
    :data:`WINDOW` of every change, and again should that find more (``X``, ``state`` in place)."""
    n = len(X)
    moving = _around(hot, SMALL, n)
    touched = np.zeros(n, bool)
    touched[hot] = True
    final, flips = False, np.zeros(X.shape, np.int16)
    for _ in range(MAX_LOCAL):
        problem.solve(X, state, moving)
        check = _around(moving, 2, n)  # the frames whose KKT conditions the step changed
        viol = problem.violations(X, state, check)
        count, wrong = _exchange(X, state, check, viol, flips=flips)
        if trace is not None:
            trace.append((len(moving), count))
        if count == 0:
            if final:
                return
            final = True
            moving = np.flatnonzero(_dilate(touched, WINDOW))
            touched[:] = False  # the next exact round covers only what changes after this one
            continue
        final = False
        touched[check[wrong]] = True
        moving = _around(check[wrong], SMALL, n)


def _dilate(mask, reach):
    """(T,) bool: the frames within ``reach`` of a True one."""
    count = np.concatenate([[0], np.cumsum(mask)])
    n = len(mask)
    t = np.arange(n)
    return count[np.minimum(t + reach + 1, n)] - count[np.maximum(t - reach, 0)] > 0
