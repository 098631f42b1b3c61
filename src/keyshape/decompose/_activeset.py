"""Active-set finish of the spacetime QP (:mod:`keyshape.decompose._spacetime`), for where ADMM stalls.

:func:`face_solve` minimises ``F`` exactly on a face of the constraint set (bound variables
fixed, active ``Σw = 1`` rows enforced) with one banded Cholesky factorisation;
:func:`exchange` is the primal–dual active-set update (Hintermüller, Ito & Kunisch 2003),
:func:`newton` its loop, and :func:`active_set` the monotone primal active-set method
(Nocedal & Wright 2006, Alg. 16.3) that finishes where the exchanges cycle.

:func:`local_finish` runs them on a few frames only. Where ADMM stalls it has stalled
locally: across a long gap only the smoothness term holds the weights, and ADMM's slow modes
live there, while on frames with data its error falls by a steady factor per frame of
distance from the gap (the decay of the Green's function of ``λ I + μ LᵀL``). The frames whose
optimality residual stands out, widened by a margin that this decay places, and whole gaps
they touch, form windows; with every other frame fixed at ADMM's values the windows decouple
from the rest (the smoothness couples a frame to two on either side) and from each other,
and one small QP (all windows stacked) is solved exactly. The certificate of the whole take
then says whether that was enough.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _kernels, _kernels_face
from ._reduced import FREE, LOWER, UPPER
from ._sequence import Best, EigenSolver, Sequence, hessian_mul, multipliers, objective, project

_HOT = 1e-3  # a frame's residual above this fraction of the largest marks it for a window
_REACH = 1e-6  # a window reaches as far as ADMM's error takes to fall by this factor
_KKT_TOL = 1e-11  # a dimensionless KKT violation below this is none
_MAX_SHARE = 0.5  # windows over more of the take than this: a face of the whole take is as cheap

_LOCAL_SHARE = 0.01  # once the exchanges touch this share of the frames, windows finish (local_finish)
_ALM_STEPS = 30  # method-of-multipliers steps per Newton step for active Σw = 1 rows


def classify(seq: Sequence, Z: np.ndarray):
    """Variable states (LOWER / FREE / UPPER) and active-sum rows of a feasible ``Z``."""
    state = np.where(Z <= 0.0, LOWER, np.where(Z >= seq.upper, UPPER, FREE)).astype(np.int8)
    sums = (Z.sum(axis=1) >= 1.0 - 1e-12) if seq.convex else np.zeros(len(Z), bool)
    return state, sums


class Workspace:
    """Memory the face factorisations of one solve reuse: a fresh factor of a long take is
    tens of megabytes, and the first touch of new pages costs as much as filling them."""

    def __init__(self):
        self._flat = np.empty(0)

    def packed(self, size: int) -> np.ndarray:
        """An uninitialised ``(size,)`` array, a view of the workspace's memory."""
        if self._flat.size < size:
            self._flat = np.empty(int(1.1 * size) + 1)
        return self._flat[:size]


@dataclass(frozen=True, eq=False)
class FaceFactor:
    """Cholesky factor of a face system over its free variables (:mod:`keyshape.decompose._kernels_face`).

    ``index (T, K)`` numbers the free variables frame-major (−1 for fixed ones); column ``j``
    of the factor holds ``packed[offset[j] : offset[j] + reach[j] + 1]``, its diagonal first.
    """

    index: np.ndarray
    reach: np.ndarray
    offset: np.ndarray
    packed: np.ndarray
    n_free: int

    def solve(self, x: np.ndarray) -> None:
        """``x ← (L Lᵀ)⁻¹ x`` in place, ``x (n_free,)`` float, C order."""
        _kernels_face.solve_face(self.n_free, self.reach, self.offset, self.packed, x)


