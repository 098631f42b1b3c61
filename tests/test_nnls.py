"""The per-frame solver's parts: the compiled block principal pivoting and the monotone
active-set finish it hands stalled frames to."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize

from keyshape.decompose import _kernels_nnls, _nnls


def bounded_reference(A, B, upper):
    """``min ‖Aw − b‖², 0 ≤ w ≤ u`` per row by scipy's bounded-variable least squares."""
    return np.array([scipy.optimize.lsq_linear(A, b, bounds=(0.0, upper), method="bvls", tol=1e-14).x
                     for b in B])


def problem(seed, n=200, k=6, m=20):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((m, k)) @ (np.eye(k) + 0.6)  # correlated keys
    B = rng.random((n, k)) @ A.T * 1.5 + 0.3 * rng.standard_normal((n, m))
    return A, B


def test_block_pivoting_flags_a_singular_free_block():
    G = np.array([[1.0, 0.0], [0.0, -1.0]])  # not positive definite
    state = np.full((1, 2), _nnls.FREE, np.int8)
    X = np.empty((1, 2))
    stalled = _kernels_nnls.block_pivoting(G, np.array([[1.0, 1.0]]), np.full(2, np.inf), False, state, X)
    assert stalled.tolist() == [True]


@pytest.mark.parametrize("upper", [np.inf, 0.7])
def test_block_pivoting_solves_and_classifies(upper):
    A, B = problem(1)
    gram = _nnls.Gram.from_matrix(A.T @ A)
    u = np.full(A.shape[1], upper)
    C = B @ A
    state = _nnls.initial_state(C @ gram.H, u)
    X = np.empty(C.shape)
    stalled = _kernels_nnls.block_pivoting(gram.G, C, u, bool(np.isfinite(upper)), state, X)
    assert not stalled.any()
    np.testing.assert_allclose(X, bounded_reference(A, B, u), atol=1e-8)
    assert ((state == _nnls.LOWER) == (X <= 1e-12)).all()
    assert ((state == _nnls.UPPER) == (X >= upper - 1e-12)).all()


@pytest.mark.parametrize("upper", [np.inf, 0.7])
def test_stalled_frames_are_finished_by_the_active_set_method(monkeypatch, upper):
    """Every frame handed over as stalled, from zero: the finish alone must be exact."""

    def stall_everything(G, C, upper, bounded, state, X):
        X[:] = 0.0
        state[:] = _nnls.LOWER
        return np.ones(len(C), bool)

    monkeypatch.setattr(_kernels_nnls, "block_pivoting", stall_everything)
    A, B = problem(2, n=60)
    u = np.full(A.shape[1], upper)
    W = _nnls.nnls_gram(A.T @ A, B @ A, u)
    np.testing.assert_allclose(W, bounded_reference(A, B, u), atol=1e-8)
