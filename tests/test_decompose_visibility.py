"""The solve with hidden landmarks (decompose/_weighted.py): a hand over the mouth no longer
corrupts the weights; a fully hidden region is bridged like a gap; all-visible is unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from keyshape.alignment import align
from keyshape.containers import KeyShapes, Track
from keyshape.datasets import make_performance
from keyshape.decompose import solve_weights

SPAN = slice(110, 130)  # 20 frames without a planted extreme or the planted neutral


@pytest.fixture(scope="module")
def take():
    perf = make_performance(n_frames=200, n_keys=6, noise=0.3, random_state=1)
    assert not set(perf.extreme_frames.tolist()) & set(range(SPAN.start, SPAN.stop))
    aligned, _ = align(perf.track, reference=perf.neutral, stable=perf.stable)
    keys = KeyShapes(perf.neutral, perf.key_deltas, tuple(f"k{i}" for i in range(perf.n_keys)),
                     perf.extreme_frames, perf.key_regions, perf.regions)
    lower = [k for k, r in enumerate(perf.key_regions) if r == "lower"]
    return perf, aligned, keys, lower


def _hand(aligned, landmarks, seed=0):
    """The landmarks replaced by a tracker's guesses under a hand over SPAN, and their visibility 0."""
    rng = np.random.default_rng(seed)
    points = aligned.points.copy()
    points[SPAN, landmarks] += rng.normal(0.0, 15.0, points[SPAN, landmarks].shape)
    seen = np.ones(points.shape[:2])
    seen[SPAN, landmarks] = 0.0
    return points, seen


def _error(weights, perf, lower):
    return np.abs(weights[SPAN][:, lower] - perf.true_weights[SPAN][:, lower]).max()


@pytest.mark.parametrize("smoothness", [0.0, 0.1])
def test_partly_hidden_mouth_is_solved_from_what_is_seen(take, smoothness):
    perf, aligned, keys, lower = take
    hidden = np.random.default_rng(3).permutation(perf.regions["lower"])[: int(0.6 * len(perf.regions["lower"]))]
    points, seen = _hand(aligned, hidden)
    clean = _error(solve_weights(aligned, keys, upper=1.0, smoothness=smoothness).values, perf, lower)
    blind = _error(solve_weights(Track(points, 30.0), keys, upper=1.0, smoothness=smoothness).values, perf, lower)
    seeing = _error(solve_weights(Track(points, 30.0, visibility=seen), keys, upper=1.0,
                                  smoothness=smoothness).values, perf, lower)
    # measured: clean 0.045 / 0.040, without visibility 0.90 / 0.77, with it 0.069 / 0.039
    assert blind > 0.5
    assert seeing < clean + 0.05


def test_fully_hidden_mouth_is_carried_by_the_smoothness(take):
    perf, aligned, keys, lower = take
    points, seen = _hand(aligned, perf.regions["lower"])
    blind = solve_weights(Track(points, 30.0), keys, upper=1.0, smoothness=0.1).values
    seeing = solve_weights(Track(points, 30.0, visibility=seen), keys, upper=1.0, smoothness=0.1).values
    gap = aligned.points.copy()
    gap[SPAN] = np.nan  # the same frames as a gap: what the smoothness alone makes of them
    bridged = solve_weights(Track(gap, 30.0), keys, upper=1.0, smoothness=0.1).values
    np.testing.assert_allclose(seeing[SPAN][:, lower], bridged[SPAN][:, lower], atol=1e-4)
    # measured: 0.15 from the truth (the bumps under the hand are unknowable), 0.83 without visibility
    assert _error(seeing, perf, lower) < 0.2 and _error(blind, perf, lower) > 0.5
    upper = [k for k in range(perf.n_keys) if k not in lower]  # the seen eyes are solved as before
    clean = solve_weights(aligned, keys, upper=1.0, smoothness=0.1).values
    np.testing.assert_allclose(seeing[:, upper], clean[:, upper], atol=1e-6)


def test_fully_hidden_region_without_smoothing_has_no_weights(take):
    perf, aligned, keys, lower = take
    points, seen = _hand(aligned, perf.regions["lower"])
    weights = solve_weights(Track(points, 30.0, visibility=seen), keys, upper=1.0).values
    assert np.isnan(weights[SPAN][:, lower]).all() and np.isfinite(weights[:SPAN.start]).all()