def face_factor(seq: Sequence, free: np.ndarray, sums: np.ndarray, rho_s: float,
                work: Workspace | None = None) -> FaceFactor:
    """The factor of ``P_FF + ρ_s Σ_{active t} 1 1ᵀ`` over the free variables ``free (T, K)``
    (in ``work``'s memory when given: valid until its next use)."""
    index = np.empty(free.shape, dtype=np.int64)
    reach = np.empty(free.size, dtype=np.int64)
    offset = np.empty(free.size, dtype=np.int64)
    n_free, size = _kernels_face.number_free(free, index, reach, offset)
    packed = (work or Workspace()).packed(size)
    _kernels_face.fill_face(seq.G, seq.delta, float(seq.mu), *seq.gram, index, sums, float(rho_s), reach, offset,
                            packed)
    if not _kernels_face.factor_face(n_free, reach, offset, packed):
        raise np.linalg.LinAlgError("banded Cholesky failed on the face: not positive definite")
    return FaceFactor(index, reach, offset, packed, n_free)


def face_solve(seq: Sequence, state: np.ndarray, sums: np.ndarray, work: Workspace | None = None):
    """Minimiser ``X (T, K)`` of ``F`` on a face, and the multipliers ``ν (T,)`` of its sums.

    Bound variables sit at their bounds; free ones solve ``P_FF x_F = c_F − P_FN x_N``, with
    ``Σ_t w_t = 1`` on the ``sums`` rows enforced by the method of multipliers (Hestenes 1969)
    on one banded Cholesky factorisation of ``P_FF + ρ_s Σ 1 1ᵀ``.
    """
    free = state == FREE
    fixed = np.where(state == UPPER, np.where(np.isfinite(seq.upper), seq.upper, 0.0), 0.0)
    # ρ_s ≈ 10 λ_max(P): the multiplier error then shrinks ≥ 10-fold per step
    rho_s = 10.0 * (float(np.abs(seq.G).sum(axis=1).max()) + 16.0 * seq.mu) if sums.any() else 0.0
    factor = face_factor(seq, free, sums, rho_s, work)
    rhs = seq.C - hessian_mul(seq, fixed) if fixed.any() else seq.C
    room = 1.0 - fixed.sum(axis=1)  # what the free variables of an active row must add up to
    nu = np.zeros(len(state))
    X = fixed.copy()
    for _ in range(_ALM_STEPS if sums.any() else 1):
        x = np.ascontiguousarray((rhs - np.where(sums, nu - rho_s * room, 0.0)[:, None])[free])
        factor.solve(x)
        X[free] = x
        excess = np.where(sums, X.sum(axis=1) - fixed.sum(axis=1) - room, 0.0) if sums.any() else 0.0
        nu += rho_s * excess
        if np.abs(excess).max() <= 1e-13:
            break
    return X, nu


def newton(seq: Sequence, best: Best, *, rtol: float, max_newton: int, start: np.ndarray | None = None) -> None:
    """Primal–dual active-set steps from the active set of ``start`` (default ``best.Z``) until
    ``best`` certifies ``rtol``.

    Each step lands on the exact minimiser of its face. While many variables still change
    side the step is not certified (the bound would be poor, and it costs a solve); once few
    do (:data:`_LOCAL_SHARE` of the frames), the remaining exchanges are local and
    :func:`local_finish` settles them on windows around those frames. Should the exchanges
    stop shrinking they are damped (:func:`exchange`), and the monotone :func:`active_set`
    finishes.
    """
    state, sums = classify(seq, best.Z if start is None else start)
    history, limit = [], None
    lam = np.linalg.eigvalsh(seq.G)
    work = Workspace()
    for step in range(max_newton):
        if best.gap <= rtol:
            break
        X, nu = face_solve(seq, state, sums, work)
        PX = hessian_mul(seq, X)
        size, rows = violations(seq, state, sums, X, nu, PX)
        new_state, new_sums, changed = _move(state, sums, X, size, rows, limit)
        frames = int(((size > _KKT_TOL).any(axis=1) | (rows > _KKT_TOL)).sum())
        few = frames <= _LOCAL_SHARE * len(X)
        if few or limit is not None or step == max_newton - 1:
            best.offer(project(X, seq.upper, seq.convex), multipliers(seq, X, state, np.where(sums, nu, 0.0), PZ=PX))
            if best.gap <= rtol:
                break
            if few and changed and limit is None:  # the rest is local: windows around the violations
                mask = _dilate((size > _KKT_TOL).any(axis=1) | (rows > _KKT_TOL), decay_margin(seq, lam))
                mask |= np.roll(mask, 1) & np.roll(mask, -1)  # no 1-frame holes between windows
                Z = project(X, seq.upper, seq.convex)
                best.offer(solve_windows(seq, Z, mask, new_state, new_sums, max_newton=max_newton))
                if best.gap <= rtol:
                    break
        state, sums = new_state, new_sums
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


