"""Reconstruction error against the number of key shapes: the paper's comparison.

Chuang & Bregler compare their key-shape choices by the error of reconstructing the
performance from ``K`` key shapes, against PCA with ``K`` components. :func:`error_vs_k`
computes that curve per region for

``pca``
    mean + ``K`` principal components, unconstrained: the best any ``K``-dimensional
    (affine) model can do, an unreachable lower bound (its "keys" are not real frames and
    its weights may be negative);
``spread``, ``hull``
    the paper's two selection methods;
``spa``
    ours (the default of :func:`keyshape.keyshapes._search.find_keyshapes`).

For the selection methods each frame is fitted by its best blend ``0 <= w <= upper`` of
the keys (exact bounded NNLS), as the product solves it. Errors are RMS over the valid
frames and the region's landmarks, in % of the inter-ocular distance of the neutral
(:func:`keyshape.metrics.face_scale`; "% face size" for schemes without eye corners).

References
----------
.. [1] E. Chuang and C. Bregler, "Performance driven facial animation using blendshape
   interpolation", Stanford CS-TR-2002-02, 2002, section 4 (error against the number of
   key shapes, PCA as the baseline).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from itertools import islice

import numpy as np

from ..containers import Track
from ..decompose import check_upper
from ..exceptions import InputError
from ..metrics import face_scale
from . import _search as keyshapes
from . import _select
from ._search import candidate_frames, check_neutral_frame, check_regions, region_data
from ._select_pca import scatter

__all__ = ["CURVE_METHODS", "KCurve", "error_vs_k"]

CURVE_METHODS: tuple[str, ...] = ("pca", "spread", "hull", "spa")


@dataclass(frozen=True, eq=False)
class KCurve:
    """RMS reconstruction error against the number of key shapes, per method and region.

    Attributes
    ----------
    ks : (n_ks,) int
    errors : dict method -> dict region -> (n_ks,) float
        RMS error in ``unit`` for each ``K`` of ``ks``.
    unit : str
        ``"% inter-ocular"`` or ``"% face size"`` (see :func:`keyshape.metrics.face_scale`).
    scale : float
        The length (aligned units) that is 100 ``unit``.
    upper : float or None
        Upper bound of the weights in the fits (None: none).
    neutral_frame : int
    """

    ks: np.ndarray
    errors: dict[str, dict[str, np.ndarray]]
    unit: str
    scale: float
    upper: float | None
    neutral_frame: int

    @property
    def table(self) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
        """``{method: {region: (ks, errors)}}``, the input of :func:`keyshape.report.plots.error_vs_k`."""
        return {m: {r: (self.ks, e) for r, e in per_region.items()} for m, per_region in self.errors.items()}

    def rows(self) -> Iterator[tuple[str, str, int, float]]:
        """``(region, method, k, error)`` for every entry, region by region."""
        regions = next(iter(self.errors.values()), {})
        for region in regions:
            for method, per_region in self.errors.items():
                for k, error in zip(self.ks.tolist(), per_region[region].tolist()):
                    yield region, method, k, error


def error_vs_k(
    aligned: Track,
    *,
    regions: dict[str, np.ndarray],
    neutral_frame: int,
    ks: Iterable[int] = range(1, 31),
    methods: Iterable[str] = CURVE_METHODS,
    upper: float | None = None,
) -> KCurve:
    """RMS reconstruction error of each region for ``K`` key shapes, per method.

    The key sets are those :func:`keyshape.keyshapes._search.find_keyshapes` returns for each
    ``K`` (same candidates, same ``upper``); work is shared across ``K``: one PCA per
    region, ``spa``'s sets grown one from the other, every set fitted once. Beyond
    ``keyshapes.MAX_CANDIDATES`` candidate frames the sets come from the same pool of
    frames as there (see "Long takes" in :mod:`keyshape.keyshapes._search`) and each is fitted to
    every frame block by block; ``pca`` then takes the ``σ²`` as the eigenvalues of the
    scatter matrix. Errors are always over every valid frame.

    Parameters
    ----------
    aligned : Track
        ``points (n_frames, n_landmarks, n_dims)`` with head motion removed.
    regions : dict str -> (n_region_landmarks,) int, keyword-only
    neutral_frame : int, keyword-only
        A valid frame; deltas are measured from it and it is never a key.
    ks : iterable of int, keyword-only
        Numbers of keys, each in ``1 … n_valid_frames − 1``.
    methods : iterable of str, keyword-only
        Any of ``"pca"``, ``"spread"``, ``"hull"``, ``"spa"``.
    upper : float or None, keyword-only
        Upper bound of the weights of the selection methods' fits (``pca`` is unconstrained).

    Returns
    -------
    KCurve

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> perf = make_performance(n_keys=4, noise=0.0)
    >>> curve = error_vs_k(perf.track.with_points(perf.canonical), regions=perf.regions,
    ...                    neutral_frame=perf.neutral_frame, ks=[1, 2, 3], upper=1.0)
    >>> curve.unit, curve.errors["spa"]["upper"].round(6).tolist()
    ('% face size', [1.040287, 0.0, 0.0])
    """
    regions = check_regions(regions, aligned.n_landmarks)
    neutral_frame = check_neutral_frame(aligned, neutral_frame)
    upper = check_upper(upper)
    methods = _check_methods(methods)
    candidates = candidate_frames(aligned, neutral_frame)
    ks = _check_ks(ks, candidates.size)
    scale, unit = face_scale(aligned.points[neutral_frame])
    errors: dict[str, dict[str, np.ndarray]] = {m: {} for m in methods}
    for region, landmarks in regions.items():
        data = region_data(aligned, candidates, neutral_frame, landmarks)
        to_percent = 100.0 / (scale * np.sqrt((candidates.size + 1) * len(landmarks)))
        squared = _region_curves(data, ks, methods, upper)
        for method in methods:
            errors[method][region] = np.sqrt(squared[method]) * to_percent
    return KCurve(ks, errors, unit, scale, upper, neutral_frame)


def _region_curves(data: np.ndarray, ks: np.ndarray, methods: tuple[str, ...],
                   upper: float | None) -> dict[str, np.ndarray]:
    """method -> (n_ks,) summed squared errors over the valid frames (the neutral adds 0)."""
    pool = _select.pool(data, keyshapes.MAX_CANDIDATES)
    objective = _select.Objective(pool.X, upper)
    out = {}
    for method in methods:
        if method == "pca":
            out[method] = _pca_squared(data, ks)
            continue
        steps = _select.steps(pool.X, method, objective=objective, axes=pool.axes, q95=pool.q95)
        sets = list(islice(steps, int(ks.max())))
        if pool.whole:
            out[method] = np.array([objective(sets[k - 1]) for k in ks])
        else:  # the keys of the pool, their error over every frame
            out[method] = np.array([_select.squared_error(data, pool.rows[sets[k - 1]], upper) for k in ks])
    return out


def _pca_squared(data: np.ndarray, ks: np.ndarray) -> np.ndarray:
    """Squared error of mean + K principal components, over the candidates and the neutral.

    The best ``K``-dimensional affine fit leaves the trailing singular values (Eckart &
    Young 1936): ``E_K = Σ_{i > K} σ_i²`` of the centred data.
    """
    if len(data) > keyshapes.MAX_CANDIDATES:  # σ² as the eigenvalues of the scatter matrix: no copy of the data
        mean = data.sum(axis=0) / (len(data) + 1)
        squares = np.linalg.eigvalsh(scatter(data, mean) + np.outer(mean, mean))[::-1].clip(0.0)
    else:
        frames = np.vstack([data, np.zeros((1, data.shape[1]))])  # the neutral is the origin
        squares = np.linalg.svd(frames - frames.mean(axis=0), compute_uv=False) ** 2
    tail = np.concatenate([np.cumsum(squares[::-1])[::-1], [0.0]])  # tail[k] = Σ_{i >= k} σ_i²
    return tail[np.minimum(ks, squares.size)]


def _check_methods(methods) -> tuple[str, ...]:
    methods = tuple(methods)
    unknown = [m for m in methods if m not in CURVE_METHODS]
    if not methods or unknown:
        raise InputError(f"methods must be some of {CURVE_METHODS}; got {methods!r}")
    return methods


def _check_ks(ks, n_candidates: int) -> np.ndarray:
    values = np.array(list(ks))
    if values.ndim != 1 or not values.size or not np.issubdtype(values.dtype, np.integer):
        raise InputError(f"ks must be a non-empty sequence of ints; got {ks!r}")
    if values.min() < 1 or values.max() > n_candidates:
        raise InputError(f"ks must lie in 1..{n_candidates} (the valid frames besides the neutral); "
                         f"got {values.min()}..{values.max()}")
    return values.astype(int)
