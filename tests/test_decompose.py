"""Decompose: exact batched NNLS against scipy, KKT, recovery of known weights, smoothing."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from keyshape.containers import KeyShapes, Track
from keyshape.decompose import solve_nnls, solve_spacetime, solve_weights
from keyshape.exceptions import InputError

# --------------------------------------------------------------------------- helpers


def scipy_loop(A, B):
    """The reference: one ``scipy.optimize.nnls`` call per frame."""
    return np.array([scipy.optimize.nnls(A, b)[0] for b in B]).reshape(len(B), A.shape[1])


def assert_kkt(A, B, W, *, upper=None, tol=1e-8):
    """KKT conditions of ``min ‖Aw − b‖², 0 ≤ w ≤ u`` for every row, relative to its scale."""
    u = np.full(A.shape[1], np.inf) if upper is None else np.broadcast_to(upper, A.shape[1])
    grad = (W @ A.T - B) @ A  # ½ ∇‖Aw − b‖², (n_frames, n_keys)
    scale = tol * (1.0 + np.abs(B).max(axis=1, keepdims=True)) * (1.0 + np.abs(A).sum())
    assert (W >= 0).all() and (W <= u).all()
    scale = np.broadcast_to(scale, W.shape)
    inside, lower, top = (W > 0) & (W < u), (W == 0) & (u > 0), (W == u) & (u > 0)
    assert (np.abs(grad[inside]) <= scale[inside]).all()
    assert (grad[lower] >= -scale[lower]).all()
    assert (grad[top] <= scale[top]).all()


def residual(A, B, W):
    return np.linalg.norm(W @ A.T - B, axis=1)


def problem(seed, n_frames, m, k, noise=0.1, sparsity=0.5):
    """Random ``A (m, k)``, known non-negative ``W (n_frames, k)`` and ``B = W Aᵀ + noise``."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((m, k))
    W = rng.random((n_frames, k)) * (rng.random((n_frames, k)) > sparsity)
    B = W @ A.T + noise * rng.standard_normal((n_frames, m))
    return A, W, B


# --------------------------------------------------------------------------- per-frame NNLS

KINDS = ["generic", "duplicate", "zero", "wide", "scaled", "mixed signs"]