def exchange(seq: Sequence, state, sums, X, nu, limit=None):
    """Primal–dual active-set update: the new ``(state, sums)`` and how many changed.

    Every variable that breaks its KKT condition on the current face changes side (free and
    out of bounds → bound; bound with a wrong-signed multiplier → free); likewise the sum
    rows (over-full → active; negative multiplier → inactive). With ``limit``, only that many
    of the largest (dimensionless) violations change, which damps the cycling a plain
    primal–dual active-set step can fall into on degenerate problems.
    """
    return _move(state, sums, X, *violations(seq, state, sums, X, nu), limit)


def violations(seq: Sequence, state, sums, X, nu, PX=None):
    """Dimensionless KKT violations on a face: ``(T, K)`` of the variables, ``(T,)`` of the sum
    rows; positive where the constraint changes side under :func:`exchange` (``PX = P X`` if known)."""
    grad = (hessian_mul(seq, X) if PX is None else PX) - seq.C + np.where(sums, nu, 0.0)[:, None]  # ∇(F/2) + ν·1
    x_scale = 1.0 + np.abs(X).max()
    g_scale = (np.abs(seq.C).max() + np.abs(seq.G).max() + seq.mu) * x_scale
    primal = np.maximum(-X, X - seq.upper) / x_scale  # > 0: a free variable out of its box
    dual = np.where(state == LOWER, -grad, grad) / g_scale  # > 0: a bound one pulled inside
    size = np.where(state == FREE, primal, dual)
    rows = np.full(len(X), -np.inf)
    if seq.convex:
        rows = np.where(sums, -nu / g_scale, (X.sum(axis=1) - 1.0) / x_scale)
    return size, rows


def _move(state, sums, X, size, rows, limit):
    if limit is not None:
        cut = np.sort(np.concatenate([size.ravel(), rows]))[-limit]
        size, rows = np.where(size >= cut, size, 0.0), np.where(rows >= cut, rows, 0.0)
    move, flip = size > _KKT_TOL, rows > _KKT_TOL
    to_bound = np.where(X < 0.0, LOWER, UPPER)
    new = np.where(move, np.where(state == FREE, to_bound, FREE), state).astype(np.int8)
    return new, sums ^ flip, int(move.sum() + flip.sum())


def active_set(seq: Sequence, best: Best, *, max_steps: int) -> None:
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


# --------------------------------------------------------------------------- windows


@dataclass(frozen=True, eq=False)
class Window(Sequence):
    """Some frames of a :class:`Sequence` (``rows``, in runs) with all the others fixed.

    ``C`` holds ``δ_t c_t − μ (LᵀL Z_out)_t``, the pull of the fixed frames through the
    smoothness; ``diagonals`` are the rows' block of ``LᵀL`` (couplings to frames outside
    removed), which :attr:`gram` returns instead of the second-difference Gram of ``T`` frames.
    ``const`` makes :func:`keyshape.decompose._sequence.objective` the whole take's ``F``.
    """

    diagonals: tuple = ()
    rows: np.ndarray | None = None

    gram = property(lambda self: self.diagonals)


