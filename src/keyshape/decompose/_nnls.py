"""Exact bounded least squares for many frames that share one matrix (Gram form).

Every frame ``t`` solves the strictly convex quadratic programme

.. math::

    \\min_{w} \\tfrac12 w^T G w - c_t^T w
    \\quad\\text{s.t.}\\quad 0 \\le w \\le u, \\;\\; (\\mathbf 1^T w \\le 1),

which is ``min ‖A w − b_t‖²`` written with ``G = AᵀA`` and ``c_t = Aᵀ b_t`` (Bro & de Jong 1997
precompute the same cross products). ``G`` is shared by all frames:

1. *Block principal pivoting* (Júdice & Pires 1994; Kim & Park 2011), started from the signs of
   the unconstrained solution. Each sweep classifies every variable of a frame as at its
   lower bound, free, or at its upper bound, solves the reduced system by Cholesky and
   exchanges every variable that breaks a KKT condition; most frames need two or three
   sweeps. This loop is compiled and runs frame by frame
   (:func:`keyshape.decompose._kernels_nnls.block_pivoting`): the systems are at most ``K × K``.
2. Frames on which the block exchanges stop making progress (Kim & Park's trigger for their
   backup rule) finish, batched, with the *primal active-set method* (Lawson & Hanson 1974, ch. 23,
   generalised to two-sided bounds as in Nocedal & Wright 2006, Alg. 16.3): monotone in the
   objective, hence safe on ill-conditioned frames where rounding could make exchanges cycle.
3. The optional constraint ``Σ w ≤ 1`` is handled through its multiplier ``ν ≥ 0``: the box
   solution for ``c − ν·1`` has a sum that is piecewise linear and non-increasing in ``ν``, and
   a bracketed Newton iteration on it lands on the exact ``ν`` once it reaches the right piece.

References
----------
Lawson, C. L. & Hanson, R. J. (1974). *Solving Least Squares Problems*, ch. 23. Prentice-Hall.
Júdice, J. J. & Pires, F. M. (1994). A block principal pivoting algorithm for large-scale
strictly monotone linear complementarity problems. *Computers & OR* 21(5), 587–596.
Bro, R. & de Jong, S. (1997). A fast non-negativity-constrained least squares algorithm.
*J. Chemometrics* 11(5), 393–401.
Kim, J. & Park, H. (2011). Fast nonnegative matrix factorization: an active-set-like method and
comparisons. *SIAM J. Sci. Comput.* 33(6), 3261–3281.
Nocedal, J. & Wright, S. J. (2006). *Numerical Optimization*, 2nd ed., §16.5. Springer.
Golub, G. H. & Van Loan, C. F. (2013). *Matrix Computations*, 4th ed., §4.2. Johns Hopkins.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from ..exceptions import ConvergenceWarning
from ._reduced import FREE, KKT_TOL, LOWER, UPPER, free_solve

_RIDGE = 1e-10  # relative ridge added to a rank-deficient G (see Gram)
_TOL = KKT_TOL  # relative tolerance of the KKT tests


@dataclass(frozen=True, eq=False)
class Gram:
    """The matrix shared by every frame: ``G`` (made positive definite) and its inverse ``H``.

    Duplicate or zero keys, or fewer equations than keys, make ``G = AᵀA`` singular and the
    least-squares weights non-unique. Then a tiny ridge ``δ = 1e-10 · λ_max(G)`` (Tikhonov) is
    added: it picks the smallest-norm blend among equally good ones and changes the squared
    residual by about ``δ‖w‖²``. A well-conditioned ``G`` is used exactly as given.

    Attributes
    ----------
    G : (K, K) float, symmetric positive definite
    H : (K, K) float, ``G⁻¹``
    ridge : float, the ``δ`` added to the diagonal (0 when none)
    use_inverse : bool, whether ``H`` is accurate enough (``cond(G) ≤ 1e8``) for the
        Schur-complement solves of :func:`keyshape.decompose._reduced.free_solve`
    """

    G: np.ndarray
    H: np.ndarray
    ridge: float
    use_inverse: bool

    @classmethod
    def from_matrix(cls, G: np.ndarray) -> Gram:
        """Regularise (if needed) and invert a ``(K, K)`` positive semi-definite ``G``."""
        G = 0.5 * (G + G.T)
        eig = np.linalg.eigvalsh(G)
        top = max(float(eig[-1]), 0.0)
        ridge = 0.0 if eig[0] > 10 * _RIDGE * top else max(_RIDGE * top, 1e-150)
        G = G + ridge * np.eye(len(G))
        H = np.linalg.inv(G)  # K x K, positive definite (numpy: the solve needs no scipy import)
        cond = (top + ridge) / (eig[0] + ridge)
        return cls(G, 0.5 * (H + H.T), ridge, bool(cond <= 1e8))


# --------------------------------------------------------------------------- box constraints


def initial_state(X0: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """(n, K) int8 classification of an unconstrained guess ``X0``: below 0, inside, above ``u``."""
    return (X0 > upper).view(np.int8) - (X0 < 0).view(np.int8) + np.int8(FREE)


def _evaluate(gram, C, upper, state):
    """Subspace minimiser ``x`` (fixed variables at their bounds) and its gradient ``Gx − c``."""
    if not np.isfinite(upper).any():  # plain NNLS: every fixed variable is 0
        x = free_solve(gram, state == FREE, C)
        return x, x @ gram.G - C
    fixed = np.where(state == UPPER, upper, 0.0)  # (n, K): value of the non-free variables
    x = free_solve(gram, state == FREE, C - fixed @ gram.G) + fixed
    return x, x @ gram.G - C


def _tolerances(x, C, gram, upper):
    """(n, 1) primal and dual KKT tolerances, relative to each row's scale."""
    scale = 1.0 + np.abs(np.where(np.isfinite(upper), np.minimum(np.abs(x), upper), x)).max(
        axis=1, keepdims=True
    )
    g_scale = np.abs(C).max(axis=1, keepdims=True) + np.abs(gram.G).max() * scale
    return _TOL * scale, _TOL * g_scale