def degenerate(kind, A, B, rng):
    """Make ``A`` rank deficient or badly scaled, or ``B`` unlike the model."""
    A = A.copy()
    if kind == "duplicate" and A.shape[1] > 1:
        A[:, -1] = A[:, 0]
    elif kind == "zero":
        A[:, rng.integers(A.shape[1])] = 0.0
    elif kind == "scaled":
        A *= np.logspace(-2, 2, A.shape[1])
    elif kind == "mixed signs":
        B = rng.standard_normal(B.shape) * 3.0
    return A, B


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    k=st.integers(1, 24),
    extra_rows=st.integers(3, 40),
    n_frames=st.integers(1, 40),
    kind=st.sampled_from(KINDS),
)
def test_batched_nnls_matches_scipy_loop(seed, k, extra_rows, n_frames, kind):
    rng = np.random.default_rng(seed)
    m = max(1, k // 2) if kind == "wide" else k + extra_rows
    A, _, B = problem(seed, n_frames, m, k)
    A, B = degenerate(kind, A, B, rng)
    W = solve_nnls(A, B)
    R = scipy_loop(A, B)
    assert W.shape == (n_frames, k)
    if kind in ("generic", "mixed signs"):  # unique solution: the weights themselves agree
        np.testing.assert_allclose(W, R, atol=1e-8 * (1.0 + np.abs(R).max()), rtol=0)
        assert_kkt(A, B, W)
    else:  # non-unique (or wildly scaled) weights: the fit agrees
        fit, ref = residual(A, B, W), residual(A, B, R)
        assert (fit <= ref + 1e-8 * (1.0 + np.linalg.norm(B, axis=1))).all()
        assert (W >= 0).all()


@pytest.mark.parametrize("k", [1, 8, 16, 24])
def test_batched_nnls_matches_scipy_on_many_frames(k):
    A, _, B = problem(k, 2000, 3 * k + 30, k, noise=0.3)
    np.testing.assert_allclose(solve_nnls(A, B), scipy_loop(A, B), atol=1e-8, rtol=0)


@pytest.mark.parametrize("cond", [1e2, 1e4])
def test_ill_conditioned_keys_still_match(cond):
    rng = np.random.default_rng(3)
    U, _ = np.linalg.qr(rng.standard_normal((120, 12)))
    V, _ = np.linalg.qr(rng.standard_normal((12, 12)))
    A = (U * np.logspace(0, -np.log10(cond), 12)) @ V.T
    B = np.maximum(rng.standard_normal((300, 12)), 0) @ A.T + 0.01 * rng.standard_normal((300, 120))
    W, R = solve_nnls(A, B), scipy_loop(A, B)
    np.testing.assert_allclose(residual(A, B, W), residual(A, B, R), rtol=1e-10)
    np.testing.assert_allclose(W, R, atol=1e-6)


def test_recovers_true_weights_without_noise():
    A, W_true, B = problem(0, 500, 60, 12, noise=0.0)
    np.testing.assert_allclose(solve_nnls(A, B), W_true, atol=1e-10)


def test_nan_frames_give_nan_rows():
    A, W_true, B = problem(1, 20, 30, 5, noise=0.0)
    B[[3, 7]] = np.nan
    B[11, 4] = np.nan
    W = solve_nnls(A, B)
    bad = [3, 7, 11]
    assert np.isnan(W[bad]).all()
    good = np.setdiff1d(np.arange(20), bad)
    np.testing.assert_allclose(W[good], W_true[good], atol=1e-10)


def test_empty_and_trivial_inputs():
    assert solve_nnls(np.ones((3, 2)), np.zeros((0, 3))).shape == (0, 2)
    np.testing.assert_array_equal(solve_nnls(np.zeros((4, 3)), np.ones((2, 4))), np.zeros((2, 3)))


@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 12), u=st.floats(0.0, 2.0))
@settings(max_examples=60, deadline=None)
def test_upper_bound_kkt(seed, k, u):
    A, _, B = problem(seed, 30, k + 10, k, noise=0.5)
    B *= 3.0  # push many weights above the bound
    W = solve_nnls(A, B, upper=u)
    assert_kkt(A, B, W, upper=u)


def test_upper_bound_per_key_and_infinite():
    A, _, B = problem(5, 200, 40, 6, noise=0.2)
    upper = np.array([0.2, np.inf, 0.5, 1.0, 0.0, np.inf])
    W = solve_nnls(A, 3 * B, upper=upper)
    assert_kkt(A, 3 * B, W, upper=upper)
    assert (W[:, 4] == 0).all()


def qp_reference(A, b, upper=None, convex=False):
    """One frame solved by Clarabel through qpsolvers (tests only)."""
    qpsolvers = pytest.importorskip("qpsolvers")
    from scipy import sparse

    k = A.shape[1]
    u = None if upper is None else np.broadcast_to(upper, k).astype(float)
    G, h = (sparse.csc_matrix(np.ones((1, k))), np.ones(1)) if convex else (None, None)
    return qpsolvers.solve_qp(
        sparse.csc_matrix(A.T @ A), -A.T @ b, G=G, h=h, lb=np.zeros(k), ub=u, solver="clarabel",
        tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12,
    )


@pytest.mark.parametrize("upper", [None, 0.6])
def test_convex_matches_clarabel(upper):
    A, _, B = problem(7, 40, 25, 6, noise=0.3, sparsity=0.2)
    B *= 2.0
    W = solve_nnls(A, B, upper=upper, convex=True)
    assert (W >= 0).all() and (W.sum(axis=1) <= 1.0).all()
    if upper is not None:
        assert (W <= upper).all()
    R = np.array([qp_reference(A, b, upper, convex=True) for b in B])
    np.testing.assert_allclose(residual(A, B, W) ** 2, residual(A, B, R) ** 2, rtol=1e-7)
    np.testing.assert_allclose(W, R, atol=1e-5)


