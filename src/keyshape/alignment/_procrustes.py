"""Stage 2, ALIGN: remove rigid head motion from a landmark track.

Each frame is mapped onto a canonical reference shape by the similarity transform
(rotation, translation, isotropic scale) that best fits a few *stable* landmarks
(eye corners, nose bridge, temples), in the least-squares sense of Umeyama (1991).
The transform is then undone on every landmark, so what remains is expression.

    Track (image) ──align──▶ Track (canonical) + Poses      x_image = s · R @ x_canonical + t

References
----------
.. [1] S. Umeyama, "Least-squares estimation of transformation parameters between two
   point patterns", IEEE TPAMI 13(4):376-380, 1991.
.. [2] J. C. Gower, "Generalized Procrustes analysis", Psychometrika 40:33-51, 1975.
.. [3] E. Chuang and C. Bregler, "Performance driven facial animation using blendshape
   interpolation", Stanford CS-TR-2002-02, 2002 (2D normalisation before decomposition).
"""

from __future__ import annotations

import warnings

import numpy as np

from ..containers import Poses, Track
from ..exceptions import DegenerateFrameWarning, InputError, KeyshapeError

__all__ = ["procrustes", "align", "choose_neutral", "to_canonical"]


def procrustes(source: np.ndarray, target: np.ndarray, *, scale: bool = True) -> Poses:
    """Similarity transforms mapping ``source`` points onto ``target`` (Umeyama 1991).

    Finds, per frame, the proper rotation ``R`` (det +1, never a reflection), translation
    ``t`` and scale ``s`` minimising ``Σ_p |target_p - (s · R @ source_p + t)|²``.
    All frames are solved at once with one batched SVD.

    Parameters
    ----------
    source : (n_points, d) or (n_frames, n_points, d) float, d in {2, 3}
    target : (n_points, d) or (n_frames, n_points, d) float
        Broadcast against ``source`` over frames. A frame with any NaN gives a NaN pose.
    scale : bool, keyword-only
        Estimate the scale; if False, ``s = 1``.

    Returns
    -------
    Poses
        ``n_frames`` transforms (1 if neither input has a frame axis), with
        ``target ≈ poses.to_image(source)``. Degenerate frames (too few distinct points)
        have NaN poses and raise a :class:`DegenerateFrameWarning`.

    References
    ----------
    .. [1] Umeyama (1991), Eqs. (34)-(42).

    Examples
    --------
    >>> source = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    >>> target = 2.0 * source[:, ::-1] * [1, -1] + [3.0, 4.0]   # rotate -90°, scale 2, shift
    >>> poses = procrustes(source, target)
    >>> float(poses.scales[0]), poses.translations[0].round(6).tolist()
    (2.0, [3.0, 4.0])
    """
    src, dst = _check_pair(source, target)
    n_frames, d = src.shape[0], src.shape[2]
    rotations = np.full((n_frames, d, d), np.nan)
    translations = np.full((n_frames, d), np.nan)
    scales = np.full(n_frames, np.nan)
    shared = n_frames > 1 and src.strides[0] == 0  # one source shape for every frame (align's reference)
    ok = np.isfinite(src[:1] if shared else src).all(axis=(1, 2)) & np.isfinite(dst).all(axis=(1, 2))
    if ok.any():
        rot, tra, sca, good = _umeyama(src[:1] if shared else src[ok], dst[ok], scale=scale)
        rotations[ok], translations[ok], scales[ok] = rot, tra, sca
        ok[ok] = good
        rotations[~ok], translations[~ok], scales[~ok] = np.nan, np.nan, np.nan
        if not good.all():
            warnings.warn(
                f"{int((~good).sum())} frame(s) have degenerate stable points; their poses are NaN",
                DegenerateFrameWarning,
                stacklevel=2,
            )
    return Poses(rotations, translations, scales)


