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
    separable non-negative factorisation, grown one key at a time and refined by
    exchanges that lower the reconstruction error of all frames; never worse than the
    ``spread`` or ``hull`` set without near-neutral frames (see
    :func:`keyshape.keyshapes._select.spa_steps`).

The error ``spa`` minimises is that of the weights the product solves: ``w >= 0``, and
``w <= upper`` (default 1). Under the bound a key is only worth its delta at full weight,
so no key is a frame near the neutral that the fit would scale up several times. And
``spa`` keys are strong frames by rule: a frame whose delta is below a quarter of the
region's 95th-percentile delta (``_select.MIN_STRENGTH``) is never a key, however much it
would lower the error (faint frames explain the small wobbles of the many resting frames,
which an artist cannot sculpt).

The number of keys can be chosen per region from an error target (``n_keys="auto"``,
:func:`choose_n_keys`): the smallest ``K`` whose RMS reconstruction error is below
``max_error`` % of the inter-ocular distance.

Long takes
----------
The search works on the Gram matrix ``X Xᵀ`` (``n_candidates²`` floats), so a region with
more than ``MAX_CANDIDATES`` (2048) candidate frames, e.g. several long takes selected
together, has its keys searched among 2048 of them (:func:`keyshape.keyshapes._select.pool`): the
frames ``spread`` and ``hull`` pick on the whole take (extremes along the principal axes
and the outer hull layers, with the principal axes and the range of motion of all frames),
successive-projection and farthest-point extremes (a quarter of the 2048) and evenly
spaced frames for the rest. Memory is then bounded but for terms linear in the frames
(the region's ``X``); the errors of ``n_keys="auto"`` are still those of every frame. Up
to 2048 candidates nothing changes: the keys are those of the search over all frames.

References
----------
.. [1] E. Chuang and C. Bregler, "Performance driven facial animation using blendshape
   interpolation", Stanford CS-TR-2002-02, 2002.
.. [2] N. Gillis and S. A. Vavasis, "Fast and robust recursive algorithms for separable
   nonnegative matrix factorization", IEEE TPAMI 36(4):698-714, 2014.
"""

from __future__ import annotations

from itertools import islice
from typing import Literal, NamedTuple

import numpy as np

from ..containers import KeyShapes, Track
from ..decompose import check_upper
from ..defaults import DEFAULT_METHOD, DEFAULT_N_KEYS, DEFAULT_UPPER, MAX_ERROR, MAX_KEYS
from ..exceptions import InputError, UsageError
from ..metrics import face_scale
from . import _select

__all__ = ["MAX_CANDIDATES", "MAX_ERROR", "MAX_KEYS", "METHODS", "KChoice", "choose_n_keys", "find_keyshapes",
           "check_neutral_frame"]

Method = Literal["spa", "spread", "hull"]
METHODS: tuple[str, ...] = ("spa", "spread", "hull")
MAX_CANDIDATES = 2048  # more candidate frames: keys are searched among this many (see the module notes)


class KChoice(NamedTuple):
    """The number of keys chosen for a region and the RMS error it reaches.

    ``error`` is in % of :func:`keyshape.metrics.face_scale` (the inter-ocular distance for
    MediaPipe and iBUG-68 tracks); it is above the target only when the cap was reached.
    """

    k: int
    error: float


def find_keyshapes(
    aligned: Track,
    *,
    regions: dict[str, np.ndarray],
    n_keys: int | dict[str, int] | Literal["auto"] = DEFAULT_N_KEYS,
    method: Method = DEFAULT_METHOD,
    neutral_frame: int,
    stable: np.ndarray | None = None,
    upper: float | None = DEFAULT_UPPER,
    max_error: float = MAX_ERROR,
    max_keys: int = MAX_KEYS,
) -> KeyShapes:
    """Choose ``n_keys`` real frames per region as key shapes.

    Parameters
    ----------
    aligned : Track
        ``points (n_frames, n_landmarks, n_dims)`` with head motion removed (see ``align``).
    regions : dict str -> (n_region_landmarks,) int, keyword-only
        Landmark indices of each region; ``{"whole": np.arange(n_landmarks)}`` for one.
    n_keys : int, dict str -> int, or "auto", keyword-only
        Key shapes per region (the same for all, or one per region), or ``"auto"``: the
        fewest whose RMS error is below ``max_error`` (:func:`choose_n_keys`).
    method : {"spa", "spread", "hull"}, keyword-only
    neutral_frame : int, keyword-only
        A valid frame; it is never a key, and the deltas are measured from it.
    stable : (n_stable,) int, optional, keyword-only
        The landmarks used for alignment, recorded in the result.
    upper : float or None, keyword-only
        Upper bound of the weights the keys will be solved with (``0 <= w <= upper``);
        ``spa`` and ``"auto"`` measure the error under it. Default 1, as the product solves
        (:func:`keyshape.app._pipeline.solve_take`). None: no bound, the paper's NNLS; a key and
        a weaker frame of the same shape then fit equally well, and either may be chosen.
    max_error : float, keyword-only
        Target RMS error of ``n_keys="auto"``, in % of the inter-ocular distance.
    max_keys : int, keyword-only
        Most keys per region with ``n_keys="auto"``.

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

    Notes
    -----
    With more than ``MAX_CANDIDATES`` (2048) valid frames besides the neutral, each
    region's keys are searched among 2048 well-spread frames, so memory stays bounded for
    long or many takes (see "Long takes" in the module notes); up to 2048 every frame is a
    candidate.

    References
    ----------
    .. [1] Chuang & Bregler (2002), section 4; Gillis & Vavasis (2014), Algorithm 1.

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> from keyshape.alignment._procrustes import align
    >>> perf = make_performance(n_keys=4, noise=0.0)
    >>> aligned, _ = align(perf.track, reference=perf.neutral, stable=perf.stable)
    >>> keys = find_keyshapes(aligned, regions=perf.regions, n_keys=2, neutral_frame=perf.neutral_frame)
    >>> keys.names
    ('upper_00', 'upper_01', 'lower_00', 'lower_01')
    >>> sorted(keys.frames.tolist()) == sorted(perf.extreme_frames.tolist())
    True
    >>> auto = find_keyshapes(aligned, regions=perf.regions, n_keys="auto", max_error=0.5, upper=1.0,
    ...                       neutral_frame=perf.neutral_frame)
    >>> auto.names == keys.names
    True
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}; got {method!r}")
    regions = check_regions(regions, aligned.n_landmarks)
    neutral_frame = check_neutral_frame(aligned, neutral_frame)
    upper = check_upper(upper)
    counts = None if isinstance(n_keys, str) and n_keys == "auto" else _check_counts(n_keys, regions)
    seen = {region: visible_frames(aligned, candidate_frames(aligned, neutral_frame), landmarks,
                                   at_least=0 if counts is None else counts[region])
            for region, landmarks in regions.items()}
    if counts is None:
        picked = _auto(aligned, regions, neutral_frame, method, upper, max_error, max_keys)
        rows = {region: pick[0] for region, pick in picked.items()}
    else:
        rows = {region: _select_rows(region_data(aligned, seen[region], neutral_frame, landmarks),
                                     counts[region], method, upper, region)
                for region, landmarks in regions.items()}
    frames = [int(seen[region][i]) for region in regions for i in rows[region]]
    key_regions = [region for region in regions for _ in rows[region]]
    neutral = aligned.points[neutral_frame]
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


