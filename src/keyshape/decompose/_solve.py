"""Stage 4, decompose: every frame as a non-negative blend of the key shapes.

Chuang & Bregler write each frame as ``s_t ≈ s_neutral + Σ_i w_i (k_i − s_neutral)``,
``w ≥ 0`` (the paper's Eq. 1 in delta form), solved per region by non-negative least squares.
For a region with landmark indices ``keys.regions[r]`` and keys ``keys.keys_of(r)``::

    A   = deltas of the region's keys at its landmarks, flattened   (m, K)   m = n_landmarks·n_dims
    b_t = aligned frame t at those landmarks − neutral, flattened   (m,)

``A`` is the same for every frame, so the solvers work on the Gram form ``G = AᵀA`` (K × K) and
``c_t = Aᵀ b_t`` and treat all frames at once:

* :func:`solve_nnls` — exact per-frame (bounded) NNLS, vectorised over frames
  (:mod:`keyshape.decompose._nnls`: block principal pivoting plus a Lawson–Hanson active-set finish);
* :func:`solve_spacetime` — the whole sequence at once with a second-difference smoothness
  term, zero-phase by construction (:mod:`keyshape.decompose._spacetime`);
* :func:`solve_weights` — the stage function: Track + KeyShapes → Weights, region by region.

References
----------
Chuang, E. & Bregler, C. (2002). Performance driven facial animation using blendshape
interpolation. Stanford CS-TR-2002-02.
Lawson, C. L. & Hanson, R. J. (1974). *Solving Least Squares Problems*. Prentice-Hall.
Kim, J. & Park, H. (2011). Fast nonnegative matrix factorization: an active-set-like method and
comparisons. *SIAM J. Sci. Comput.* 33(6), 3261–3281.
"""

from __future__ import annotations

import numpy as np

from ..containers import KeyShapes, Track, Weights
from ..exceptions import InputError
from ._nnls import nnls_gram

# The smoothed and the weighted solves (_spacetime, _weighted) and the kernels of all solves (numba)
# are imported on first use: importing keyshape.decompose stays light.

__all__ = ["solve_nnls", "solve_spacetime", "solve_weights", "check_upper"]


def solve_nnls(
    A: np.ndarray, B: np.ndarray, *, upper: float | np.ndarray | None = None, convex: bool = False
) -> np.ndarray:
    """Exact non-negative least squares for many frames sharing one matrix.

    Each row ``b_t`` of ``B`` gives

    .. math::

        w_t = \\arg\\min_w \\lVert A w - b_t \\rVert^2
        \\quad\\text{s.t.}\\quad 0 \\le w \\le u, \\;\\; (\\textstyle\\sum_i w_i \\le 1),

    identical (to rounding) to ``scipy.optimize.nnls(A, b_t)`` when there is no upper
    bound, but fast: the Gram form ``G = AᵀA``, ``c_t = Aᵀb_t`` is formed once and block
    principal pivoting (Kim & Park 2011) runs compiled, frame by frame, finished by a
    Lawson–Hanson active-set step on any frame where pivoting stalls.

    Parameters
    ----------
    A : (m, n_keys) float
        The key deltas as columns.
    B : (n_frames, m) float
        The frames (minus the neutral) as rows; a row with a NaN gives a NaN row.
    upper : float, (n_keys,) float or None
        Upper bound ``u ≥ 0`` of the weights (``inf`` entries are unbounded); None for none.
    convex : bool
        Also require ``Σ_i w_i ≤ 1`` (the blend stays inside the keys' simplex).

    Returns
    -------
    (n_frames, n_keys) float
        The weights, within the bounds exactly.

    Notes
    -----
    A rank-deficient ``A`` (duplicate or zero keys, ``m < n_keys``) has no unique solution;
    a ridge of ``1e-10 · λ_max(AᵀA)`` is then added to ``AᵀA`` so that the smallest-norm blend
    among the (numerically) equally good ones is returned.

    References
    ----------
    Lawson & Hanson (1974), ch. 23; Júdice & Pires (1994); Kim & Park (2011).

    Examples
    --------
    >>> A = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    >>> solve_nnls(A, np.array([[2.0, -1.0, 2.0], [1.0, 1.0, 2.0]]))
    array([[2., 0.],
           [1., 1.]])
    """
    A, B = _check_system(A, B)
    return nnls_gram(A.T @ A, B @ A, _upper_bounds(upper, A.shape[1]), bool(convex))