def _dual_violations(y, state, tol_y):
    """(n, K) float ≥ 0: how far each bound variable's multiplier has the wrong sign."""
    wrong = np.where(state == LOWER, -y, np.where(state == UPPER, y, 0.0))
    return np.where(wrong > tol_y, wrong, 0.0)


def box_solve(gram: Gram, C: np.ndarray, upper: np.ndarray, state: np.ndarray):
    """Exact solution of ``min ½wᵀGw − cᵀw`` s.t. ``0 ≤ w ≤ u`` for every row of ``C``.

    Parameters
    ----------
    gram : Gram, the shared ``G`` and ``G⁻¹``
    C : (n, K) float, finite
    upper : (K,) float, ``inf`` where unbounded
    state : (n, K) int8, initial guess (LOWER, FREE, UPPER) of each variable

    Returns
    -------
    X : (n, K) float, the solutions, within ``[0, u]``
    state : (n, K) int8, their classification
    """
    from . import _kernels_nnls  # numba (half a second to start): imported on the first solve

    state = np.array(state, dtype=np.int8, order="C")
    X = np.empty(C.shape)
    bounded = bool(np.isfinite(upper).any())
    stalled = np.flatnonzero(_kernels_nnls.block_pivoting(gram.G, np.ascontiguousarray(C), upper, bounded, state, X))
    if len(stalled):
        X[stalled], state[stalled] = _active_set(gram, C[stalled], upper, X[stalled], state[stalled])
    return np.clip(X, 0.0, upper), state