def choose_n_keys(
    aligned: Track,
    *,
    regions: dict[str, np.ndarray],
    neutral_frame: int,
    method: Method = "spa",
    max_error: float = MAX_ERROR,
    max_keys: int = MAX_KEYS,
    upper: float | None = DEFAULT_UPPER,
) -> dict[str, KChoice]:
    """The fewest key shapes per region whose reconstruction error is below a target.

    For ``K = 1, 2, …`` the region's keys are chosen by ``method`` (as
    :func:`find_keyshapes` would choose ``K`` of them) and every valid frame is fitted by
    its best blend ``0 <= w <= upper``; the first ``K`` whose RMS error over the region's
    landmarks and the valid frames is below ``max_error`` is taken. The search stops at
    ``max_keys`` (or at the number of frames), whatever the error.

    Parameters
    ----------
    aligned : Track
        ``points (n_frames, n_landmarks, n_dims)``, head motion removed.
    regions : dict str -> (n_region_landmarks,) int, keyword-only
    neutral_frame : int, keyword-only
    method : {"spa", "spread", "hull"}, keyword-only
    max_error : float, keyword-only
        Target RMS error in % of :func:`keyshape.metrics.face_scale` of the neutral (the
        inter-ocular distance when the scheme has eye corners). Default 2 %, about twice
        the error the tracker's own jitter leaves.
    max_keys : int, keyword-only
        Cap per region (default 24).
    upper : float or None, keyword-only
        Upper bound of the weights, as they will be solved (default 1, as the product).

    Returns
    -------
    dict str -> KChoice
        ``(k, error)`` per region; ``error > max_error`` only when the cap was reached.

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> perf = make_performance(n_keys=6, noise=0.0)
    >>> choices = choose_n_keys(perf.track.with_points(perf.canonical), regions=perf.regions,
    ...                         neutral_frame=perf.neutral_frame, upper=1.0, max_error=0.5)
    >>> {region: k for region, (k, error) in choices.items()}
    {'upper': 3, 'lower': 3}
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}; got {method!r}")
    regions = check_regions(regions, aligned.n_landmarks)
    neutral_frame = check_neutral_frame(aligned, neutral_frame)
    picked = _auto(aligned, regions, neutral_frame, method, check_upper(upper), max_error, max_keys)
    return {region: KChoice(len(rows), error) for region, (rows, error) in picked.items()}


def _auto(aligned, regions, neutral_frame, method, upper, max_error, max_keys):
    """region -> (rows of the candidates, RMS error in %): the fewest keys below ``max_error``."""
    max_error, max_keys = _check_target(max_error, max_keys)
    scale, _ = face_scale(aligned.points[neutral_frame])
    out = {}
    for region, landmarks in regions.items():
        candidates = visible_frames(aligned, candidate_frames(aligned, neutral_frame), landmarks)
        n_valid = candidates.size + 1  # the neutral frame counts, with zero error
        data = region_data(aligned, candidates, neutral_frame, landmarks)
        to_percent = 100.0 / (scale * np.sqrt(n_valid * len(landmarks)))  # sqrt(Σ|r|²) -> RMS %
        pool = _select.pool(data, MAX_CANDIDATES)
        objective = _select.Objective(pool.X, upper)
        rows, error = np.zeros(0, dtype=int), np.inf
        for rows in islice(_select.steps(pool.X, method, objective=objective, axes=pool.axes, q95=pool.q95),
                           max_keys):
            squared = objective(rows) if pool.whole else _select.squared_error(data, pool.rows[rows], upper)
            error = np.sqrt(squared) * to_percent
            if error < max_error:
                break
        out[region] = (pool.rows[rows], float(error))
    return out


def candidate_frames(aligned: Track, neutral_frame: int) -> np.ndarray:
    """``(n_candidates,)`` int: the valid frames but the neutral one."""
    candidates = np.flatnonzero(aligned.valid)
    return candidates[candidates != neutral_frame]


def visible_frames(aligned: Track, candidates: np.ndarray, landmarks, *, at_least: int = 0) -> np.ndarray:
    """The ``candidates`` (n_candidates,) int in which no landmark of the region of ``landmarks`` is hidden.

    A landmark is hidden when its visibility is below 0.5 (a hand over it,
    :mod:`keyshape.capture.visibility`): a key is a real frame of the region, never the tracker's
    guess under a hand, not even of one eye of the upper face. Tracks without visibility keep every
    candidate. When fewer than ``at_least`` frames show the region whole (a short take asked for
    many keys), the least hidden frames make up the count.
    """
    if aligned.visibility is None:
        return candidates
    hidden = (aligned.visibility[np.ix_(candidates, np.asarray(landmarks))] < 0.5).any(axis=1)
    if (~hidden).sum() >= max(at_least, 1):
        return candidates[~hidden]
    # too few frames show the region (a short take): the least hidden ones make up the count
    share = (aligned.visibility[np.ix_(candidates, np.asarray(landmarks))] < 0.5).mean(axis=1)
    keep = np.sort(np.argsort(share, kind="stable")[: max(at_least, int((~hidden).sum()))])
    return candidates[keep] if len(keep) else candidates


def region_data(aligned: Track, candidates: np.ndarray, neutral_frame: int, landmarks) -> np.ndarray:
    """``X (n_candidates, n_region_landmarks · n_dims)``: candidate frames − neutral frame."""
    points = aligned.points[np.ix_(candidates, landmarks)]  # no copy of the other landmarks
    points -= aligned.points[neutral_frame, landmarks]
    return points.reshape(candidates.size, -1)


def _select_rows(data: np.ndarray, n_keys: int, method: str, upper: float | None,
                 region: str) -> np.ndarray:
    """``(n_keys,)`` distinct rows of ``data (n_candidates, n_features)``."""
    if n_keys > len(data):
        raise InputError(f"region {region!r} asks for {n_keys} keys but the track has only "
                         f"{len(data)} valid frames besides the neutral one")
    if n_keys == 0:
        return np.zeros(0, dtype=int)
    pool = _select.pool(data, MAX_CANDIDATES)
    if method == "spread":
        rows = _select.spread(pool.X, n_keys, axes=pool.axes)
    elif method == "hull":
        rows = _select.hull(pool.X, n_keys, axes=pool.axes)
    else:
        rows = _select.spa(pool.X, n_keys, upper=upper, axes=pool.axes, q95=pool.q95)
    return pool.rows[rows]


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


def check_regions(regions, n_landmarks: int) -> dict[str, np.ndarray]:
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
    if isinstance(n_keys, str):
        raise InputError(f"n_keys must be an int, a dict of region -> int, or 'auto'; got {n_keys!r}")
    counts = n_keys if isinstance(n_keys, dict) else dict.fromkeys(regions, n_keys)
    missing = set(regions) - set(counts)
    if missing:
        raise InputError(f"n_keys gives no count for regions {sorted(missing)}")
    for name in regions:
        if not isinstance(counts[name], (int, np.integer)) or counts[name] < 0:
            raise InputError(f"n_keys for region {name!r} must be a non-negative int; got {counts[name]!r}")
    return {name: int(counts[name]) for name in regions}


def check_neutral_frame(track: Track, frame, *, name: str = "neutral_frame") -> int:
    """``frame`` as an int if it is a frame of ``track`` with a face; ``name`` is the argument's
    name in the message (``--neutral`` on the command line)."""
    if not isinstance(frame, (int, np.integer)) or not 0 <= frame < track.n_frames:
        kind = UsageError if name.startswith("--") else InputError  # a command-line option: exit code 2
        raise kind(f"{name} must be a frame in 0..{track.n_frames - 1}; got {frame!r}")
    if not track.valid[frame]:
        raise InputError(f"{name} frame {frame} has no face; choose a frame where the face was found")
    return int(frame)


def _check_target(max_error, max_keys) -> tuple[float, int]:
    if not isinstance(max_error, (int, float, np.number)) or not max_error > 0:
        raise InputError(f"max_error must be a number > 0 (% of the inter-ocular distance); got {max_error!r}")
    if not isinstance(max_keys, (int, np.integer)) or max_keys < 1:
        raise InputError(f"max_keys must be an int >= 1; got {max_keys!r}")
    return float(max_error), int(max_keys)