def _check_pair(source, target) -> tuple[np.ndarray, np.ndarray]:
    """Broadcast ``source`` and ``target`` to ``(n_frames, n_points, d)`` float arrays."""
    src, dst = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    for name, arr in (("source", src), ("target", dst)):
        if arr.ndim not in (2, 3) or arr.shape[-1] not in (2, 3):
            raise InputError(f"{name} must have shape ([n_frames,] n_points, 2 or 3); got {arr.shape}")
    if src.shape[-2:] != dst.shape[-2:]:
        raise InputError(f"source and target must have the same points; got {src.shape} and {dst.shape}")
    src, dst = (src[None] if src.ndim == 2 else src), (dst[None] if dst.ndim == 2 else dst)
    try:
        shape = np.broadcast_shapes(src.shape, dst.shape)
    except ValueError:
        raise InputError(f"source and target frames differ: {src.shape} and {dst.shape}") from None
    return np.broadcast_to(src, shape), np.broadcast_to(dst, shape)


def _umeyama(src: np.ndarray, dst: np.ndarray, *, scale: bool):
    """Batched Umeyama kernel on finite frames: ``dst (n_frames, n_points, d)`` and ``src`` of the
    same shape, or ``(1, n_points, d)``: one source for every frame (a reference shape), whose
    terms are then computed once.

    Returns rotations ``(n_frames, d, d)``, translations ``(n_frames, d)``, scales
    ``(n_frames,)`` and a ``(n_frames,)`` bool mask of well-posed frames.
    """
    n = len(dst)
    # means and centring as einsum and per coordinate: the sums of x.mean(axis=1), x - μ[:, None], in
    # loops over the points rather than over the d coordinates of each point
    mu_src, mu_dst = np.einsum("fpi->fi", src) / src.shape[1], np.einsum("fpi->fi", dst) / dst.shape[1]
    src_c, dst_c = _minus(src, mu_src), _minus(dst, mu_dst)
    # Eq. (38): cross-covariance Σ_xy = 1/n Σ_p (y_p - μ_y)(x_p - μ_x)ᵀ.  f: frame, p: point
    if len(src) == 1 < n:  # Σ[f, i, j] = Σ_p dst_c[f, p, i] src_c[p, j]: one matrix product
        cov = np.tensordot(dst_c, src_c[0], axes=([1], [0])) / src.shape[1]
    else:
        cov = np.einsum("fpi,fpj->fij", dst_c, src_c) / src.shape[1]
    rotations, trace, good = _rotations(cov)
    var_src = (src_c**2).sum(axis=(1, 2)) / src.shape[1]  # Eq. (36): σ²_x, (n_frames,) or (1,)
    good &= var_src > 0
    scales = trace / np.where(good, var_src, 1.0) if scale else np.ones(n)  # Eq. (42): s = tr(D S) / σ²_x
    # Eq. (41): t = μ_y - s R μ_x.
    translations = mu_dst - scales[:, None] * (rotations @ mu_src[:, :, None])[:, :, 0]
    return rotations, translations, scales, good