def _active_set(gram, C, upper, X, state, max_iter=None):
    """Primal active-set iterations from the feasible start ``clip(X)`` (Lawson & Hanson 1974).

    Each step moves to the minimiser of the current subspace, or as far towards it as the
    bounds allow, fixing the variable that blocks; at a subspace minimiser the bound variable
    with the most wrong-signed multiplier is released. A variable released on a rounding-level
    multiplier that blocks at once is not released again (Lawson & Hanson's safeguard).
    """
    n, k = C.shape
    X = np.where(state == LOWER, 0.0, np.where(state == UPPER, upper, np.clip(X, 0.0, upper)))
    state, frozen, released = state.copy(), np.zeros((n, k), bool), np.full(n, -1)
    todo = np.arange(n)
    for _ in range(max_iter or 5 * k + 20):
        s = state[todo]
        xs, y = _evaluate(gram, C[todo], upper, s)
        tol_x, tol_y = _tolerances(xs, C[todo], gram, upper)
        out_of_box = (s == FREE) & ((xs < -tol_x) | (xs > upper + tol_x))
        blocked = out_of_box.any(axis=1)
        X[todo[~blocked]] = np.clip(xs[~blocked], 0.0, upper)
        wrong = _dual_violations(y, s, tol_y) * ~frozen[todo]
        release = ~blocked & wrong.any(axis=1)
        _step_to_block(X, state, frozen, released, todo[blocked], xs[blocked], out_of_box[blocked], upper)
        rows, j = todo[release], np.argmax(wrong[release], axis=1)
        state[rows, j], released[rows] = FREE, j
        todo = todo[blocked | release]
        if not len(todo):
            return X, state
    warnings.warn(
        f"the active-set solver stopped after {max_iter or 5 * k + 20} steps with {len(todo)} "
        "frames unsolved; their weights are feasible but not optimal",
        ConvergenceWarning,
        stacklevel=4,
    )
    return X, state


def _step_to_block(X, state, frozen, released, rows, xs, out_of_box, upper):
    """Move ``X[rows]`` towards ``xs`` until the first free variable reaches a bound; fix it."""
    x = X[rows]
    # α_i = distance to the bound over distance to the target, for the variables leaving the box
    target = np.where(xs < 0, 0.0, upper)
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.where(out_of_box, (target - x) / (xs - x), np.inf)
    j = np.argmin(alpha, axis=1)
    at = (np.arange(len(rows)), j)
    a = np.clip(alpha[at], 0.0, 1.0)[:, None]
    x = np.clip(x + a * (xs - x), 0.0, upper)
    x[at] = target[at]  # the blocking variable lands exactly on its bound
    hit = (state[rows] == FREE) & ((x <= 0.0) | (x >= upper))
    X[rows] = x
    state[rows] = np.where(hit, np.where(x <= 0.0, LOWER, UPPER), state[rows])
    # Lawson & Hanson's safeguard: a just-released variable that blocks at once stays fixed
    again = (a[:, 0] <= _TOL) & (released[rows] == j)
    frozen[rows[again], j[again]] = True
    released[rows] = -1


# --------------------------------------------------------------------------- sum ≤ 1


def sum_newton(gram, C, upper, X, state, a, *, max_iter=200):
    """Enforce ``aᵀw ≤ 1`` (``a > 0``) on the rows whose box solution ``X`` breaks it.

    Safeguarded Newton iteration on ``φ(ν) = aᵀw(ν) − 1``, where ``w(ν)`` is the box
    solution for ``c − ν a``. ``φ`` is piecewise linear and non-increasing, its slope on the
    current piece is ``−a_Fᵀ G_FF⁻¹ a_F``, and the root lies in ``[0, max_i c_i / a_i]``.

    Parameters
    ----------
    gram : Gram
    C : (n, K) float
    upper : (K,) float
    X : (n, K) float, box solutions (``ν = 0``)
    state : (n, K) int8, their classification
    a : (K,) float > 0, the constraint's coefficients (all ones for ``Σ w ≤ 1``)

    Returns
    -------
    (n, K) float, solutions of the problem with the constraint
    """
    X = X.copy()
    todo = np.flatnonzero(X @ a > 1.0)
    lo, hi = np.zeros(len(todo)), np.maximum((C[todo] / a).max(axis=1), 0.0)
    nu, x, s = np.zeros(len(todo)), X[todo], state[todo]
    for _ in range(max_iter):
        phi = x @ a - 1.0
        done = np.abs(phi) <= 10 * _TOL
        X[todo[done]] = x[done]
        keep = ~done
        todo, lo, hi, nu, x, s, phi = (v[keep] for v in (todo, lo, hi, nu, x, s, phi))
        if not len(todo):
            break
        lo, hi = np.where(phi > 0, nu, lo), np.where(phi > 0, hi, nu)
        nu = _newton_step(gram, s, a, nu, phi, lo, hi)
        x, s = box_solve(gram, C[todo] - nu[:, None] * a, upper, s)
    else:
        X[todo] = x
    return X


