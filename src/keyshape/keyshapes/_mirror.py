"""Mirrored key shapes: every key's left-right mirror image, added where it adds reach.

An actor who pulls the mouth left in one take pulls it right in the next; a key set found on
the first take cannot blend the second from its frames. A face is (nearly) symmetric, so each
key ``S`` has a mirror image ``S'``: landmark ``i`` of ``S'`` is landmark ``p(i)`` of ``S`` (its
left-right partner) reflected through the face's symmetry plane,

.. math::

    \\delta'_i = (I - 2 n n^\\top)\\, \\delta_{p(i)},

with ``δ`` the key's delta from the neutral and ``n`` the plane's unit normal (the neutral
stays the neutral: only the expression is reflected). ``p`` is the scheme's pairing
(:func:`keyshape.schemes.mirror_pairs`: MediaPipe's from its canonical face, iBUG 68's from the
markup) or one found on the neutral (:func:`find_mirror_pairs`); ``n`` is fitted to the pairs
of the neutral (:func:`symmetry_plane`).

A mirror is added only where it reaches what the set cannot: its best bounded blend of the
keys already in its region (``0 ≤ w ≤ upper``) must leave at least ``min_reach`` of it
unexplained (the residual's norm over the mirror's), and that residual must exceed the key
set's error target (RMS over the region's landmarks above ``max_error`` % of the inter-ocular
distance: what the keys already reach within the target needs no key). A symmetric smile is
its own mirror (residual near 0) and gets none; a one-sided smirk gets one; a faint key whose
mirror differs from the keys only by the tracker's noise gets none. The default 0.3 was chosen by
measurement (BENCHMARKS.md, "Mirrored keys").
"""

from __future__ import annotations

import numpy as np

from ..containers import KeyShapes
from ..decompose import solve_nnls
from ..defaults import MAX_ERROR, MIRROR_SUFFIX
from ..exceptions import InputError
from ..mesh import mirror_field
from ..metrics import face_scale
from ..schemes import mirror_pairs

__all__ = ["MIN_REACH", "MIRROR_SUFFIX", "add_mirrors", "find_mirror_pairs", "mirror_deltas", "symmetry_plane",
           "mirror_gains"]

MIN_REACH = 0.3  # a mirror must leave this fraction of itself unexplained by the keys already there


def symmetry_plane(points: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, float]:
    """The plane ``n · x = c`` that best swaps each landmark with its partner.

    Parameters
    ----------
    points : (n_landmarks, n_dims) float, a neutral face
    pairs : (n_landmarks,) int, the partner of every landmark (itself on the midline)

    Returns
    -------
    (normal (n_dims,) unit, with a non-negative first component; offset float)

    Notes
    -----
    The partners' differences ``x_i − x_p(i)`` all point along ``n``: ``n`` is their leading
    right singular vector, and ``c`` the mean of ``n · (x_i + x_p(i)) / 2``.
    """
    points = np.asarray(points, dtype=float)
    moved = points - points[pairs]
    if not np.any(pairs != np.arange(len(pairs))) or not np.isfinite(moved).all():
        raise InputError("no left-right pairs to find the face's symmetry plane from")
    normal = np.linalg.svd(moved, full_matrices=False)[2][0]
    normal = normal if normal[0] >= 0 else -normal
    return normal, float(np.mean((points + points[pairs]) @ normal) / 2)


MAX_ASYMMETRY = 0.05  # a found pairing must map the neutral onto itself within 5 % of its size (RMS)


def find_mirror_pairs(neutral: np.ndarray) -> np.ndarray | None:
    """A left-right pairing of landmarks found on a neutral face (for schemes without one).

    The face is reflected through the plane ``x = median x`` (image x runs left to right on a
    frontal face), each reflected landmark matched one-to-one to the nearest landmark, the plane
    refitted to the matches, and the whole repeated until the pairing holds.

    Parameters
    ----------
    neutral : (n_landmarks, n_dims) float

    Returns
    -------
    (n_landmarks,) int, an involution (``pairs[pairs] == arange``); None when the landmarks are
    not a symmetric face: the reflected neutral misses its partners by more than
    ``MAX_ASYMMETRY`` (5 %) of the face's size (RMS distance from the centroid)
    """
    from scipy.optimize import linear_sum_assignment

    points = np.asarray(neutral, dtype=float)
    normal = np.eye(points.shape[1])[0]
    offset = float(np.median(points[:, 0]))
    pairs = np.arange(len(points))
    for _ in range(10):
        reflected = points - 2 * (points @ normal - offset)[:, None] * normal
        rows, cols = linear_sum_assignment(((reflected[:, None] - points[None]) ** 2).sum(-1))
        found = cols[np.argsort(rows)]
        found = np.where(found[found] == np.arange(len(points)), found, np.arange(len(points)))
        if np.array_equal(found, pairs):
            break
        pairs = found
        if np.any(pairs != np.arange(len(pairs))):
            normal, offset = symmetry_plane(points, pairs)
    if not np.any(pairs != np.arange(len(pairs))):
        return None
    reflected = points - 2 * (points @ normal - offset)[:, None] * normal
    size = np.sqrt(np.mean(((points - points.mean(axis=0)) ** 2).sum(axis=1)))
    miss = np.sqrt(np.mean(((reflected[pairs] - points) ** 2).sum(axis=1)))
    return pairs if miss <= MAX_ASYMMETRY * size else None


