"""Stage 3, KEYSHAPES: discover the key shapes of a performance.

Key shapes are *real frames* of the aligned take that span the actor's expression space,
chosen per region (e.g. upper = brows + eyes, lower = mouth + jaw) so that a few shapes
combine freely. Every frame is later written as a non-negative blend of them
(Chuang & Bregler 2002). Selection works, per region, on the data matrix

    X (n_candidates, n_region_landmarks · n_dims) = candidate frames − neutral frame

whose rows are all valid frames but the neutral one.

Methods
-------
``"spread"``
    The paper's first method: frames with extreme (largest and smallest) projections on
    each principal component in turn.
``"hull"``
    The paper's second method: vertices of the convex hull of the first principal
    components (3, or the rank of ``X`` if lower).
``"spa"`` (default)
    Successive projection (Gillis & Vavasis 2014), the provably robust algorithm for
    separable non-negative factorisation, refined by exchanges that lower the
    non-negative reconstruction error of all frames. If that local search ends above
    the error of the ``spread`` or ``hull`` set, it is rerun from the better of those,
    so ``spa`` is never worse than the paper's methods.

References
----------
.. [1] E. Chuang and C. Bregler, "Performance driven facial animation using blendshape
   interpolation", Stanford CS-TR-2002-02, 2002.
.. [2] N. Gillis and S. A. Vavasis, "Fast and robust recursive algorithms for separable
   nonnegative matrix factorization", IEEE TPAMI 36(4):698-714, 2014.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from . import _select
from .containers import KeyShapes, Track
from .exceptions import InputError

__all__ = ["find_keyshapes", "METHODS"]

Method = Literal["spa", "spread", "hull"]
METHODS: tuple[str, ...] = ("spa", "spread", "hull")


def find_keyshapes(
    aligned: Track,
    *,
    regions: dict[str, np.ndarray],
    n_keys: int | dict[str, int] = 8,
    method: Method = "spa",
    neutral_frame: int,
    stable: np.ndarray | None = None,
) -> KeyShapes:
    """Choose ``n_keys`` real frames per region as key shapes.

    Parameters
    ----------
    aligned : Track
        ``points (n_frames, n_landmarks, n_dims)`` with head motion removed (see ``align``).
    regions : dict str -> (n_region_landmarks,) int, keyword-only
        Landmark indices of each region; ``{"whole": np.arange(n_landmarks)}`` for one.
    n_keys : int or dict str -> int, keyword-only
        Key shapes per region (the same for all, or one per region).
    method : {"spa", "spread", "hull"}, keyword-only
    neutral_frame : int, keyword-only
        A valid frame; it is never a key, and the deltas are measured from it.
    stable : (n_stable,) int, optional, keyword-only
        The landmarks used for alignment, recorded in the result.

    Returns
    -------
    KeyShapes
        Keys named ``f"{region}_{i:02d}"``, ``frames`` the source frame of each (never
        the neutral frame nor a NaN frame, distinct within a region), ``deltas`` the key
        frame minus the neutral frame on the region's landmarks and zero elsewhere.

    Raises
    ------
    InputError
        For an unknown method, a bad region or neutral frame, or too few frames.

    References
    ----------
    .. [1] Chuang & Bregler (2002), section 4; Gillis & Vavasis (2014), Algorithm 1.

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> from keyshape.align import align
    >>> perf = make_performance(n_keys=4, noise=0.0)
    >>> aligned, _ = align(perf.track, reference=perf.neutral, stable=perf.stable)
    >>> keys = find_keyshapes(aligned, regions=perf.regions, n_keys=2, neutral_frame=perf.neutral_frame)
    >>> keys.names
    ('upper_00', 'upper_01', 'lower_00', 'lower_01')
    >>> sorted(keys.frames.tolist()) == sorted(perf.extreme_frames.tolist())
    True
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}; got {method!r}")
    regions = _check_regions(regions, aligned.n_landmarks)
    counts = _check_counts(n_keys, regions)
    neutral_frame = _check_neutral(neutral_frame, aligned)
    candidates = np.flatnonzero(aligned.valid)
    candidates = candidates[candidates != neutral_frame]
    neutral = aligned.points[neutral_frame]
    frames, key_regions = [], []
    for region, landmarks in regions.items():
        if counts[region] > candidates.size:
            raise InputError(
                f"region {region!r} asks for {counts[region]} keys but the track has only "
                f"{candidates.size} valid frames besides the neutral one"
            )
        data = (aligned.points[candidates][:, landmarks] - neutral[landmarks]).reshape(candidates.size, -1)
        frames.extend(candidates[_select_rows(data, counts[region], method)])
        key_regions.extend([region] * counts[region])
    return KeyShapes(
        neutral=neutral,
        deltas=_region_deltas(aligned.points, neutral, frames, key_regions, regions),
        names=_key_names(key_regions),
        frames=np.array(frames, dtype=int),
        key_regions=tuple(key_regions),
        regions=regions,
        neutral_frame=neutral_frame,
        method=method,
        stable=stable,
    )


