"""The smoothed solve's parts: compiled kernels against independent references, the ADMM
penalties, the active-set finish that ADMM hands over to when it stalls, and its local form
on windows around long gaps."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import sparse
from scipy.linalg import solveh_banded

from keyshape.decompose import _activeset, _kernels, _sequence, _spacetime

# --------------------------------------------------------------------------- helpers


def sparse_hessian(seq):
    """``P = blockdiag(δ_t G) + μ LᵀL ⊗ I_K`` built from scratch, ``(T·K, T·K)``, frame-major."""
    T, K = seq.C.shape
    L = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(T - 2, T))
    return sparse.csc_matrix(sparse.kron(sparse.diags(seq.delta), seq.G) + seq.mu * sparse.kron(L.T @ L, sparse.eye(K)))


def dense_hessian(seq):
    return sparse_hessian(seq).toarray()


def sequence(seed, T=60, K=4, gaps=(), upper=1.0, convex=False, mu=0.5, with_sq=False):
    """A small region problem with known smooth weights, noise and optional gaps (and with
    ``with_sq`` its ``‖b_t‖² (T,)`` too)."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((3 * K, K))
    W = np.clip(np.cumsum(rng.standard_normal((T, K)) * 0.15, axis=0) + 0.3, 0.0, None)
    B = W @ A.T + 0.2 * rng.standard_normal((T, 3 * K))
    delta = np.ones(T)
    for a, b in gaps:
        delta[a:b] = 0.0
    G = A.T @ A
    C = np.ascontiguousarray((B @ A) * delta[:, None])
    const = float(np.sum(B[delta > 0] ** 2))
    seq = _sequence.Sequence(G, C, delta, mu * np.trace(G) / K, np.full(K, upper), convex, const)
    return (seq, np.sum(B**2, axis=1)) if with_sq else seq


def project_by_bisection(v, u):
    """Projection of one row on ``{0 ≤ z ≤ u, Σ z ≤ 1}`` by bisection on the shift ``τ``."""
    z = np.clip(v, 0.0, u)
    if z.sum() <= 1.0:
        return z
    lo, hi = 0.0, float(np.max(v))
    for _ in range(200):
        tau = 0.5 * (lo + hi)
        lo, hi = (tau, hi) if np.clip(v - tau, 0.0, u).sum() > 1.0 else (lo, tau)
    return np.clip(v - 0.5 * (lo + hi), 0.0, u)


# --------------------------------------------------------------------------- kernels


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), T=st.integers(1, 40), K=st.integers(1, 6))
def test_pentadiagonal_solve_matches_scipy(seed, T, K):
    rng = np.random.default_rng(seed)
    a1, a2 = rng.uniform(-1, 1, T), rng.uniform(-1, 1, T)
    a0 = rng.uniform(0.1, 2.0, (T, K)) + 4.0  # diagonally dominant: positive definite
    Y = rng.standard_normal((T, K))
    X = Y.copy()
    factor = tuple(np.empty_like(a0) for _ in range(3))
    assert _kernels.penta_factor(a0, a1, a2, *factor)
    _kernels.penta_solve(*factor, X)
    for k in range(K):
        ab = np.zeros((3, T))
        ab[0], ab[1, : T - 1], ab[2, : T - 2] = a0[:, k], a1[: T - 1], a2[: T - 2]
        np.testing.assert_allclose(X[:, k], solveh_banded(ab, Y[:, k], lower=True), rtol=1e-10, atol=1e-12)


def test_pentadiagonal_factor_refuses_an_indefinite_matrix():
    a0 = np.array([[1.0], [-1.0], [1.0]])
    assert not _kernels.penta_factor(a0, np.zeros(3), np.zeros(3), *(np.empty_like(a0) for _ in range(3)))
    seq = sequence(0, T=10, K=2)
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        _sequence.EigenSolver(seq, -1e6)