def test_convex_leaves_feasible_frames_alone():
    A, _, B = problem(8, 50, 25, 6, noise=0.0, sparsity=0.8)
    B *= 0.1
    np.testing.assert_allclose(solve_nnls(A, B, convex=True), solve_nnls(A, B), atol=1e-12)


@pytest.mark.parametrize(
    ("upper", "match"),
    [(-1.0, "upper must be"), ([1.0, 2.0], "upper must be"), (np.nan, "upper must be")],
)
def test_bad_upper_is_rejected(upper, match):
    with pytest.raises(InputError, match=match):
        solve_nnls(np.eye(3), np.ones((2, 3)), upper=upper)


def test_bad_shapes_are_rejected():
    with pytest.raises(InputError, match=r"B must have shape \(n_frames, 3\)"):
        solve_nnls(np.eye(3), np.ones((2, 4)))
    with pytest.raises(InputError, match="A must have shape"):
        solve_nnls(np.ones(3), np.ones((2, 3)))


# --------------------------------------------------------------------------- solve_weights


def two_region_keys(rng, n_landmarks=10, n_dims=3):
    """A hand-built landmark rig: 3 keys on the upper half, 4 on the lower half."""
    regions = {"upper": np.arange(0, 4), "lower": np.arange(4, n_landmarks)}
    neutral = rng.standard_normal((n_landmarks, n_dims))
    deltas, key_regions = [], []
    for region, count in (("lower", 4), ("upper", 3)):
        for _ in range(count):
            d = np.zeros((n_landmarks, n_dims))
            d[regions[region]] = rng.standard_normal((len(regions[region]), n_dims))
            deltas.append(d)
            key_regions.append(region)
    names = tuple(f"{r}_{i:02d}" for i, r in enumerate(key_regions))
    return KeyShapes(neutral, np.array(deltas), names, np.arange(7), tuple(key_regions), regions)


def test_solve_weights_recovers_known_blend():
    rng = np.random.default_rng(11)
    keys = two_region_keys(rng)
    W_true = rng.random((40, 7)) * (rng.random((40, 7)) > 0.4)
    points = keys.pose(W_true)
    points[[5, 17]] = np.nan
    weights = solve_weights(Track(points, fps=25.0), keys)
    assert weights.names == keys.names and weights.fps == 25.0
    assert weights.values.shape == (40, 7)
    assert np.isnan(weights.values[[5, 17]]).all()
    valid = np.setdiff1d(np.arange(40), [5, 17])
    np.testing.assert_allclose(weights.values[valid], W_true[valid], atol=1e-10)


def test_solve_weights_bounds_and_convex():
    rng = np.random.default_rng(12)
    keys = two_region_keys(rng)
    W_true = 2.0 * rng.random((30, 7))
    track = Track(keys.pose(W_true), fps=30.0)
    bounded = solve_weights(track, keys, upper=0.7).values
    assert bounded.max() <= 0.7 and bounded.min() >= 0.0
    convex = solve_weights(track, keys, convex=True).values
    for region in keys.regions:
        assert (convex[:, keys.keys_of(region)].sum(axis=1) <= 1.0).all()


def test_solve_weights_rejects_mismatched_track():
    rng = np.random.default_rng(13)
    keys = two_region_keys(rng)
    with pytest.raises(InputError, match="align the track onto the key set first"):
        solve_weights(Track(np.zeros((3, 9, 3)), fps=30.0), keys)
    with pytest.raises(InputError, match="smoothness must be"):
        solve_weights(Track(np.zeros((3, 10, 3)), fps=30.0), keys, smoothness=-1.0)


# --------------------------------------------------------------------------- spacetime


def smooth_problem(seed=0, n_frames=600, m=45, k=6, noise=0.6, gaps=()):
    """Smooth true weight curves in ``[0, 1]`` (many exact zeros), noisy frames, optional gaps."""
    from scipy.ndimage import gaussian_filter1d

    rng = np.random.default_rng(seed)
    A = rng.standard_normal((m, k))
    Z = gaussian_filter1d(rng.standard_normal((n_frames, k)), 8.0, axis=0)
    W = np.clip(Z / Z.std(axis=0) * 0.5, 0.0, 1.0)
    B = W @ A.T + noise * rng.standard_normal((n_frames, m))
    for start, stop in gaps:
        B[start:stop] = np.nan
    return A, W, B