def local_finish(seq: Sequence, best: Best, *, rtol: float, max_newton: int) -> None:
    """Solve the windows around ``best.Z``'s unconverged frames exactly; offer the result to ``best``.

    Primal–dual active-set steps (:func:`exchange`) on all windows at once (:func:`solve_windows`),
    from the active set of ``best.Z``.
    """
    mask = window_frames(seq, best.Z)
    if mask.any():
        best.offer(solve_windows(seq, best.Z, mask, *classify(seq, best.Z), max_newton=max_newton))


def solve_windows(seq: Sequence, Z: np.ndarray, mask: np.ndarray, state: np.ndarray, sums: np.ndarray, *,
                  max_newton: int) -> np.ndarray:
    """``Z (T, K)`` with the frames of ``mask`` re-solved exactly, the others fixed, from the
    active set ``(state, sums)`` there; feasible.

    Primal–dual active-set steps on all windows (runs of ``mask``) at once; a window whose
    active set no longer changes sits at its exact minimiser and leaves, so later steps cost
    only the windows still moving. When the exchanges stop shrinking they are damped, down to
    the single largest violation per step (cheap on a few small windows, and it breaks the
    two-cycles seen on these problems); windows still moving after ``max_newton`` steps are
    finished by :func:`active_set`.
    """
    whole = restrict(seq, Z, mask)
    run = np.cumsum(np.append(True, np.diff(whole.rows) > 1)) - 1  # (rows,) window of each row
    X = np.array(Z[whole.rows])
    state, sums = state[whole.rows].copy(), sums[whole.rows].copy()
    moving, history, limit = np.ones(len(X), bool), [], None
    for _ in range(max_newton):
        sub = select(whole, moving)
        X[moving], nu = face_solve(sub, state[moving], sums[moving])
        size, rows = violations(sub, state[moving], sums[moving], X[moving], nu)
        wrong = (size > _KKT_TOL).any(axis=1) | (rows > _KKT_TOL)
        state[moving], sums[moving], changed = _move(state[moving], sums[moving], X[moving], size, rows, limit)
        moving &= np.isin(run, run[moving][wrong])  # a window without violations is at its minimiser
        history.append(changed)
        if not moving.any():
            break
        if len(history) > 3 and changed >= history[-4]:  # no progress: damp the exchanges
            limit = max(1, (limit or changed) // 2)
            history.clear()
    Z = Z.copy()
    Z[whole.rows] = project(X, seq.upper, seq.convex)
    if moving.any():  # cycling windows: the monotone method, from their best point so far
        sub = restrict(seq, Z, _frames(len(Z), whole.rows[moving]))
        local = Best(sub, EigenSolver(sub, 0.0), np.ascontiguousarray(Z[sub.rows]))
        active_set(sub, local, max_steps=int(np.clip(2e6 // sub.C.size, 20, 200)))
        Z[sub.rows] = local.Z
    return Z


def select(window: Window, keep: np.ndarray) -> Window:
    """The rows ``keep`` (whole windows) of ``window``: still decoupled, their ``const`` dropped."""
    d0, d1, d2 = window.diagonals
    return Window(window.G, np.ascontiguousarray(window.C[keep]), window.delta[keep], window.mu, window.upper,
                  window.convex, 0.0, (d0[keep], d1[keep], d2[keep]), window.rows[keep])


def _frames(n_frames: int, rows: np.ndarray) -> np.ndarray:
    mask = np.zeros(n_frames, bool)
    mask[rows] = True
    return mask


def window_frames(seq: Sequence, Z: np.ndarray) -> np.ndarray:
    """(T,) bool: the frames of the windows around ``Z``'s largest optimality residuals; none
    where ADMM has not converged outside them (windows would not help) or where they would
    cover more than :data:`_MAX_SHARE` of the take (a face of the whole take costs as much).

    The residual of frame ``t`` is ``‖z_t − Π_C(z_t + g_t / L_t)‖`` (``g = c − PZ``,
    ``L_t = δ_t λ_max + 16μ`` its curvature): zero exactly at the optimum.
    """
    lam = np.linalg.eigvalsh(seq.G)
    g = seq.C - hessian_mul(seq, Z)
    step = g / (seq.delta * lam[-1] + 16.0 * seq.mu)[:, None]
    residual = np.linalg.norm(Z - project(Z + step, seq.upper, seq.convex), axis=1)
    if not residual.max() > 0.0:
        return np.zeros(len(Z), bool)
    hot = _dilate(residual > _HOT * residual.max(), 1)
    gap = seq.delta == 0.0
    runs = np.cumsum(np.diff(np.concatenate([[False], gap])) > 0) * gap  # gap runs numbered 1, 2, ...
    hot |= np.isin(runs, runs[hot & gap]) & gap  # a window that reaches a gap spans it
    mask = _dilate(hot, decay_margin(seq, lam))
    mask |= np.roll(mask, 1) & np.roll(mask, -1)  # no 1-frame holes: two windows would share a row of L
    if mask.mean() > _MAX_SHARE or residual[~mask].max() > _REACH * residual.max():
        return np.zeros(len(Z), bool)
    return mask


def decay_margin(seq: Sequence, lam: np.ndarray) -> int:
    """Frames over which the slowest mode with data, ``λ_min I + μ LᵀL``, decays by :data:`_REACH`.

    Its Green's function falls by ``|z|`` per frame, ``z`` the root inside the unit circle of
    ``(z − 2 + 1/z)² = −λ_min / μ``.
    """
    w = 2.0 + 1j * np.sqrt(max(lam[0], 0.0) / seq.mu)
    z = abs((w - np.sqrt(w * w - 4.0)) / 2.0)
    z = min(z, 1.0 / z) if z > 0.0 else 0.0
    if not 0.0 < z < 1.0:
        return len(seq.delta)
    return int(np.clip(np.ceil(np.log(_REACH) / np.log(z)) + 2, 4, len(seq.delta)))


def _dilate(mask: np.ndarray, reach: int) -> np.ndarray:
    """Frames within ``reach`` of a True frame."""
    count = np.concatenate([[0], np.cumsum(mask)])
    n = len(mask)
    t = np.arange(n)
    return count[np.minimum(t + reach + 1, n)] - count[np.maximum(t - reach, 0)] > 0


def restrict(seq: Sequence, Z: np.ndarray, mask: np.ndarray) -> Window:
    """The QP on the frames of ``mask`` (runs at least two frames apart) with the others at ``Z``."""
    rows = np.flatnonzero(mask)
    d0, d1, d2 = seq.gram
    outside = np.ascontiguousarray(np.where(mask[:, None], 0.0, Z))
    pull = np.zeros_like(outside)  # μ (LᵀL Z_out): the fixed frames' pull through the smoothness
    _kernels.add_smoothness(pull, outside, np.zeros(len(Z)), float(seq.mu), d0, d1, d2)
    n = len(rows)
    nxt = np.concatenate([rows[1:], [-1]])[:n] == rows + 1  # the next row is the next frame
    nxt2 = np.concatenate([rows[2:], [-1, -1]])[:n] == rows + 2
    diagonals = (d0[rows], np.where(nxt, d1[rows], 0.0), np.where(nxt2, d2[rows], 0.0))
    C = np.ascontiguousarray(seq.C[rows] - pull[rows])
    sub = Window(seq.G, C, seq.delta[rows], seq.mu, seq.upper, seq.convex, 0.0, diagonals, rows)
    const = objective(seq, Z) - objective(sub, Z[rows])
    return Window(seq.G, C, seq.delta[rows], seq.mu, seq.upper, seq.convex, const, diagonals, rows)