def test_eigen_solver_inverts_the_shifted_hessian():
    seq = sequence(1, T=30, K=3, gaps=[(10, 14)])
    rho = np.random.default_rng(1).uniform(0.5, 2.0, 30)
    R = np.random.default_rng(2).standard_normal((30, 3))
    X = _sequence.EigenSolver(seq, rho).solve(R)
    P = dense_hessian(seq) + np.diag(np.repeat(rho, 3))
    np.testing.assert_allclose(X.ravel(), np.linalg.solve(P, R.ravel()), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(_sequence.hessian_mul(seq, X).ravel(), dense_hessian(seq) @ X.ravel(), atol=1e-10)


@pytest.mark.parametrize("seed", range(6))
def test_face_factorisation_solves_the_free_block(seed):
    rng = np.random.default_rng(seed)
    seq = sequence(seed, T=25, K=4, gaps=[(8, 11)], convex=True)
    free = rng.random((25, 4)) < (0.6 if seed % 2 else 0.25)  # sparse faces too: frames with nothing free
    sums = rng.random(25) < 0.3
    rho_s = 3.0
    factor = _activeset.face_factor(seq, free, sums, rho_s)
    index, reach = factor.index, factor.reach
    # the factor is of P + ρ_s Σ_active 1 1ᵀ on the free block, numbered frame-major
    M = dense_hessian(seq) + rho_s * np.kron(np.diag(sums.astype(float)), np.ones((4, 4)))
    f = free.ravel()
    np.testing.assert_array_equal(index.ravel()[f], np.arange(f.sum()))
    assert (index.ravel()[~f] == -1).all()
    expected = M[np.ix_(f, f)]
    L = np.zeros_like(expected)
    for j in range(len(L)):
        L[j : j + reach[j] + 1, j] = factor.packed[factor.offset[j] : factor.offset[j] + reach[j] + 1]
    np.testing.assert_allclose(L @ L.T, expected, atol=1e-10)
    np.testing.assert_allclose(L, np.linalg.cholesky(expected), atol=1e-10)  # nothing lost outside the reach
    b = rng.standard_normal(len(expected))
    x = b.copy()
    factor.solve(x)
    np.testing.assert_allclose(x, np.linalg.solve(expected, b), rtol=1e-9, atol=1e-11)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), K=st.integers(1, 9), convex=st.booleans())
def test_projection_matches_bisection(seed, K, convex):
    rng = np.random.default_rng(seed)
    V = rng.uniform(-0.5, 1.2, (20, K))
    upper = np.where(rng.random(K) < 0.3, np.inf, rng.uniform(0.1, 1.0, K))
    Z = _sequence.project(V, upper, convex)
    assert (Z >= 0).all() and (Z <= upper).all()
    if convex:
        assert (Z.sum(axis=1) <= 1.0 + 1e-12).all()
        ref = np.array([project_by_bisection(v, upper) for v in V])
    else:
        ref = np.clip(V, 0.0, upper)
    np.testing.assert_allclose(Z, ref, atol=1e-9)


def test_admm_step_is_the_relaxed_projected_update():
    rng = np.random.default_rng(3)
    W, Z, U, C = (rng.standard_normal((15, 3)) for _ in range(4))
    Z = np.clip(Z, 0, 1)
    rho, upper, alpha = rng.uniform(0.5, 2, 15), np.ones(3), 1.6
    hat = alpha * W + (1 - alpha) * Z
    Z_new = np.clip(hat + U, 0, 1)
    U_new = U + hat - Z_new
    dz, primal = _kernels.admm_step(W, Z0 := Z.copy(), U0 := U.copy(), C, rho, upper, alpha, False)
    np.testing.assert_allclose(Z0, Z_new)
    np.testing.assert_allclose(U0, U_new)
    np.testing.assert_allclose(W, C + rho[:, None] * (Z_new - U_new))  # the next right-hand side
    assert dz == pytest.approx(np.sum((Z_new - Z) ** 2))
    assert primal == pytest.approx(np.sum((hat - Z_new) ** 2))


def test_point_multipliers_follow_the_active_constraints():
    seq = sequence(4, T=20, K=3, convex=True, upper=0.6)
    Z = np.zeros((20, 3))
    Z[:, 0], Z[:5, 1] = 0.5, 0.5  # rows 0–4 full (Σ = 1)
    Z[5:10, 0], Z[5:10, 1] = 0.0, 0.6  # rows 5–9: key 1 at its bound, the row not full
    g = np.random.default_rng(4).standard_normal((20, 3))
    Y = np.full_like(g, np.nan)
    _kernels.point_multipliers(g, Z, seq.upper, True, Y)
    nu = np.maximum(g[:5, :2].mean(axis=1), 0.0)  # full rows: mean of g over the free entries
    np.testing.assert_allclose(Y[:5, :2], np.broadcast_to(nu[:, None], (5, 2)))
    np.testing.assert_allclose(Y[:5, 2], nu + np.minimum(g[:5, 2] - nu, 0.0))
    np.testing.assert_allclose(Y[5:10, 1], np.maximum(g[5:10, 1], 0.0))
    np.testing.assert_allclose(Y[5:10, 2], np.minimum(g[5:10, 2], 0.0))
    assert (Y[10:, 0] == 0).all()