def test_all_visible_is_the_unweighted_solve(take):
    _, aligned, keys, _ = take
    seen = Track(aligned.points, 30.0, visibility=np.ones(aligned.points.shape[:2]))
    for smoothness in (0.0, 0.1):
        np.testing.assert_array_equal(solve_weights(seen, keys, upper=1.0, smoothness=smoothness).values,
                                      solve_weights(aligned, keys, upper=1.0, smoothness=smoothness).values)


def _weighted_problem(seed=0, n=60, m=12, K=4, gap=(20, 26)):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, K))
    truth = np.clip(rng.normal(0.4, 0.4, (n, K)), 0, 1)
    B = truth @ A.T + rng.normal(0, 0.05, (n, m))
    B[gap[0]:gap[1]] = np.nan
    weight = np.clip(rng.uniform(-0.5, 1.5, (n, m)), 0, 1)
    return A, B, weight, np.ones(K)


def _objective(A, B, weight, X, mu):
    seen = np.isfinite(B).all(axis=1)
    r = np.where(seen[:, None], X @ A.T - np.nan_to_num(B), 0.0)
    L = X[2:] - 2 * X[1:-1] + X[:-2]
    return float((weight * r**2).sum() + mu * (L**2).sum())


def _clarabel(A, B, weight, mu, upper):
    """The weighted smoothed QP as one sparse QP, solved by Clarabel (the independent reference)."""
    qpsolvers = pytest.importorskip("qpsolvers")
    from scipy import sparse

    n, K = B.shape[0], A.shape[1]
    seen = np.isfinite(B).all(axis=1)
    blocks, q = [], np.zeros(n * K)
    for t in range(n):
        At = A * (weight[t] if seen[t] else np.zeros(len(weight[t])))[:, None]
        blocks.append(At.T @ A)
        if seen[t]:
            q[t * K:(t + 1) * K] -= B[t] @ At
    L = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n))
    P = sparse.block_diag(blocks) + mu * sparse.kron(L.T @ L, sparse.eye(K))
    x = qpsolvers.solve_qp(sparse.csc_matrix(2 * P), 2 * q, lb=np.zeros(n * K),
                           ub=np.broadcast_to(upper, (n, K)).ravel(), solver="clarabel")
    return x.reshape(n, K)


def _kkt(A, B, weight, X, mu, upper):
    """The largest violation of the KKT conditions, relative to the gradient's scale (analytic gradient)."""
    seen = np.isfinite(B).all(axis=1)
    r = np.where(seen[:, None], weight * (X @ A.T - np.nan_to_num(B)), 0.0)
    grad = 2 * r @ A
    L = X[2:] - 2 * X[1:-1] + X[:-2]
    smooth = np.zeros_like(X)
    smooth[2:] += L
    smooth[1:-1] -= 2 * L
    smooth[:-2] += L
    grad += 2 * mu * smooth
    scale = np.abs(grad).max()
    free = (X > 1e-9) & (X < upper - 1e-9)
    return max(np.abs(grad[free]).max(initial=0.0), -grad[X <= 1e-9].min(initial=0.0),
               grad[X >= upper - 1e-9].max(initial=0.0)) / scale


@pytest.mark.parametrize("seed, bound", [(0, 1.0), (1, 1.0), (2, 1.0), (3, np.inf)])
def test_exact_weighted_smoothed_solve_is_the_optimum(seed, bound):
    """The exact solve of the weighted smoothed QP (in Gram form) meets its KKT conditions, matches
    an independent QP solver (Clarabel) and is no worse than majorise-minimise (also unbounded above)."""
    from keyshape.decompose._solve import _mu, _solve_region
    from keyshape.decompose._weighted import _majorise, solve_weighted

    A, B, weight, upper = _weighted_problem(seed)
    upper = np.full_like(upper, bound)
    mu = _mu(A.T @ A, 0.1)
    solve = lambda b: _solve_region(A, b, upper, 0.1, False)  # noqa: E731
    X = solve_weighted(A, B, weight, solve, smoothness=0.1, upper=upper, convex=False, mu=mu)
    assert (X >= 0).all() and (X <= upper).all() and (X > 1).any() == (bound > 1)
    assert _kkt(A, B, weight, X, mu, upper) < 1e-6
    # against majorise-minimise from the unweighted solve, and against Clarabel on the whole QP
    partial = np.flatnonzero(np.isfinite(B).all(axis=1) & (weight < 1).any(axis=1))
    slow = _majorise(A, B.copy(), weight[partial], partial, solve(B), solve)
    assert _objective(A, B, weight, X, mu) <= _objective(A, B, weight, slow, mu) + 1e-9
    reference = _clarabel(A, B, weight, mu, upper)
    theirs = _objective(A, B, weight, reference, mu)
    assert _objective(A, B, weight, X, mu) <= theirs + 1e-9 * theirs  # as low as Clarabel's, or lower
    np.testing.assert_allclose(X, reference, atol=1e-3)