def solve_spacetime(
    A: np.ndarray,
    B: np.ndarray,
    *,
    smoothness: float,
    upper: float | np.ndarray | None = None,
    convex: bool = False,
    tol: float = 1e-7,
) -> np.ndarray:
    """Weights of a whole sequence at once, with a temporal smoothness term and no lag.

    Solves

    .. math::

        \\min_W \\sum_t \\lVert A w_t - b_t \\rVert^2
              + μ \\sum_t \\lVert w_{t+1} - 2 w_t + w_{t-1} \\rVert^2
        \\quad\\text{s.t.}\\quad 0 \\le w_t \\le u, \\;\\; (\\textstyle\\sum_i w_{t,i} \\le 1),

    with ``μ = smoothness · trace(AᵀA) / n_keys`` (scale free: relative to the mean squared
    key delta). Every frame is fitted together with its neighbours on both sides, so the
    weights are smooth without the lag of a causal filter. ``smoothness = 0`` is
    :func:`solve_nnls`. The solver (ADMM in the eigenbasis of ``AᵀA``, compiled; active-set
    Newton steps with a banded Cholesky factorisation where ADMM stalls, as in long gaps;
    :mod:`keyshape.decompose._spacetime`) stops at a certified relative objective gap of ``tol``.

    Parameters
    ----------
    A : (m, n_keys) float
    B : (n_frames, m) float
        Rows with a NaN are gaps: their data term is absent and the smoothness term bridges
        them. Frames before the first or after the last finite row are NaN (not extrapolated).
    smoothness : float ≥ 0
    upper : float, (n_keys,) float or None
    convex : bool
        Also require ``Σ_i w_{t,i} ≤ 1``.
    tol : float in (0, 1)
        Relative accuracy of the objective, proven by a duality gap. 1e-7 (the default) is
        far below what shows in an animation; 1e-4 saves about a quarter of the time.

    Returns
    -------
    (n_frames, n_keys) float
        Within the bounds exactly.

    References
    ----------
    Boyd et al. (2011), ADMM; Hintermüller, Ito & Kunisch (2003), primal–dual active sets.

    Examples
    --------
    >>> A = np.eye(2)
    >>> B = np.array([[1.0, 0.0], [np.nan, np.nan], [1.0, 0.0], [1.0, 0.0]])
    >>> solve_spacetime(A, B, smoothness=1.0).round(6)
    array([[1., 0.],
           [1., 0.],
           [1., 0.],
           [1., 0.]])
    """
    A, B = _check_system(A, B)
    upper = _upper_bounds(upper, A.shape[1])
    return _solve_region(A, B, upper, _check_smoothness(smoothness), bool(convex), _check_tol(tol))


def solve_weights(
    track: Track,
    keys: KeyShapes,
    *,
    upper: float | np.ndarray | None = None,
    smoothness: float = 0.0,
    convex: bool = False,
    tol: float = 1e-7,
) -> Weights:
    """Blend weights of every frame of an aligned take, region by region.

    Parameters
    ----------
    track : Track
        Aligned landmarks ``(n_frames, n_landmarks, n_dims)`` in the key set's canonical
        coordinates (see :func:`keyshape.alignment._procrustes.align`); NaN frames have no face.
    keys : KeyShapes
        Neutral, key deltas and regions, with the same landmarks as ``track``.
    upper : float, (n_keys,) float or None
        Upper bound of each weight (in ``keys.names`` order); None for no bound.
    smoothness : float
        Weight ``λ ≥ 0`` of the temporal second-difference penalty. It is scale free: per
        region ``μ = λ · trace(AᵀA) / K``, i.e. relative to the mean squared key delta, in
        ``Σ_t ‖A w_t − b_t‖² + μ Σ_t ‖w_{t+1} − 2 w_t + w_{t−1}‖²``, solved over the whole
        sequence (no lag). 0 solves every frame on its own (the paper's NNLS).
    convex : bool
        Also require ``Σ_i w_i ≤ 1`` in each region and frame.
    tol : float
        Relative accuracy of the smoothed solve (see :func:`solve_spacetime`).

    Returns
    -------
    Weights
        ``values (n_frames, n_keys)`` in ``keys.names`` order, ``fps = track.fps``. With
        ``smoothness == 0`` frames without a face get NaN weights; with ``smoothness > 0``
        gaps between faces are bridged by the smoothness term, and only frames before the
        first or after the last face stay NaN (nothing is extrapolated).

    Examples
    --------
    >>> neutral = np.zeros((2, 2))
    >>> keys = KeyShapes(neutral, [[[1, 0], [0, 0]], [[0, 0], [0, 1]]], ("a", "b"), [0, 0],
    ...                  ("whole", "whole"), {"whole": [0, 1]})
    >>> track = Track([[[0.5, 0.0], [0.0, 2.0]], [[np.nan, 0], [0, 0]]], fps=30)
    >>> solve_weights(track, keys).values
    array([[0.5, 2. ],
           [nan, nan]])
    """
    track, keys = _check_take(track, keys)
    upper = _upper_bounds(upper, keys.n_keys)
    smoothness, tol = _check_smoothness(smoothness), _check_tol(tol)
    values = np.zeros((track.n_frames, keys.n_keys))
    for region, landmarks in keys.regions.items():
        ks = keys.keys_of(region)
        if len(ks):
            A, B = _region_system(track, keys, landmarks, ks)
            values[:, ks] = _solve_seen(A, B, track, landmarks, upper[ks], smoothness, bool(convex), tol)
    if smoothness == 0.0:
        values[~track.valid] = np.nan
    return Weights(values, keys.names, track.fps, track.frame_index, track.time)