# --------------------------------------------------------------------------- penalties and phases


def test_gap_penalty_follows_the_gap_length():
    seq = sequence(5, T=60, K=3, gaps=[(10, 13), (30, 45)])
    lam = np.linalg.eigvalsh(seq.G)
    rho = _spacetime.admm_rho(seq, lam)
    data = np.sqrt(lam[0] * (lam[-1] + 4 * seq.mu))
    assert rho[0] == pytest.approx(data) and rho[59] == pytest.approx(data)
    assert rho[11] == pytest.approx(min(data, 4 * seq.mu * (np.pi / 6) ** 2))
    assert rho[40] == pytest.approx(min(data, 4 * seq.mu * (np.pi / 18) ** 2))
    assert rho[40] < rho[11]


@pytest.mark.parametrize(("convex", "gaps"), [(False, ()), (True, [(20, 32)]), (False, [(5, 9), (40, 70)])])
def test_active_set_finish_reaches_the_certified_optimum(convex, gaps, monkeypatch):
    seq = sequence(6, T=120, K=4, gaps=gaps, convex=convex, upper=0.6)
    W_admm, gap_admm = _spacetime.solve_sequence(seq, rtol=1e-9)
    # no ADMM beyond the first 20 iterations and a target ADMM cannot reach in them:
    # the primal–dual active-set steps must finish
    faces = []
    face_solve = _activeset.face_solve
    monkeypatch.setattr(_activeset, "face_solve", lambda *a: faces.append(1) or face_solve(*a))
    W_newton, gap_newton = _spacetime.solve_sequence(seq, rtol=1e-12, max_admm=20)
    assert faces, "the active-set steps did not run"
    assert gap_admm <= 1e-9 and gap_newton <= 1e-12
    F = _sequence.objective
    assert abs(F(seq, W_newton) - F(seq, W_admm)) <= 2e-9 * F(seq, W_admm)
    # and the monotone active-set method alone, from zero
    best = _sequence.Best(seq, _sequence.EigenSolver(seq, 0.0), np.zeros(seq.C.shape))
    _activeset.active_set(seq, best, max_steps=2000)
    assert best.gap <= 1e-9
    assert abs(best.F - F(seq, W_admm)) <= 2e-9 * F(seq, W_admm)


def test_dual_bound_never_exceeds_the_objective():
    seq = sequence(7, T=80, K=3, gaps=[(30, 40)], convex=True)
    W, _ = _spacetime.solve_sequence(seq)
    exact = _sequence.EigenSolver(seq, 0.0)
    rng = np.random.default_rng(7)
    for _ in range(5):  # any multipliers give a lower bound on F* (weak duality)
        Y = _sequence.multipliers(seq, _sequence.project(W + 0.1 * rng.standard_normal(W.shape), seq.upper, True))
        assert _sequence.lower_bound(seq, exact, Y) <= _sequence.objective(seq, W) * (1 + 1e-12)


# --------------------------------------------------------------------------- windows