def _hand_problem(seed, n=1400, m=30, K=6):
    """A take with a hand over the mouth for 170 frames in every 700 (as bench_decompose.py's
    case): 60 % of the landmarks at visibility 0.05 with wrong data, the middle 40 frames fully
    hidden, correlated keys (one a near-copy of another, as mirrored keys are)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, K)) @ np.linalg.cholesky(0.5 * np.eye(K) + 0.5).T
    A[:, -1] = A[:, 0] + 0.05 * rng.normal(size=m)  # a near-duplicate key
    from scipy.ndimage import gaussian_filter1d

    Z = gaussian_filter1d(rng.standard_normal((n, K)), 6.0, axis=0)
    truth = np.clip(Z / Z.std(axis=0) * 0.5, 0.0, 1.0)
    B = truth @ A.T + 0.05 * rng.normal(size=(n, m))
    weight = np.ones((n, m // 3))
    for start in range(300, n - 175, 700):
        covered = rng.permutation(m // 3)[: int(0.6 * (m // 3))]
        weight[start:start + 170, covered] = 0.05
        weight[start + 65:start + 105] = 0.0
    weight = np.repeat(weight, 3, axis=1)
    B = B + (weight < 1) * rng.normal(0.0, 0.5, B.shape)
    return A, B, weight, np.ones(K)


@pytest.mark.parametrize("seed", [0, 1])
def test_hand_over_the_mouth_is_solved_to_the_certificate(seed, monkeypatch):
    """A longer take where the exchanges need local phases (and, with CYCLING at 1, every
    variable that moves twice is damped): the optimum, as low as Clarabel's."""
    import keyshape.decompose._weighted as weighted
    from keyshape.decompose._solve import _mu

    A, B, weight, upper = _hand_problem(seed)
    mu = _mu(A.T @ A, 0.1)
    seen = np.isfinite(B).all(axis=1) & (weight.mean(axis=1) >= weighted.HIDDEN)
    Bh = np.where(seen[:, None], B, np.nan)
    v = np.where(seen[:, None], weight, 0.0)
    B0 = np.nan_to_num(Bh)
    G, C, sq = weighted.weighted_gram(A, v), (v * B0) @ A, np.einsum("fm,fm->f", v * B0, B0)
    trace = []
    found = weighted._exact(G, C, float(sq.sum()), mu, upper, tol=1e-9, trace=trace)
    X, gap = found
    assert gap <= 1e-9 and any(len(step) == 2 and not isinstance(step[0], str) for step in trace)  # local steps ran
    reference = _clarabel(A, Bh, weight, mu, upper)
    ours, theirs = _objective(A, Bh, weight, X, mu), _objective(A, Bh, weight, reference, mu)
    assert ours <= theirs * (1 + 1e-8)
    assert _kkt(A, Bh, weight, X, mu, upper) < 1e-4  # certified by the gap, not by exact KKT: close to it
    monkeypatch.setattr(weighted, "CYCLING", 1)  # every variable that moved once moves one per window
    monkeypatch.setattr(weighted, "FEW", 10)  # local phases from the first steps on
    damped, gap = weighted._exact(G, C, float(sq.sum()), mu, upper, tol=1e-9)
    assert gap <= 1e-9 and _objective(A, Bh, weight, damped, mu) <= theirs * (1 + 1e-8)