def mirror_deltas(deltas: np.ndarray, pairs: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """The mirror images ``δ'_i = (I − 2nnᵀ) δ_p(i)`` of ``deltas (..., n_landmarks, n_dims)``
    (:func:`keyshape.mesh.mirror_field`, on landmarks)."""
    return mirror_field(deltas, pairs, normal)


def _pairs_for(keys: KeyShapes, pairs) -> np.ndarray | None:
    if pairs is None:
        pairs = mirror_pairs(keys.n_landmarks)
    if pairs is None:
        pairs = find_mirror_pairs(keys.neutral)
        if pairs is None:
            return None
    pairs = np.asarray(pairs)
    if pairs.shape != (keys.n_landmarks,) or not np.issubdtype(pairs.dtype, np.integer) \
            or pairs.min(initial=0) < 0 or pairs.max(initial=0) >= keys.n_landmarks \
            or not np.array_equal(pairs[pairs], np.arange(keys.n_landmarks)):
        raise InputError(f"mirror pairs must be ({keys.n_landmarks},) landmark indices that pair each "
                         "landmark with its partner (pairs[pairs] == range)")
    return pairs


def _mirror_region(keys: KeyShapes, region: str, pairs: np.ndarray) -> str:
    """The region holding the mirror images of ``region``'s landmarks (most of them)."""
    mirrored = set(pairs[keys.regions[region]].tolist())
    return max(keys.regions, key=lambda r: (len(mirrored & set(keys.regions[r].tolist())), r == region))


def mirror_gains(keys: KeyShapes, *, pairs: np.ndarray | None = None,
                 upper: float | None = 1.0) -> dict[str, float]:
    """How much of each key's mirror the other keys of its region cannot reach.

    Returns
    -------
    dict key name -> float in [0, 1]: ``‖δ' − Bw‖ / ‖δ'‖`` for the best ``0 ≤ w ≤ upper`` blend
    ``Bw`` of the frame keys in the mirror's region (0: the mirror adds nothing); empty when the
    landmarks are not a symmetric face.
    """
    pairs = _pairs_for(keys, pairs)
    if pairs is None:
        return {}
    normal, _ = symmetry_plane(keys.neutral, pairs)
    out = {}
    for k in np.flatnonzero(~keys.mirrored):
        target = _mirror_region(keys, keys.key_regions[k], pairs)
        out[keys.names[k]] = _unreached(keys, k, target, [], pairs, normal, upper)[0]
    return out


def _unreached(keys, k, region, extra, pairs, normal, upper) -> tuple[float, float, np.ndarray]:
    """(fraction of key k's mirror left unexplained in ``region``, that residual's RMS over the
    region's landmarks, the mirror's delta)."""
    landmarks = keys.regions[region]
    delta = np.zeros_like(keys.neutral)
    delta[landmarks] = mirror_deltas(keys.deltas[k], pairs, normal)[landmarks]
    norm = np.linalg.norm(delta)
    basis = [keys.deltas[j][landmarks].ravel() for j in keys.keys_of(region) if not keys.mirrored[j]]
    basis += [d[landmarks].ravel() for d in extra]
    if norm == 0:
        return 0.0, 0.0, delta
    x = delta[landmarks].ravel()
    if basis:
        B = np.array(basis).T
        x = x - B @ solve_nnls(B, x[None], upper=upper)[0]
    residual = float(np.linalg.norm(x))
    return residual / norm, residual / np.sqrt(len(landmarks)), delta


def add_mirrors(keys: KeyShapes, *, pairs: np.ndarray | None = None, min_reach: float = MIN_REACH,
                max_error: float = MAX_ERROR, upper: float | None = 1.0) -> KeyShapes:
    """``keys`` with the mirror image of each key that reaches what the set cannot.

    Parameters
    ----------
    keys : KeyShapes, aligned (canonical) coordinates; mirrored keys already in it are kept
    pairs : (n_landmarks,) int, optional: each landmark's left-right partner (default: the
        scheme's, :func:`keyshape.schemes.mirror_pairs`, else found on the neutral; when the
        neutral is not a symmetric face, :func:`find_mirror_pairs`, no mirror is added)
    min_reach : float in [0, 1]: a mirror is added when its best bounded blend of the keys in
        its region (the frames and the mirrors added before it) leaves at least this fraction
        of it (by norm) unexplained; 0 adds every mirror, 1 none
    max_error : and when that residual's RMS over the region's landmarks exceeds this, % of the
        inter-ocular distance (the key set's error target; 0 to drop this test)
    upper : the weight bound the keys will be solved with

    Returns
    -------
    KeyShapes
        The same keys in the same order, each region's new mirrors after its own keys, named
        ``f"{source}_mirror"`` with ``mirror_of`` the source's name and ``frames`` / ``takes``
        the source's.

    Examples
    --------
    >>> import numpy as np
    >>> neutral = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])   # two mouth corners, a midline point
    >>> deltas = np.zeros((2, 3, 2))
    >>> deltas[0, 0] = [-0.3, 0.2]                                   # the left corner alone pulls out and up
    >>> deltas[1, :2] = [[-0.2, 0.3], [0.2, 0.3]]                    # both corners: a symmetric smile
    >>> keys = KeyShapes(neutral, deltas, ("smirk", "smile"), [5, 9], ("mouth", "mouth"), {"mouth": [0, 1, 2]})
    >>> out = add_mirrors(keys, pairs=np.array([1, 0, 2]), max_error=0)
    >>> out.names, out.mirror_of
    (('smirk', 'smile', 'smirk_mirror'), ('', '', 'smirk'))
    >>> out.deltas[2, 1].round(2).tolist()                           # the right corner pulls out and up
    [0.3, 0.2]
    """
    if not 0 <= min_reach <= 1:
        raise InputError(f"min_reach must be in [0, 1]; got {min_reach!r}")
    pairs = _pairs_for(keys, pairs)
    if pairs is None:  # not a symmetric face: nothing to mirror
        return keys
    normal, _ = symmetry_plane(keys.neutral, pairs)
    floor = max_error / 100 * face_scale(keys.neutral)[0]
    taken = {m for m in keys.mirror_of if m}
    added: dict[str, list[tuple[int, np.ndarray]]] = {r: [] for r in keys.regions}
    for k in np.flatnonzero(~keys.mirrored):
        if keys.names[k] in taken:
            continue
        region = _mirror_region(keys, keys.key_regions[k], pairs)
        extra = [d for _, d in added[region]] + [keys.deltas[j] for j in keys.keys_of(region) if keys.mirrored[j]]
        reach, rms, delta = _unreached(keys, k, region, extra, pairs, normal, upper)
        if reach >= min_reach and reach > 0 and rms > floor:
            added[region].append((int(k), delta))
    if not any(added.values()):
        return keys
    names = set(keys.names)
    deltas, new_names, frames, regions_of, takes, mirror_of = [], [], [], [], [], []
    for region in keys.regions:
        rows = [(int(j), keys.deltas[j], keys.names[j], keys.mirror_of[j]) for j in keys.keys_of(region)]
        rows += [(k, d, _unique(f"{keys.names[k]}{MIRROR_SUFFIX}", names), keys.names[k]) for k, d in added[region]]
        for j, delta, name, source in rows:
            deltas.append(delta)
            new_names.append(name)
            frames.append(int(keys.frames[j]))
            regions_of.append(region)
            takes.append(keys.takes[j])
            mirror_of.append(source)
    return KeyShapes(keys.neutral, np.array(deltas), tuple(new_names), np.array(frames), tuple(regions_of),
                     keys.regions, tuple(takes), keys.neutral_frame, keys.neutral_take, keys.method,
                     keys.stable, tuple(mirror_of))


def _unique(name: str, names: set[str]) -> str:
    out, i = name, 2
    while out in names:
        out, i = f"{name}{i}", i + 1
    names.add(out)
    return out