def long_gap_sequence(seed, T=1400, K=5, gap=60, every=700, convex=False, mu=0.1, with_sq=False):
    """The benchmark's weak spot in small: a ``gap``-frame gap every ``every`` frames."""
    gaps = [(a, a + gap) for a in range(every // 2, T - gap - 5, every)]
    return sequence(seed, T=T, K=K, gaps=gaps, convex=convex, mu=mu, upper=1.0, with_sq=with_sq)


def test_window_is_the_restricted_qp():
    seq = sequence(8, T=50, K=3, gaps=[(12, 20)], convex=True)
    rng = np.random.default_rng(8)
    Z = _sequence.project(rng.uniform(0, 0.5, (50, 3)), seq.upper, True)
    mask = np.zeros(50, bool)
    mask[[0, 1, 2, 33]] = mask[10:23] = mask[25:30] = mask[48:] = True  # runs two or more frames apart
    sub = _activeset.restrict(seq, Z, mask)
    np.testing.assert_array_equal(sub.rows, np.flatnonzero(mask))
    P = dense_hessian(seq)
    f = np.repeat(mask, 3)
    for _ in range(3):  # F on the windows, the other frames fixed, is the whole take's F
        X = rng.uniform(0, 0.5, (mask.sum(), 3))
        full = Z.copy()
        full[mask] = X
        assert _sequence.objective(sub, X) == pytest.approx(_sequence.objective(seq, full), rel=1e-12)
        np.testing.assert_allclose(_sequence.hessian_mul(sub, X).ravel(), P[np.ix_(f, f)] @ X.ravel(), atol=1e-10)
    # whole windows taken out of it stay the restricted QP (of those frames)
    keep = sub.rows >= 10
    part = _activeset.select(sub, keep)
    X = rng.uniform(0, 0.5, (keep.sum(), 3))
    g = np.repeat(_activeset._frames(50, part.rows), 3)
    np.testing.assert_allclose(_sequence.hessian_mul(part, X).ravel(), P[np.ix_(g, g)] @ X.ravel(), atol=1e-10)


def test_windows_cover_the_long_gaps_and_little_else():
    seq = long_gap_sequence(12)
    lam = np.linalg.eigvalsh(seq.G)
    rho = _spacetime.admm_rho(seq, lam)
    exact = _sequence.EigenSolver(seq, 0.0)
    start = _sequence.project(exact.solve(seq.C), seq.upper, False)
    Z, _ = _spacetime.admm(seq, _sequence.EigenSolver(seq, rho), rho, start, np.zeros(seq.C.shape), 90)
    mask = _activeset.window_frames(seq, Z)
    assert mask[seq.delta == 0].all()
    margin = _activeset.decay_margin(seq, lam)
    assert 4 <= margin < 100
    assert mask.mean() < 0.2
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    assert (edges[2::2] - edges[1:-1:2] >= 2).all()  # windows two or more frames apart: decoupled
    # where ADMM has not converged away from the gaps, windows would not do: none
    Z, _ = _spacetime.admm(seq, _sequence.EigenSolver(seq, rho), rho, start, np.zeros(seq.C.shape), 2)
    assert not _activeset.window_frames(seq, Z).any()


@pytest.mark.parametrize(("seed", "mu"), [(11, 0.1), (12, 0.3), (13, 1.0)])
def test_long_gaps_finish_in_windows_at_the_global_optimum(seed, mu, monkeypatch):
    seq = long_gap_sequence(seed, mu=mu)
    windows = []
    window_frames = _activeset.window_frames
    monkeypatch.setattr(_activeset, "window_frames", lambda *a: windows.append(window_frames(*a)) or windows[-1])
    W, gap = _spacetime.solve_sequence(seq, rtol=1e-9)
    assert windows and windows[0].any(), "the windows were not solved"
    assert gap <= 1e-9
    monkeypatch.setattr(_spacetime, "local_finish", lambda *a, **k: None)  # the global active set only
    W_global, gap_global = _spacetime.solve_sequence(seq, rtol=1e-9)
    assert gap_global <= 1e-9
    F = _sequence.objective
    assert abs(F(seq, W) - F(seq, W_global)) <= 2e-9 * F(seq, W_global)


def test_long_gaps_match_clarabel():
    qpsolvers = pytest.importorskip("qpsolvers")
    seq = long_gap_sequence(14)
    W, gap = _spacetime.solve_sequence(seq)
    assert gap <= 1e-7
    T, K = seq.C.shape
    x = qpsolvers.solve_qp(2 * sparse_hessian(seq), -2 * seq.C.ravel(), lb=np.zeros(T * K), ub=np.ones(T * K),
                           solver="clarabel", tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
    F = _sequence.objective
    ours, theirs = F(seq, W), F(seq, x.reshape(T, K))
    assert ours <= theirs * (1 + 1e-7)
    assert theirs <= ours * (1 + 1e-6)  # Clarabel's own accuracy


# --------------------------------------------------------------------------- near-copies of keys, pieces


def near_copy_sequence(seed, T=400, K=5, likeness=0.999, gaps=(), convex=False, with_sq=False):
    """Keys of which the last is nearly a copy of the first (a key and its mirror image on a
    symmetric face): the Gram matrix is ill-conditioned and ADMM would crawl."""
    seq = sequence(seed, T=T, K=K, gaps=gaps, convex=convex, mu=0.1)
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((3 * K, K))
    A[:, -1] = likeness * A[:, 0] + np.sqrt(1 - likeness**2) * rng.standard_normal(3 * K)
    W = np.clip(np.cumsum(rng.standard_normal((T, K)) * 0.15, axis=0) + 0.3, 0.0, 1.0)
    B = W @ A.T + 0.2 * rng.standard_normal((T, 3 * K))
    G = A.T @ A
    C = np.ascontiguousarray((B @ A) * seq.delta[:, None])
    const = float(np.sum(B[seq.delta > 0] ** 2))
    seq = _sequence.Sequence(G, C, seq.delta, 0.1 * np.trace(G) / K, np.ones(K), convex, const)
    return (seq, np.sum(B**2, axis=1)) if with_sq else seq


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_near_copies_go_to_newton_first_and_reach_the_admm_optimum(seed, monkeypatch):
    # (without Σw ≤ 1, the default: with it, about one such problem in ten stops short of 1e-7
    # by either way, the exchanges cycling on the sums, before this change as after it)
    seq = near_copy_sequence(seed, gaps=[(150, 165)])
    lam = np.linalg.eigvalsh(seq.G)
    assert _spacetime.admm_iterations(seq, lam, 1e-9) > _spacetime._ADMM_LIMIT
    admm_calls = []
    admm = _spacetime.admm
    monkeypatch.setattr(_spacetime, "admm", lambda *a, **k: admm_calls.append(1) or admm(*a, **k))
    W, gap = _spacetime.solve_sequence(seq, rtol=1e-9)
    assert not admm_calls, "ADMM ran although the forecast sent the problem to the Newton steps"
    assert gap <= 1e-9
    monkeypatch.setattr(_spacetime, "_ADMM_LIMIT", np.inf)  # ADMM's way, as before the forecast
    W_admm, gap_admm = _spacetime.solve_sequence(seq, rtol=1e-9, max_admm=4000)
    assert admm_calls and gap_admm <= 1e-9
    F = _sequence.objective
    assert abs(F(seq, W) - F(seq, W_admm)) <= 2e-9 * F(seq, W_admm)


def test_forecast_keeps_well_conditioned_keys_on_admm():
    seq = sequence(3, T=200, K=4)
    assert _spacetime.admm_iterations(seq, np.linalg.eigvalsh(seq.G), 1e-7) < _spacetime._ADMM_LIMIT


@pytest.mark.parametrize(("make", "n_pieces"), [
    (lambda: long_gap_sequence(15, T=3000, with_sq=True), 3),  # 60-frame gaps, one of them across a seam
    (lambda: near_copy_sequence(16, T=2400, gaps=[(790, 830)], with_sq=True), 2),
    (lambda: sequence(17, T=2000, K=4, convex=True, upper=0.6, with_sq=True), 4),
])
def test_pieces_join_to_the_whole_take_optimum(make, n_pieces, monkeypatch):
    seq, sq = make()
    sq = np.where(seq.delta > 0, sq, np.random.default_rng(0).uniform(0, 9, seq.n_frames))  # any value in gaps
    fallback = []
    newton = _spacetime.newton
    monkeypatch.setattr(_spacetime, "newton",  # steps on the whole take, not a piece's own
                        lambda s, *a, **k: fallback.append(s.n_frames == seq.n_frames) or newton(s, *a, **k))
    W, gap = _spacetime.solve_pieces(seq, sq, rtol=1e-9, n_pieces=n_pieces)
    monkeypatch.setattr(_spacetime, "newton", newton)
    W_whole, gap_whole = _spacetime.solve_sequence(seq, rtol=1e-9)
    assert gap <= 1e-9 and gap_whole <= 1e-9
    F = _sequence.objective
    assert abs(F(seq, W) - F(seq, W_whole)) <= 2e-9 * F(seq, W_whole)
    assert ((W >= 0) & (W <= seq.upper)).all()
    assert not any(fallback), "the joined pieces needed the whole take's active-set steps"