def _newton_step(gram, state, a, nu, phi, lo, hi):
    """Newton step on the current linear piece, or bisection when it leaves ``(lo, hi)``."""
    free = state == FREE
    slope = free_solve(gram, free, free * a) @ a  # a_Fᵀ G_FF⁻¹ a_F
    with np.errstate(divide="ignore", invalid="ignore"):
        step = nu + phi / slope
    ok = (slope > 0) & (step > lo) & (step < hi)
    return np.where(ok, step, 0.5 * (lo + hi))


# --------------------------------------------------------------------------- entry point


def nnls_gram(G, C, upper=None, convex=False):
    """Exact per-row solution of ``min ½wᵀGw − cᵀw`` s.t. ``0 ≤ w ≤ u`` (and ``Σw ≤ 1``).

    The problem is first equilibrated, ``w = D v`` with ``D = diag(G)^{-1/2}`` (Jacobi
    scaling, Golub & Van Loan §3.5.2), so keys of very different magnitude cost no accuracy;
    the bounds become ``v ≤ u / d`` and the sum constraint ``dᵀv ≤ 1``.

    Parameters
    ----------
    G : (K, K) float, symmetric positive semi-definite
    C : (n, K) float; rows with a NaN give NaN rows
    upper : (K,) float or None, ``inf`` where unbounded
    convex : bool, add ``Σ w ≤ 1``

    Returns
    -------
    (n, K) float
    """
    n, k = C.shape
    upper = np.full(k, np.inf) if upper is None else upper
    valid = np.isfinite(C).all(axis=1)
    if not valid.all():  # NaN frames: solve the others, NaN rows out
        out = np.full((n, k), np.nan)
        out[valid] = nnls_gram(G, C[valid], upper, convex) if valid.any() else 0.0
        return out
    if not k or not n:
        return np.zeros((n, k))
    d = equilibration(G)
    gram, C, u = Gram.from_matrix(d[:, None] * G * d), C * d, upper / d
    V, state = box_solve(gram, C, u, initial_state(C @ gram.H, u))
    if gram.ridge:
        V = _undo_ridge(gram, C, u, V, state)
    if convex:
        V = sum_newton(gram, C, u, V, state, d)
    W = V * d
    if np.isfinite(upper).any():
        W = np.where(V >= u, upper, np.minimum(W, upper))  # a bound stays exact
    return cap_sum(W) if convex else W


def _undo_ridge(gram, C, upper, V, state, steps=3):
    """Iterated Tikhonov on each frame's free set: the ridge's bias shrinks as ``(δ/(λ+δ))^steps``.

    With the classification fixed, ``v_F ← v_F + (G_FF + δI)⁻¹ (c − G v)_F`` converges to the
    unregularised least-squares fit (Engl, Hanke & Neubauer 1996, §5.1).
    """
    free = state == FREE
    G0 = gram.G - gram.ridge * np.eye(len(gram.G))
    for _ in range(steps):
        V = V + free_solve(gram, free, C - V @ G0)
    return np.clip(V, 0.0, upper)


def cap_sum(W: np.ndarray) -> np.ndarray:
    """Rows of ``W ≥ 0`` rescaled, where needed, until ``Σ w ≤ 1`` holds in floating point."""
    W = W.copy()
    over = np.flatnonzero(W.sum(axis=1) > 1.0)
    W[over] /= W[over].sum(axis=1, keepdims=True)
    while len(over := np.flatnonzero(W.sum(axis=1) > 1.0)):
        W[over] *= 1.0 - np.finfo(float).eps
    return W


def equilibration(G: np.ndarray) -> np.ndarray:
    """(K,) float: Jacobi scaling ``1/√G_ii`` (1 for an all-zero key)."""
    diag = np.diag(G)
    return 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