def test_deepest_of_each_run_goes_to_its_bound():
    """_deepest keeps one variable per run of consecutive frames, key and side: the largest
    violation (the first of equal ones); a frame missing from rows, another key or the other
    bound starts a new run."""
    from keyshape.decompose._weighted import _deepest

    rows = np.array([3, 4, 5, 6, 8, 9])  # frame 7 not among them: 6 and 8 are not consecutive
    out = np.zeros((6, 2), bool)
    viol = np.zeros((6, 2))
    below = np.ones((6, 2), bool)
    out[:, 0] = True
    viol[:, 0] = [0.3, 0.1, 0.3, 0.1, 0.5, 0.5]  # runs 3-6 (a tie: 3, not 5) and 8-9 (a tie: 8)
    out[1:4, 1] = True
    viol[1:4, 1] = [0.2, 0.1, 0.4]
    below[3, 1] = False  # frame 6 of key 1 is past the upper bound: a run of its own
    keep = _deepest(rows, out, viol, below)
    expected = np.zeros((6, 2), bool)
    expected[[0, 4], 0] = True
    expected[[1, 3], 1] = True
    np.testing.assert_array_equal(keep, expected)


@pytest.mark.parametrize("seed", [0, 1])
def test_deepest_exchanges_reach_the_same_optimum_in_fewer_local_steps(seed, monkeypatch):
    """With gaps started free and only the deepest of a run past a bound moved per step, the
    hand over the mouth ends on the same certified face as the former exchanges (every
    violation at once, gaps starting at the frame before's bounds), in a quarter of the local
    steps (those released a dip put at 0 about one frame per step)."""
    import keyshape.decompose._weighted as weighted
    from keyshape.decompose._solve import _mu

    A, B, weight, upper = _hand_problem(seed)
    mu = _mu(A.T @ A, 0.1)
    seen = np.isfinite(B).all(axis=1) & (weight.mean(axis=1) >= weighted.HIDDEN)
    v = np.where(seen[:, None], weight, 0.0)
    B0 = np.where(seen[:, None], B, 0.0)
    G, C, sq = weighted.weighted_gram(A, v), (v * B0) @ A, np.einsum("fm,fm->f", v * B0, B0)
    found = {}
    for new in (False, True):
        monkeypatch.setattr(weighted, "GAPS_FREE", new)
        monkeypatch.setattr(weighted, "DEEPEST", new)
        trace = []
        X, gap = weighted._exact(G, C, float(sq.sum()), mu, upper, trace=trace)
        assert gap == 0.0  # a face of the whole take met every KKT condition
        found[new] = X, sum(1 for step in trace if step[0] != "whole")
    (former, former_steps), (X, steps) = found[False], found[True]
    np.testing.assert_allclose(X, former, rtol=0.0, atol=1e-9)
    assert 0 < steps <= former_steps // 4  # either change alone is not enough (13-41 steps, against 38-40)


def test_gram_form_is_the_frames_solve():
    """solve_weighted_gram on (G_t, c_t, b_tᵀV_tb_t) gives solve_weighted's weights; frames
    outside the first and last with data are NaN, as in the unweighted solve."""
    from keyshape.decompose._solve import _mu, _solve_region
    from keyshape.decompose._weighted import solve_weighted, solve_weighted_gram, weighted_gram

    A, B, weight, upper = _weighted_problem(3)
    B[:2] = np.nan
    mu = _mu(A.T @ A, 0.1)
    solve = lambda b: _solve_region(A, b, upper, 0.1, False)  # noqa: E731
    frames = solve_weighted(A, B, weight, solve, smoothness=0.1, upper=upper, convex=False, mu=mu)
    seen = np.isfinite(B).all(axis=1)
    G = np.array([(A * w[:, None]).T @ A for w in weight])  # one Gram matrix per frame, directly
    np.testing.assert_allclose(weighted_gram(A, weight), G, atol=1e-12)
    B0 = np.nan_to_num(B)
    gram = solve_weighted_gram(G, (weight * B0) @ A, np.einsum("fm,fm->f", weight * B0, B0), seen, mu, upper)
    assert np.isnan(gram[:2]).all() and np.isnan(frames[:2]).all()
    np.testing.assert_allclose(gram, frames, atol=1e-7)