def objective(A, B, W, smoothness):
    """``Σ_valid ‖A w_t − b_t‖² + μ Σ ‖Δ² w‖²`` with ``μ = smoothness · trace(AᵀA) / K``."""
    valid = np.isfinite(B).all(axis=1)
    r = (W @ A.T - B)[valid]
    d = W[:-2] - 2 * W[1:-1] + W[2:]
    return float(np.sum(r * r) + smoothness * np.trace(A.T @ A) / A.shape[1] * np.sum(d * d))


def spacetime_reference(A, B, smoothness, upper=None, convex=False):
    """The whole sequence as one sparse QP, solved by Clarabel (tests only)."""
    qpsolvers = pytest.importorskip("qpsolvers")
    from scipy import sparse

    n, k = B.shape[0], A.shape[1]
    valid = np.isfinite(B).all(axis=1)
    G = A.T @ A
    L = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n))
    P = sparse.kron(sparse.diags(valid * 1.0), G) + smoothness * np.trace(G) / k * sparse.kron(
        L.T @ L, sparse.eye(k)
    )
    q = -(np.where(valid[:, None], B, 0.0) @ A).ravel()
    ub = None if upper is None else np.full(n * k, float(upper))
    Gc, h = (sparse.kron(sparse.eye(n), np.ones((1, k))).tocsc(), np.ones(n)) if convex else (None, None)
    x = qpsolvers.solve_qp(
        sparse.csc_matrix(2 * P), 2 * q, G=Gc, h=h, lb=np.zeros(n * k), ub=ub, solver="clarabel",
        tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10,
    )
    return x.reshape(n, k)


def jitter(W):
    return float(np.mean(np.abs(W[:-2] - 2 * W[1:-1] + W[2:])))


def test_zero_smoothness_is_per_frame_nnls():
    A, _, B = smooth_problem(1, n_frames=80)
    B[[4, 50]] = np.nan
    np.testing.assert_array_equal(solve_spacetime(A, B, smoothness=0.0), solve_nnls(A, B))


@pytest.mark.parametrize(
    ("upper", "convex", "gaps"),
    [(None, False, ()), (1.0, False, [(20, 26)]), (0.4, False, ()), (None, True, [(5, 7), (40, 52)]),
     (0.6, True, ())],
)
@pytest.mark.parametrize("smoothness", [0.05, 1.0, 30.0])
def test_spacetime_matches_clarabel(upper, convex, gaps, smoothness):
    A, _, B = smooth_problem(2, n_frames=90, m=20, k=5, noise=0.4, gaps=gaps)
    B *= 1.5  # let the bounds bite
    W = solve_spacetime(A, B, smoothness=smoothness, upper=upper, convex=convex)
    assert np.isfinite(W).all() and (W >= 0).all()
    if upper is not None:
        assert (W <= upper).all()
    if convex:
        assert (W.sum(axis=1) <= 1.0).all()
    R = spacetime_reference(A, B, smoothness, upper, convex)
    ours, theirs = objective(A, B, W, smoothness), objective(A, B, R, smoothness)
    assert ours <= theirs * (1 + 1e-6)
    assert theirs <= ours * (1 + 1e-6)  # Clarabel's own accuracy


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    k=st.integers(1, 8),
    n_frames=st.integers(3, 60),
    smoothness=st.floats(1e-3, 1e2),
    upper=st.sampled_from([None, 1.0, 0.5]),
    convex=st.booleans(),
)
def test_spacetime_random_problems_match_clarabel(seed, k, n_frames, smoothness, upper, convex):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((k + 8, k))
    W_true = np.clip(np.cumsum(rng.standard_normal((n_frames, k)) * 0.2, axis=0), 0.0, None)
    B = W_true @ A.T + 0.3 * rng.standard_normal((n_frames, k + 8))
    B[1:-1][rng.random(n_frames - 2) < 0.15] = np.nan
    W = solve_spacetime(A, B, smoothness=smoothness, upper=upper, convex=convex)
    assert (W >= 0).all() and (upper is None or (W <= upper).all())
    assert not convex or (W.sum(axis=1) <= 1.0).all()
    ours = objective(A, B, W, smoothness)
    R = spacetime_reference(A, B, smoothness, upper, convex)
    assert ours <= objective(A, B, R, smoothness) * (1 + 1e-6)