def _rotations(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Umeyama's rotations ``R = U S Vᵀ`` of cross-covariances ``cov (n, d, d)`` (Eqs. 39, 40, 43), the
    ``(n,)`` traces ``tr(Rᵀ Σ) = tr(D S)`` and the ``(n,)`` bool well-posed frames (rank ≥ d - 1).

    In 3D a frame whose ``Σ`` is well conditioned with ``det Σ > 0`` (every real face) has ``S = I``
    and ``R = U Vᵀ``, the orthogonal factor of the polar decomposition ``Σ = R H``: found by Newton's
    iteration (:func:`_polar`, a few vectorised steps instead of one LAPACK call per frame). The
    others (reflections, near-degenerate point sets, 2D) take the SVD.
    """
    n, d = cov.shape[0], cov.shape[2]
    rotations, trace, good = np.empty_like(cov), np.empty(n), np.ones(n, dtype=bool)
    rest = np.ones(n, dtype=bool)
    if d == 3 and n:
        polar, rest = _polar(cov)
        rotations[~rest] = polar
        trace[~rest] = np.einsum("fij,fij->f", polar, cov[~rest])
    if rest.any():
        u, sv, vt = np.linalg.svd(cov[rest])
        sign = np.sign(np.linalg.det(u) * np.linalg.det(vt))
        sign[sign == 0] = 1.0
        s_diag = np.ones((len(sv), d))
        s_diag[:, -1] = sign
        rotations[rest] = (u * s_diag[:, None, :]) @ vt  # Eq. (40): R = U S Vᵀ
        trace[rest] = (sv * s_diag).sum(axis=1)
        good[rest] = sv[:, max(d - 2, 0)] > 1e-12 * np.maximum(sv[:, 0], 1e-300)
    return rotations, trace, good


# Row i of the cofactor matrix of a 3 × 3 X is x_{i+1} × x_{i+2}: entry (i, j) is
# X[i+1, j+1] X[i+2, j+2] - X[i+1, j+2] X[i+2, j+1] (indices mod 3), gathered from X's 9 entries.
_I, _J = np.divmod(np.arange(9), 3)
_COF = [((_I + a) % 3) * 3 + (_J + b) % 3 for a, b in ((1, 1), (2, 2), (1, 2), (2, 1))]
_POLAR_COND = 1e-6  # det Σ / ‖Σ‖_F³ above this (σ_min / σ_max > 1e-6): Newton's iteration is used
_POLAR_STEPS = 20  # Newton steps at most; it converges in 5 or 6 on a face's stable points
_POLAR_TOL = 1e-9  # the largest move of an entry of X before the final step (see _polar)


def _polar(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthogonal polar factors ``(m, 3, 3)`` of the frames of ``cov (n, 3, 3)`` that are not in the
    returned ``(n,)`` bool mask (those left out: ``det Σ`` not clearly positive, or no convergence).

    Scaled Newton iteration ``X ← (ζ X + X⁻ᵀ / ζ) / 2``, ``X⁻ᵀ = cof(X) / det X``, with the
    Frobenius-norm scaling ``ζ = (‖X⁻¹‖ / ‖X‖)^½`` (Higham 1986; Higham, *Functions of Matrices*,
    2008, §8.6), until a step moves no entry by more than 1e-9: the error before that step was
    about its move, so after it (the iteration converges quadratically) it is below
    ``‖X⁻¹‖ · 1e-18 / 2``, rounding. The factor agrees with ``U Vᵀ`` of the SVD to rounding.
    """
    flat = cov.reshape(len(cov), 9)
    cof = flat[:, _COF[0]] * flat[:, _COF[1]] - flat[:, _COF[2]] * flat[:, _COF[3]]
    det = np.einsum("fj,fj->f", flat[:, :3], cof[:, :3])
    with np.errstate(invalid="ignore"):
        ok = det > _POLAR_COND * np.einsum("fj,fj->f", flat, flat) ** 1.5  # False for NaN
    x, todo = flat[ok], np.arange(len(cov))[ok]
    for _ in range(_POLAR_STEPS):
        cof = x[:, _COF[0]] * x[:, _COF[1]] - x[:, _COF[2]] * x[:, _COF[3]]
        det = np.einsum("fj,fj->f", x[:, :3], cof[:, :3])
        zeta = np.sqrt(np.sqrt(np.einsum("fj,fj->f", cof, cof) / np.einsum("fj,fj->f", x, x)) / det)
        step = 0.5 * (zeta[:, None] * x + cof / (zeta * det)[:, None])
        moved, x = np.abs(step - x), step
        if not moved.max(initial=0.0) > _POLAR_TOL:
            break
    done = moved.max(axis=1, initial=0.0) <= _POLAR_TOL
    rest = np.ones(len(cov), dtype=bool)
    rest[todo[done]] = False
    return x[done].reshape(-1, 3, 3), rest


def align(
    track: Track, *, reference: np.ndarray | int, stable: np.ndarray, scale: bool = True
) -> tuple[Track, Poses]:
    """Remove head motion: map every frame onto ``reference`` using the stable landmarks.

    For each frame the similarity ``x_image = s · R @ x_canonical + t`` is fitted from the
    ``stable`` landmarks of ``reference`` to those of the frame (Umeyama 1991), then
    inverted on all landmarks: ``x_canonical = Rᵀ (x_image - t) / s``. The work is 3D when
    the track has z, 2D otherwise. NaN frames stay NaN, with NaN poses.

    Parameters
    ----------
    track : Track
        ``points (n_frames, n_landmarks, d)`` in image pixels.
    reference : (n_landmarks, d) float or int, keyword-only
        The canonical shape, or the index of a frame of ``track`` to use as one.
    stable : (n_stable,) int, keyword-only
        Landmarks that move only with the head (at least 2 in 2D, 3 in 3D).
    scale : bool, keyword-only
        Remove scale as well (default); if False, poses have unit scale.

    Returns
    -------
    aligned : Track
        Same metadata, ``points`` in the reference's coordinates.
    poses : Poses
        ``n_frames`` head transforms, canonical → image.

    References
    ----------
    .. [1] Umeyama (1991); Chuang & Bregler (2002), section 3 (normalisation).

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> perf = make_performance(n_frames=20, noise=0.0)
    >>> aligned, poses = align(perf.track, reference=perf.neutral, stable=perf.stable)
    >>> bool(np.allclose(poses.scales, perf.true_poses.scales))
    True
    """
    ref = _check_reference(track, reference)
    stable = _check_indices(stable, track.n_landmarks, name="stable")
    poses = procrustes(ref[stable], track.points[:, stable], scale=scale)
    return track.with_points(to_canonical(track.points, poses)), poses


_CHUNK_BYTES = 1 << 20  # points transformed at a time by to_canonical: the temporaries stay in a core's cache


def to_canonical(points: np.ndarray, poses: Poses) -> np.ndarray:
    """Invert the poses: ``Rᵀ (x - t) / s`` for points ``(n_frames, n_points, d)`` (read-only result).

    ``align`` is :func:`procrustes` on the stable points, then this on every landmark; a caller
    that streams a take does the two steps chunk by chunk, on the landmarks it needs.
    """
    # f: frame, p: point, i/j: dimension. Rᵀ (x - t) per point is the row (x - t) @ R:
    # out[f, p, i] = Σ_j (x[f, p, j] - t[f, j]) · R[f, j, i] / s[f], one batched matmul per chunk
    scaled = poses.rotations / poses.scales[:, None, None]
    out = np.empty(points.shape, dtype=np.result_type(points.dtype, scaled.dtype))
    step = max(1, _CHUNK_BYTES // max(out.itemsize * points.shape[1] * points.shape[2], 1))
    for lo in range(0, len(points), step):
        hi = lo + step
        np.matmul(_minus(points[lo:hi], poses.translations[lo:hi]), scaled[lo:hi], out=out[lo:hi])
    out.flags.writeable = False  # a Track takes it without a copy
    return out


def _minus(points: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``points (n, n_points, d) - vectors (n, d)[:, None]``, one coordinate at a time: numpy's loop
    then runs over the points, not over the d coordinates of each point (several times faster)."""
    out = np.empty(np.broadcast_shapes(points.shape, (len(vectors), 1, vectors.shape[1])),
                   dtype=np.result_type(points, vectors))
    for j in range(out.shape[2]):
        np.subtract(points[:, :, j], vectors[:, j, None], out=out[:, :, j])
    return out


def _check_reference(track: Track, reference) -> np.ndarray:
    if isinstance(reference, (int, np.integer)):
        frame = int(reference)
        if not (-track.n_frames <= frame < track.n_frames) or not track.valid[frame]:
            raise InputError(f"reference frame must be a valid frame of the track; got {reference}")
        return track.points[frame]
    ref = np.asarray(reference, dtype=float)
    if ref.shape != track.points.shape[1:]:
        raise InputError(f"reference must have shape {track.points.shape[1:]}; got {ref.shape}")
    if not np.isfinite(ref).all():
        raise InputError("reference must be finite; got NaN or inf values")
    return ref


def _check_indices(indices, n_landmarks: int, *, name: str) -> np.ndarray:
    """Validate landmark indices; return them as a 1-D int array."""
    ix = np.asarray(indices)
    if ix.ndim != 1 or ix.size == 0 or not np.issubdtype(ix.dtype, np.integer):
        raise InputError(f"{name} must be a non-empty 1-D array of landmark indices; got {indices!r}")
    if ix.min() < -n_landmarks or ix.max() >= n_landmarks:
        raise InputError(f"{name} indices must lie in 0..{n_landmarks - 1}; got {ix.min()}..{ix.max()}")
    return ix % n_landmarks


def choose_neutral(track: Track, *, stable: np.ndarray, regions: dict | None = None) -> int:
    """Pick the most typical, resting frame of a take as the neutral face.

    Method: (1) align every valid frame onto the per-landmark median of the raw frames,
    using the stable landmarks; (2) align again onto the per-landmark mean of the result
    (one step of generalised Procrustes analysis, Gower 1975); (3) return the valid frame
    nearest, in RMS distance over the landmarks of ``regions``, to the per-landmark
    median of the aligned shapes. A talking face spends most of its time near rest, so the
    median shape is close to rest, and the nearest real frame is a typical resting frame.

    Parameters
    ----------
    track : Track
        ``points (n_frames, n_landmarks, d)``, image or canonical coordinates.
    stable : (n_stable,) int, keyword-only
        Landmarks that move only with the head.
    regions : dict str -> (n_region_landmarks,) int, optional, keyword-only
        Landmarks that count in the distance (their union); all landmarks if None.

    Returns
    -------
    int
        Index of a valid (non-NaN) frame.

    Raises
    ------
    KeyshapeError
        If the track has no valid frame.

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> perf = make_performance(n_frames=60)
    >>> frame = choose_neutral(perf.track, stable=perf.stable)
    >>> bool(perf.track.valid[frame])
    True
    """
    valid = np.flatnonzero(track.valid)
    if valid.size == 0:
        raise KeyshapeError("cannot choose a neutral frame: the track has no frame with a face")
    stable = _check_indices(stable, track.n_landmarks, name="stable")
    raw = points = track.points[valid]
    for step in range(2):  # the median start, then one GPA iteration onto the mean
        reference = np.median(raw, axis=0) if step == 0 else np.nanmean(points, axis=0)
        points = to_canonical(raw, procrustes(reference[stable], raw[:, stable]))
    return int(valid[_nearest_to_median(points, _region_landmarks(regions, track.n_landmarks))])


def _region_landmarks(regions: dict | None, n_landmarks: int) -> np.ndarray:
    if not regions:
        return np.arange(n_landmarks)
    ix = [_check_indices(v, n_landmarks, name=f"regions[{k!r}]") for k, v in regions.items()]
    return np.unique(np.concatenate(ix))


def _nearest_to_median(points: np.ndarray, landmarks: np.ndarray) -> int:
    """Index of the shape ``(n_frames, n_landmarks, d)`` nearest the per-landmark median."""
    sub = points[:, landmarks]
    ok = np.isfinite(sub).all(axis=(1, 2))
    median = np.median(sub[ok], axis=0)
    dist = np.where(ok, ((sub - median) ** 2).sum(axis=2).mean(axis=1), np.inf)
    return int(np.argmin(dist))
