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
  ``Aᵀ V_t A``.
* With smoothing, majorise-minimise (Kiers 1997; Srebro & Jaakkola 2003): as ``V_t ⪯ I``,
  ``‖V_t^{1/2}(A w − b_t)‖² ≤ ‖A w − \\tilde b_t‖² + const`` with the hidden part filled in
  from the current fit, ``\\tilde b_t = v_t ⊙ b_t + (1 − v_t) ⊙ A w_t^{(k)}``; each step is the
  unweighted solve on ``\\tilde B`` (the shared Gram matrix, the compiled kernels) and the
  objective never increases.

Frames with every landmark seen are not touched: a track without visibility, or an all-visible
region, takes the unweighted path unchanged.

References
----------
Kiers, H. A. L. (1997). Weighted least squares fitting using ordinary least squares algorithms.
*Psychometrika* 62(2), 251–266.
Srebro, N. & Jaakkola, T. (2003). Weighted low-rank approximations. *ICML*.
O'Donoghue, B. & Candès, E. (2015). Adaptive restart for accelerated gradient schemes.
*Found. Comput. Math.* 15, 715–732.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from ..exceptions import ConvergenceWarning
from ._nnls import nnls_gram

__all__ = ["HIDDEN", "coordinate_weights", "solve_weighted"]

HIDDEN = 0.02  # a frame whose region keeps less of its weight (mean visibility) has no data term
MAX_STEPS = 500  # majorise-minimise steps of the smoothed solve
STEP_TOL = 1e-5  # ... until no weight moves by more than this


def coordinate_weights(seen: np.ndarray, n_dims: int) -> np.ndarray:
    """(n_frames, n_region_landmarks · n_dims): each landmark's visibility on its coordinates."""
    # rows of B are flattened (landmark, dimension) pairs, landmark-major
    return np.repeat(np.asarray(seen, dtype=float), n_dims, axis=1)


def solve_weighted(A: np.ndarray, B: np.ndarray, weight: np.ndarray, solve: Callable[[np.ndarray], np.ndarray], *,
                   smoothness: float, upper: np.ndarray, convex: bool) -> np.ndarray:
    """(n_frames, K) weights of one region with per-frame, per-coordinate data weights.

    Parameters
    ----------
    A : (m, K) float
    B : (n_frames, m) float, NaN rows are frames without a face
    weight : (n_frames, m) float in [0, 1]
    solve : the unweighted solve of the region, ``B (n_frames, m) -> (n_frames, K)`` (NaN rows gaps)
    smoothness : float, 0 for per-frame solves
    upper : (K,) float; convex : bool (for the exact per-frame solves)
    """
    B = np.array(B, dtype=float)
    gone = weight.mean(axis=1) < HIDDEN
    B[gone] = np.nan
    partial = np.flatnonzero(np.isfinite(B).all(axis=1) & (weight < 1.0).any(axis=1))
    W = solve(B)
    if not partial.size:
        return W
    if smoothness == 0.0:
        for t in partial:
            Av = A * weight[t][:, None]  # V_t A
            W[t] = nnls_gram(Av.T @ A, (B[t] @ Av)[None], upper, convex)[0]
        return W
    return _majorise(A, B, weight[partial], partial, W, solve)


def _majorise(A, B, v, partial, W, solve):
    """Majorise-minimise steps from ``W`` until the weights settle (see the module notes).

    Each step is a proximal-gradient step in the metric ``AᵀA`` (the smoothness and the bounds
    are its proximal part), so Nesterov's extrapolation applies: steps from ``Y = W_k + β_k
    (W_k − W_{k−1})``, restarted whenever a step turns back (O'Donoghue & Candès 2015).
    """
    seen, Y, momentum = v * B[partial], W, 1.0
    for _ in range(MAX_STEPS):
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
    warnings.warn(f"the visibility-weighted solve stopped after {MAX_STEPS} steps with weights still moving by "
                  f"{step:.2g}", ConvergenceWarning, stacklevel=4)
    return W