def _region_system(track, keys, landmarks, ks):
    """``A (m, K)`` and ``B (n_frames, m)`` of one region (delta form, flattened)."""
    # k: key, p: region landmark, d: dimension
    A = keys.deltas[np.ix_(ks, landmarks)].reshape(len(ks), -1).T
    B = (track.points[:, landmarks] - keys.neutral[landmarks]).reshape(track.n_frames, -1)
    return A, B


def _solve_seen(A, B, track, landmarks, upper, smoothness, convex, tol):
    """One region's weights; hidden landmarks (``track.visibility`` < 1) weighted down (:mod:`._weighted`)."""
    if track.visibility is None or (track.visibility[:, landmarks] >= 1.0).all():
        return _solve_region(A, B, upper, smoothness, convex, tol)  # all seen: the unweighted fast path
    from ._weighted import coordinate_weights, solve_weighted

    weight = coordinate_weights(track.visibility[:, landmarks], track.n_dims)
    return solve_weighted(A, B, weight, lambda b: _solve_region(A, b, upper, smoothness, convex, tol),
                          smoothness=smoothness, upper=upper, convex=convex, mu=_mu(A.T @ A, smoothness), tol=tol)


def _solve_region(A, B, upper, smoothness, convex, tol=1e-7):
    """(n_frames, K): per-frame NNLS, or the spacetime solve when ``smoothness > 0``."""
    C, sq = reduce_rows(A, B)
    return solve_reduced(A.T @ A, C, sq, upper, smoothness, convex, tol)


def _mu(G: np.ndarray, smoothness: float) -> float:
    """The smoothness term's weight ``μ``: ``smoothness`` times the mean of ``diag G`` (so it does
    not depend on the landmarks' units or number)."""
    return smoothness * float(np.trace(G)) / max(G.shape[0], 1)


def reduce_rows(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Gram form of frames ``B (n, m)``: ``C = B A (n, K)`` and ``‖b_t‖² (n,)``, NaN rows
    (frames without a face) NaN in both. All the solvers read of the frames."""
    return B @ A, np.einsum("fm,fm->f", B, B)


def solve_reduced(G, C, sq, upper, smoothness, convex, tol=1e-7):
    """(n_frames, K) weights of one region from its Gram form: ``G = AᵀA (K, K)``, ``C (n, K)`` and
    ``sq (n,)`` from :func:`reduce_rows` (NaN rows are frames without data)."""
    if smoothness == 0.0:
        return nnls_gram(G, C, upper, convex)
    valid = np.isfinite(sq)
    C = np.where(valid[:, None], C, 0.0)
    mu = _mu(G, smoothness)
    if mu == 0.0:  # all keys are zero: nothing to smooth
        return np.where(valid[:, None], nnls_gram(G, C, upper, convex), np.nan)
    from ._spacetime import spacetime_gram

    return spacetime_gram(G, C, valid, sq, mu, upper, convex, rtol=tol)


# --------------------------------------------------------------------------- validation


def _check_system(A, B):
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    if A.ndim != 2:
        raise InputError(f"A must have shape (m, n_keys); got {A.shape}")
    if B.ndim != 2 or B.shape[1] != A.shape[0]:
        raise InputError(f"B must have shape (n_frames, {A.shape[0]}); got {B.shape}")
    if not np.isfinite(A).all():
        raise InputError("A must be finite; it has NaN or infinite entries")
    return A, B


def check_upper(upper) -> float | None:
    """One upper bound for every weight: None (no bound) or a number > 0; returns it as a float.

    The rule of the key-shape search and of the error measures, which take one bound; the solvers
    also take one bound per key (``_upper_bounds``).
    """
    if upper is None:
        return None
    try:
        value = float(upper)
    except (TypeError, ValueError):
        value = float("nan")
    if not value > 0:
        raise InputError(f"upper must be None or a number > 0; got {upper!r}")
    return value


def _upper_bounds(upper, n_keys):
    """(n_keys,) float upper bounds (``inf`` = none) from None, a scalar or a vector."""
    if upper is None:
        return np.full(n_keys, np.inf)
    u = np.asarray(upper, dtype=float)
    if u.ndim == 0:
        u = np.full(n_keys, float(u))
    if u.shape != (n_keys,) or np.isnan(u).any() or (u < 0).any():
        raise InputError(f"upper must be None, a number >= 0 or {n_keys} numbers >= 0; got {upper!r}")
    return u


def _check_smoothness(smoothness):
    value = float(smoothness)
    if not np.isfinite(value) or value < 0:
        raise InputError(f"smoothness must be a finite number >= 0; got {smoothness!r}")
    return value


def _check_tol(tol):
    value = float(tol)
    if not 0.0 < value < 1.0:
        raise InputError(f"tol must be a number in (0, 1); got {tol!r}")
    return value


def _check_take(track, keys):
    if not isinstance(track, Track) or not isinstance(keys, KeyShapes):
        raise InputError(
            f"solve_weights needs a Track and a KeyShapes; got {type(track).__name__} and "
            f"{type(keys).__name__}"
        )
    if track.points.shape[1:] != keys.neutral.shape:
        raise InputError(
            f"the track has landmarks of shape {track.points.shape[1:]} but the key shapes "
            f"{keys.neutral.shape}; align the track onto the key set first"
        )
    return track, keys