def test_a_stopped_solve_warns_and_stays_feasible(monkeypatch):
    """Without the budget to reach the certificate, the best point is returned, within its bounds,
    with a ConvergenceWarning naming the certified gap."""
    import keyshape.decompose._weighted as weighted
    from keyshape.decompose._solve import _mu
    from keyshape.exceptions import ConvergenceWarning

    A, B, weight, upper = _hand_problem(0, n=800)
    mu = _mu(A.T @ A, 0.1)
    seen = np.isfinite(B).all(axis=1) & (weight.mean(axis=1) >= weighted.HIDDEN)
    v = np.where(seen[:, None], weight, 0.0)
    B0 = np.where(seen[:, None], B, 0.0)
    monkeypatch.setattr(weighted, "MAX_STEPS", 1)
    monkeypatch.setattr(weighted, "FEW", 10**9)  # no local phase either
    with pytest.warns(ConvergenceWarning, match="certified relative gap"):
        X = weighted.solve_weighted_gram(weighted.weighted_gram(A, v), (v * B0) @ A,
                                         np.einsum("fm,fm->f", v * B0, B0), seen, mu, upper, tol=1e-12)
    assert np.isfinite(X).all() and (X >= 0).all() and (X <= 1).all()
    # the duality gap it reports bounds how far it really is from the optimum
    G, C, sq = weighted.weighted_gram(A, v), (v * B0) @ A, np.einsum("fm,fm->f", v * B0, B0)
    stopped, gap = weighted._exact(G, C, float(sq.sum()), mu, upper, tol=1e-12, valid=seen)
    monkeypatch.setattr(weighted, "MAX_STEPS", 30)
    monkeypatch.setattr(weighted, "FEW", 100)
    best, zero = weighted._exact(G, C, float(sq.sum()), mu, upper, tol=1e-12, valid=seen)
    Bh = np.where(seen[:, None], B, np.nan)
    F, F_star = _objective(A, Bh, weight, stopped, mu), _objective(A, Bh, weight, best, mu)
    assert zero == 0.0 and 1e-9 < (F - F_star) / F <= gap * (1 + 1e-6) + 1e-12


@pytest.mark.parametrize("bound", [1.0, np.inf])
def test_frames_on_their_own_gram_matrices_are_the_exact_nnls(bound):
    """Without smoothing every partly hidden frame is its own bounded NNLS on ``Aᵀ V_t A``: the
    compiled pass over all frames gives nnls_gram's weights frame by frame (near-duplicate key
    included), NaN where a frame has no data."""
    from keyshape.decompose._nnls import nnls_gram
    from keyshape.decompose._weighted import solve_weighted_frames, weighted_gram

    rng = np.random.default_rng(7)
    A, B, weight, upper = _hand_problem(2, n=700)
    upper = np.full_like(upper, bound)
    weight = np.clip(weight + rng.uniform(0, 0.3, weight.shape), 0, 1)
    valid = np.ones(len(B), bool)
    valid[5] = False
    X = solve_weighted_frames(weighted_gram(A, weight), (weight * B) @ A, valid, upper)
    for t in range(len(B)):
        if not valid[t]:
            assert np.isnan(X[t]).all()
            continue
        Av = A * weight[t][:, None]
        np.testing.assert_allclose(X[t], nnls_gram(Av.T @ A, (B[t] @ Av)[None], upper, False)[0], atol=1e-8)


def _random_face(seed, n=12, K=4):
    """A small weighted QP in Gram form (per-frame G_t, some nearly singular) and a face of it:
    random states, the frames ``rows`` (two runs, a gap between) re-solved, the rest held."""
    from keyshape.decompose._weighted import _Problem

    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, K + 1, K))
    G = np.einsum("tmk,tml->tkl", M, M) * rng.uniform(0.0, 1.0, n)[:, None, None]
    G[3] = 0.0  # a frame without data: the smoothness alone
    C = rng.normal(size=(n, K))
    problem = _Problem(G, C, 0.7, np.ones(K))
    state = rng.integers(0, 3, size=(n, K)).astype(np.int8)
    X = rng.uniform(0.0, 1.0, size=(n, K))
    rows = np.array([0, 1, 2, 3, 4, 5, 8, 9, 10])
    return problem, G, C, state, X, rows