def _select_rows(data: np.ndarray, n_keys: int, method: str) -> np.ndarray:
    """``(n_keys,)`` distinct rows of ``data (n_candidates, n_features)``."""
    if n_keys == 0:
        return np.zeros(0, dtype=int)
    if method == "spread":
        return _select.spread(data, n_keys)
    if method == "hull":
        return _select.hull(data, n_keys)
    return _select.spa_refined(data, n_keys)


def _region_deltas(points, neutral, frames, key_regions, regions) -> np.ndarray:
    """``(n_keys, n_landmarks, n_dims)``: key frame minus neutral on its region, zero elsewhere."""
    deltas = np.zeros((len(frames), *neutral.shape))
    for k, (frame, region) in enumerate(zip(frames, key_regions)):
        landmarks = regions[region]
        deltas[k, landmarks] = points[frame, landmarks] - neutral[landmarks]
    return deltas


def _key_names(key_regions: list[str]) -> tuple[str, ...]:
    """``f"{region}_{i:02d}"``, numbered within each region."""
    seen: dict[str, int] = {}
    names = []
    for region in key_regions:
        names.append(f"{region}_{seen.get(region, 0):02d}")
        seen[region] = seen.get(region, 0) + 1
    return tuple(names)


def _check_regions(regions, n_landmarks: int) -> dict[str, np.ndarray]:
    if not isinstance(regions, dict) or not regions:
        raise InputError(f"regions must be a non-empty dict of name -> landmark indices; got {regions!r}")
    out = {}
    for name, indices in regions.items():
        ix = np.asarray(indices)
        if ix.ndim != 1 or ix.size == 0 or not np.issubdtype(ix.dtype, np.integer):
            raise InputError(f"regions[{name!r}] must be a non-empty 1-D int array; got {indices!r}")
        if ix.min() < 0 or ix.max() >= n_landmarks:
            raise InputError(
                f"regions[{name!r}] indices must lie in 0..{n_landmarks - 1}; got {ix.min()}..{ix.max()}"
            )
        out[str(name)] = ix
    return out


def _check_counts(n_keys, regions: dict) -> dict[str, int]:
    counts = n_keys if isinstance(n_keys, dict) else {name: n_keys for name in regions}
    missing = set(regions) - set(counts)
    if missing:
        raise InputError(f"n_keys gives no count for regions {sorted(missing)}")
    for name in regions:
        if not isinstance(counts[name], (int, np.integer)) or counts[name] < 0:
            raise InputError(f"n_keys for region {name!r} must be a non-negative int; got {counts[name]!r}")
    return {name: int(counts[name]) for name in regions}


def _check_neutral(neutral_frame, aligned: Track) -> int:
    if not isinstance(neutral_frame, (int, np.integer)) or not 0 <= neutral_frame < aligned.n_frames:
        raise InputError(f"neutral_frame must be a frame index in 0..{aligned.n_frames - 1}; got {neutral_frame!r}")
    if not aligned.valid[neutral_frame]:
        raise InputError(f"neutral_frame {neutral_frame} has no face (NaN); choose a valid frame")
    return int(neutral_frame)