def test_smoothing_beats_per_frame_on_noisy_truth():
    A, W_true, B = smooth_problem(3, n_frames=800)
    raw = solve_nnls(A, B)
    smooth = solve_spacetime(A, B, smoothness=2.0, upper=1.0)
    assert np.abs(smooth - W_true).mean() < 0.7 * np.abs(raw - W_true).mean()
    assert jitter(smooth) <= 0.5 * jitter(raw)
    assert (smooth >= 0).all() and (smooth <= 1.0).all()


def test_smoothing_has_no_lag():
    A, W_true, B = smooth_problem(4, n_frames=1000)
    W = solve_spacetime(A, B, smoothness=2.0)
    lags = np.arange(-6, 7)
    for key in range(A.shape[1]):
        x, y = W_true[:, key] - W_true[:, key].mean(), W[:, key] - W[:, key].mean()
        corr = [np.dot(x[max(0, -lag) : len(x) - max(0, lag)], y[max(0, lag) : len(y) - max(0, -lag)])
                for lag in lags]
        assert lags[int(np.argmax(corr))] == 0


def test_gaps_are_bridged_and_ends_not_extrapolated():
    A, W_true, B = smooth_problem(5, n_frames=400, noise=0.3, gaps=[(0, 10), (100, 112), (390, 400)])
    W = solve_spacetime(A, B, smoothness=1.0, upper=1.0)
    assert np.isnan(W[:10]).all() and np.isnan(W[390:]).all()
    assert np.isfinite(W[10:390]).all()
    gap = slice(100, 112)
    assert np.abs(W[gap] - W_true[gap]).mean() < 0.1
    assert (W[10:390] >= 0).all() and (W[10:390] <= 1.0).all()


def test_convex_and_bounds_hold_exactly_when_smoothing():
    A, _, B = smooth_problem(6, n_frames=300, noise=0.5)
    W = solve_spacetime(A, 3.0 * B, smoothness=0.5, upper=0.7, convex=True)
    assert W.max() <= 0.7 and W.min() >= 0.0
    assert (W.sum(axis=1) <= 1.0).all()


def test_solve_weights_with_smoothness_bridges_missing_faces():
    rng = np.random.default_rng(14)
    keys = two_region_keys(rng)
    from scipy.ndimage import gaussian_filter1d

    W_true = np.clip(gaussian_filter1d(rng.standard_normal((200, 7)), 6.0, axis=0) * 3.0, 0.0, 1.0)
    points = keys.pose(W_true) + 0.05 * rng.standard_normal((200, 10, 3))
    points[50:55] = np.nan
    weights = solve_weights(Track(points, fps=30.0), keys, smoothness=0.5, upper=1.0)
    assert weights.names == keys.names
    assert np.isfinite(weights.values).all()
    assert np.abs(weights.values[50:55] - W_true[50:55]).mean() < 0.1
    raw = solve_weights(Track(points, fps=30.0), keys, upper=1.0).values
    assert np.isnan(raw[50:55]).all()
    assert jitter(weights.values) < jitter(raw[:50])


def test_looser_tolerance_is_still_close_and_feasible():
    A, _, B = smooth_problem(7, n_frames=300)
    tight = solve_spacetime(A, B, smoothness=1.0, upper=1.0)
    loose = solve_spacetime(A, B, smoothness=1.0, upper=1.0, tol=1e-3)
    assert (loose >= 0).all() and (loose <= 1.0).all()
    assert objective(A, B, loose, 1.0) <= objective(A, B, tight, 1.0) * (1 + 1e-3)
    with pytest.raises(InputError, match="tol must be"):
        solve_spacetime(A, B, smoothness=1.0, tol=0.0)