def _dense_hessian(G, mu):
    from keyshape.decompose._sequence import second_difference_gram

    n, K = G.shape[:2]
    Lap = np.diff(np.eye(n), 2, axis=0)
    P = np.zeros((n * K, n * K))
    for t in range(n):
        P[t * K:(t + 1) * K, t * K:(t + 1) * K] = G[t]
    P += mu * np.kron(Lap.T @ Lap, np.eye(K))
    d0, d1, d2 = second_difference_gram(n)  # the same LᵀL as the kernels'
    for offset, d in enumerate((d0, d1, d2)):
        np.testing.assert_allclose(np.diag(Lap.T @ Lap, offset), d)
    return P


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_weighted_face_is_the_dense_solve(seed):
    """A face solved on its envelope (per-frame G_t, the free variables of some frames only,
    the rest held) is the dense solve of the same face."""
    problem, G, C, state, X, rows = _random_face(seed)
    n, K = C.shape
    P = _dense_hessian(G, problem.mu)
    fixed = X.copy()  # held frames keep X, bound variables of rows sit at their bounds
    fixed[rows] = np.where(state[rows] == 2, 1.0, 0.0)
    free = np.zeros((n, K), bool)
    free[rows] = state[rows] == 1
    f = free.ravel()
    expected = fixed.ravel().copy()
    expected[f] = np.linalg.solve(P[np.ix_(f, f)], (C.ravel() - P @ fixed.ravel())[f])
    ours = X.copy()
    problem.solve(ours, state, rows)
    np.testing.assert_allclose(ours.ravel(), expected, rtol=1e-10, atol=1e-10)
    assert not np.allclose(ours, X)


@pytest.mark.parametrize("seed", [0, 1])
def test_weighted_envelope_factor_is_numpys_cholesky(seed):
    """The packed envelope factor (every variable free, as the certificate factors ``P``) holds
    numpy's Cholesky factor of the dense ``P``, and inverts ``P``."""
    from keyshape.decompose._weighted import _Certificate

    problem, G, C = _random_face(seed)[:3]
    n, K = C.shape
    cert = _Certificate(problem, 1.0)
    assert cert.ok and cert.n_free == n * K
    P = _dense_hessian(G, problem.mu)
    L = np.linalg.cholesky(P)
    ours = np.zeros_like(L)
    for j in range(n * K):
        column = cert.packed[cert.offset[j]: cert.offset[j] + cert.reach[j] + 1]
        ours[j: j + len(column), j] = column
    np.testing.assert_allclose(ours, L, atol=1e-12 * np.abs(L).max())
    assert np.all(L[np.tril_indices(n * K)][np.abs(ours[np.tril_indices(n * K)]) == 0.0] == 0.0)  # nothing lost
    R = np.random.default_rng(seed).normal(size=(n, K))
    np.testing.assert_allclose(cert.inverse(R).ravel(), np.linalg.solve(P, R.ravel()), rtol=1e-9, atol=1e-12)


def test_a_face_that_is_not_positive_definite_raises():
    """A face whose free block is singular (no data, no smoothness) is refused, not solved."""
    problem, _, _, state, X, rows = _random_face(0)
    problem.G[:] = 0.0
    problem.mu = 0.0
    with pytest.raises(np.linalg.LinAlgError):
        problem.solve(X, np.ones_like(state), rows)


@pytest.mark.parametrize("seed", [0, 1])
def test_weighted_solve_in_pieces_is_the_whole_take_solve(seed, monkeypatch):
    """A take cut into overlapping pieces (solved on threads, joined, finished on the whole take)
    has the whole-take solve's optimum, to the same exact KKT certificate (gap 0)."""
    import keyshape.decompose._weighted as weighted
    from keyshape.decompose._solve import _mu

    A, B, weight, upper = _hand_problem(seed, n=2100)
    mu = _mu(A.T @ A, 0.1)
    seen = np.isfinite(B).all(axis=1) & (weight.mean(axis=1) >= weighted.HIDDEN)
    v = np.where(seen[:, None], weight, 0.0)
    B0 = np.where(seen[:, None], B, 0.0)
    G, C, sq = weighted.weighted_gram(A, v), (v * B0) @ A, np.einsum("fm,fm->f", v * B0, B0)
    whole, gap = weighted._exact(G, C, float(sq.sum()), mu, upper, valid=seen)
    assert gap == 0.0
    calls = []
    exact = weighted._exact

    def spy(*args, **kwargs):
        found = exact(*args, **kwargs)
        calls.append((len(args[1]), "start" in kwargs, found[1]))
        return found

    monkeypatch.setattr(weighted, "_exact", spy)
    monkeypatch.setattr(weighted, "PIECE_FRAMES", 500)
    monkeypatch.setattr(weighted.os, "cpu_count", lambda: 3)
    pieces = weighted.solve_weighted_gram(G, C, sq, seen, mu, upper)
    assert [c[:2] for c in calls[-1:]] == [(2100, True)] and len(calls) == 4  # three pieces, then the whole
    assert all(c[0] < 2100 for c in calls[:3]) and calls[-1][2] == 0.0  # the whole take certified exactly
    np.testing.assert_allclose(pieces, whole, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_a_whole_take_face_in_two_halves_is_the_dense_solve(seed, monkeypatch):
    """The face of the whole take factored as two halves on two threads and the middle two
    frames last (one-way dissection) is the dense solve of the same face, whichever of the
    middle frames' variables are free."""
    import keyshape.decompose._weighted as weighted

    monkeypatch.setattr(weighted, "SPLIT_FRAMES", 8)
    problem, G, C, state, X, _ = _random_face(seed, n=13)
    if seed == 3:
        state[5:9] = 1  # every variable free around the middle (frames 6, 7)
    if seed == 4:
        state[6:8] = 0  # none: the halves are independent
    split = weighted._Problem(G, C, problem.mu, problem.upper, split=True)
    assert split.split
    P = _dense_hessian(G, problem.mu)
    fixed = np.where(state == 2, 1.0, 0.0)
    f = (state == 1).ravel()
    expected = fixed.ravel().copy()
    expected[f] = np.linalg.solve(P[np.ix_(f, f)], (C.ravel() - P @ fixed.ravel())[f])
    ours = X.copy()
    split.solve(ours, state, split.every)
    np.testing.assert_allclose(ours.ravel(), expected, rtol=1e-10, atol=1e-10)
    whole = X.copy()
    problem.solve(whole, state, problem.every)  # the one-envelope factorisation
    np.testing.assert_allclose(ours, whole, rtol=1e-10, atol=1e-12)
    # the KKT check of the whole take in two halves is the one in one pass
    np.testing.assert_array_equal(split.violations(ours, state, split.every),
                                  problem.violations(ours, state, problem.every))


def test_a_gap_longer_than_a_piece_is_solved_to_the_certificate(monkeypatch):
    """A piece without any data (its QP only the smoothness: singular, solved or refused) does
    not lose the take: the joined take is finished and certified as a whole, as good as
    without pieces."""
    import keyshape.decompose._weighted as weighted
    from keyshape.decompose._solve import _mu

    A, B, weight, upper = _hand_problem(0, n=2100)
    mu = _mu(A.T @ A, 0.1)
    seen = np.isfinite(B).all(axis=1) & (weight.mean(axis=1) >= weighted.HIDDEN)
    seen[550:1550] = False  # the middle piece (frames 700-1400 and its margins) has no data
    v = np.where(seen[:, None], weight, 0.0)
    B0 = np.where(seen[:, None], B, 0.0)
    G, C, sq = weighted.weighted_gram(A, v), (v * B0) @ A, np.einsum("fm,fm->f", v * B0, B0)
    whole = weighted.solve_weighted_gram(G, C, sq, seen, mu, upper)
    monkeypatch.setattr(weighted, "PIECE_FRAMES", 500)
    monkeypatch.setattr(weighted.os, "cpu_count", lambda: 3)
    pieces = weighted.solve_weighted_gram(G, C, sq, seen, mu, upper)
    assert np.isfinite(pieces).all() and (pieces >= 0).all() and (pieces <= upper).all()

    def objective(X):
        D = X[2:] - 2 * X[1:-1] + X[:-2]
        return float(np.einsum("tk,tkl,tl->", X, G, X) - 2 * np.sum(C * X) + sq.sum() + mu * np.sum(D**2))

    # the gap's weights are barely determined (the objective is flat there): equally good, to the certificate
    assert abs(objective(pieces) - objective(whole)) <= 1e-7 * objective(whole)
