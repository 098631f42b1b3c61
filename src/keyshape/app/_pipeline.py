"""The paper's method end to end, as a few calls over the stage modules.

``discover_keys`` (align + select) and ``solve_take`` (align onto the key set's neutral + solve)
glue the stages the way the command line uses them; each stage stays usable on its own.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..alignment import align, choose_neutral, choose_neutral_frame
from ..capture.filters import GapReport, fill_edges, gap_report, hold_neutral, segments
from ..capture.gaze import Gaze, estimate_gaze
from ..containers import KeyShapes, Poses, Track, Weights
from ..decompose import solve_weights
from ..defaults import (
    DEFAULT_METHOD,
    DEFAULT_MIRROR,
    DEFAULT_N_KEYS,
    DEFAULT_REGIONS,
    DEFAULT_SMOOTHNESS,
    DEFAULT_UPPER,
    MAX_ERROR,
)
from ..exceptions import InputError
from ..keyshapes import MIN_REACH, add_mirrors, check_neutral_frame, extend_keyshapes, find_keyshapes, region_errors
from ..metrics import face_scale, reconstruction_error
from ..schemes import resolve_regions, stable_points
from ._strict import converged

__all__ = ["discover_keys", "extend_keys", "coverage", "Coverage", "solve_take", "fit_errors", "head_and_gaze",
           "arkit_scores", "key_scores", "Solved"]


def _neutral_frame(track: Track, neutral: int | None, stable: np.ndarray, regions: dict | None = None) -> int:
    if neutral is None:
        return choose_neutral_frame(track, stable=stable, regions=regions)
    return check_neutral_frame(track, neutral, name="--neutral")


def discover_keys(track: Track | Sequence[Track], *, regions: str | Path | dict = DEFAULT_REGIONS,
                  n_keys: int | str = DEFAULT_N_KEYS, method: str = DEFAULT_METHOD,
                  neutral: int | str | Path | Track | None = None,
                  take: str | Sequence[str] = "", stable: np.ndarray | None = None,
                  upper: float | None = DEFAULT_UPPER, max_error: float = MAX_ERROR,
                  mirror: bool = DEFAULT_MIRROR, min_reach: float = MIN_REACH) -> KeyShapes:
    """Key shapes of one take, or one key set across several takes of the same actor.

    Pick the neutral frame (of the first take), align every frame of every take onto it,
    and select real frames per region from all takes together; each key records its take
    and frame, so one set of sculpted targets serves every take.

    Parameters
    ----------
    track : Track in image coordinates, or a sequence of them (same landmark scheme)
    regions : region scheme name, REGIONS.json path (see :func:`keyshape.schemes.resolve_regions`)
        or a dict region -> (n_region_landmarks,) int
    n_keys : key shapes per region, or "auto": the fewest per region whose RMS error is below
        ``max_error`` (% of the inter-ocular distance; see :func:`keyshape.keyshapes._search.find_keyshapes`)
    method : "spa", "hull" or "spread"
    neutral : the neutral frame of the first take; a Track, image or video file of the actor at rest (its
        median aligned shape is the neutral; ``keys.neutral_take`` is the file's name, ``neutral_frame`` its frame
        nearest that shape); or None to choose it automatically
        (:func:`keyshape.alignment.choose_neutral_frame`: the least activated frame by the tracker's
        expression scores with the whole face in view; without scores the frame closest to the median
        aligned shape)
    take : a name per take, recorded with every key
    stable : (n_stable,) int landmarks to align on (default: the scheme's stable points)
    upper : the weight bound the keys will be solved with (selection fits under it)
    mirror : add each key's left-right mirror image where it reaches what the keys cannot
        (:func:`keyshape.keyshapes.add_mirrors`; ``min_reach`` its threshold): a one-sided
        expression of this take then covers the other side in the next
    """
    tracks = [track] if isinstance(track, Track) else list(track)
    takes = [take] if isinstance(take, str) else list(take)
    takes = takes if len(takes) == len(tracks) else [f"take{i}" for i in range(len(tracks))]
    first = tracks[0]
    for name, other in zip(takes, tracks):
        if (other.n_landmarks, other.n_dims) != (first.n_landmarks, first.n_dims):
            raise InputError(f"{name}: has {other.n_landmarks} landmarks in {other.n_dims}D but "
                             f"{takes[0]} has {first.n_landmarks} in {first.n_dims}D")
    valid = sum(int(t.valid.sum()) for t in tracks)
    if valid < 2:
        has = "these have" if len(tracks) > 1 else "this one has"
        raise InputError(f"{', '.join(takes)}: a track needs at least 2 frames with a face; {has} {valid}")
    region_map = regions if isinstance(regions, dict) else resolve_regions(regions, first.n_landmarks)
    stable = stable_points(first.n_landmarks) if stable is None else np.asarray(stable)
    rest = None
    if isinstance(neutral, (str, Path, Track)):  # a separate clip or still of the actor at rest
        rest = neutral if isinstance(neutral, Track) else _track_file(neutral)
        tracks, takes = [_rest_take(rest, stable, first)], [_rest_name(neutral), *takes]
        tracks += [track] if isinstance(track, Track) else list(track)
        first, neutral = tracks[0], 0
    neutral = _neutral_frame(first, neutral, stable, region_map)
    together = Track(_aligned_together(tracks, first.points[neutral], stable), first.fps, visibility=_seen(tracks))
    keys = find_keyshapes(together, regions=region_map, n_keys=n_keys, method=method,
                          neutral_frame=neutral, stable=stable, upper=upper, max_error=max_error)
    if mirror:
        keys = add_mirrors(keys, min_reach=min_reach, max_error=max_error, upper=upper)
    keys = _split_takes(keys, [t.n_frames for t in tracks], takes)
    if rest is None:
        return keys
    # the neutral take's frame nearest its median shape is recorded (the shape is the median itself)
    frame = choose_neutral(rest, stable=stable, regions=region_map)
    return KeyShapes(keys.neutral, keys.deltas, keys.names, keys.frames, keys.key_regions, keys.regions, keys.takes,
                     frame, keys.neutral_take, keys.method, keys.stable, keys.mirror_of)


def _track_file(path) -> Track:
    from ..capture import track_video

    return track_video(path, progress=False)


def _rest_name(neutral) -> str:
    return Path(neutral).name if isinstance(neutral, (str, Path)) else "neutral"


def _rest_take(rest: Track, stable: np.ndarray, like: Track) -> Track:
    """A one-frame take: the median aligned shape of a clip (or still) of the actor at rest."""
    if (rest.n_landmarks, rest.n_dims) != (like.n_landmarks, like.n_dims) or not rest.valid.any():
        raise InputError(f"the neutral clip must show the face with {like.n_landmarks} landmarks in {like.n_dims}D; "
                         f"it has {int(rest.valid.sum())} frames with a face of {rest.n_landmarks} landmarks")
    frame = choose_neutral(rest, stable=stable)
    aligned = align(rest, reference=frame, stable=stable)[0].points[rest.valid]
    return Track(np.median(aligned, axis=0)[None], like.fps)


def _seen(tracks: Sequence[Track]) -> np.ndarray | None:
    """(sum of n_frames, n_landmarks) visibility of the takes end to end; None when none has any."""
    return None if all(t.visibility is None for t in tracks) else np.concatenate([t.seen for t in tracks])


def _aligned_together(tracks: Sequence[Track], reference: np.ndarray, stable: np.ndarray) -> np.ndarray:
    """(sum of n_frames, n_landmarks, n_dims): every take aligned onto ``reference``, end to end.

    Filled take by take into one array, so only one take's aligned copy exists besides it.
    """
    first = tracks[0]
    out = np.empty((sum(t.n_frames for t in tracks), first.n_landmarks, first.n_dims))
    start = 0
    for t in tracks:
        out[start : start + t.n_frames] = align(t, reference=reference, stable=stable)[0].points
        start += t.n_frames
    return out


def _take_frames(frames: np.ndarray, lengths: list[int], takes: list[str]) -> tuple[np.ndarray, tuple[str, ...]]:
    """Frame indices into the takes end to end -> (frames within their take, take names)."""
    starts = np.cumsum([0, *lengths[:-1]])
    which = np.searchsorted(starts, frames, side="right") - 1
    return np.asarray(frames) - starts[which], tuple(takes[i] for i in which)


def _split_takes(keys: KeyShapes, lengths: list[int], takes: list[str]) -> KeyShapes:
    """Turn frame indices into the concatenated takes back into (take, frame) pairs."""
    frames, names = _take_frames(keys.frames, lengths, takes)
    return KeyShapes(keys.neutral, keys.deltas, keys.names, frames, keys.key_regions, keys.regions, names,
                     keys.neutral_frame, takes[0], keys.method, keys.stable, keys.mirror_of)


def extend_keys(keys: KeyShapes, track: Track | Sequence[Track], *, take: str | Sequence[str] = "",
                max_error: float = MAX_ERROR, max_keys: int = 24, upper: float | None = DEFAULT_UPPER,
                mirror: bool = DEFAULT_MIRROR, min_reach: float = MIN_REACH) -> KeyShapes:
    """``keys`` plus the fewest frames of new take(s) that bring them within ``max_error``.

    Every old key keeps its name, shape and source; the new takes are aligned onto the key set's
    neutral and, per region, frames added until the takes' RMS error is below ``max_error`` %
    of the inter-ocular distance (:func:`keyshape.keyshapes.extend_keyshapes`); with ``mirror``
    the new keys' mirrors are added where they add reach. The artist sculpts only the new keys.
    """
    tracks = [track] if isinstance(track, Track) else list(track)
    takes = [take] if isinstance(take, str) else list(take)
    takes = takes if len(takes) == len(tracks) else [f"take{i}" for i in range(len(tracks))]
    for name, t in zip(takes, tracks):
        if (t.n_landmarks, t.n_dims) != (keys.n_landmarks, keys.n_dims):
            raise InputError(f"{name}: has {t.n_landmarks} landmarks in {t.n_dims}D but the key set was made "
                             f"from {keys.n_landmarks} in {keys.n_dims}D")
    stable = keys.stable if keys.stable is not None else stable_points(keys.n_landmarks)
    together = Track(_aligned_together(tracks, keys.neutral, stable), tracks[0].fps, visibility=_seen(tracks))
    extended, _ = extend_keyshapes(keys, together, max_error=max_error, max_keys=max_keys, upper=upper)
    if mirror:
        extended = add_mirrors(extended, min_reach=min_reach, max_error=max_error, upper=upper)
    # new keys' frames (and their mirrors') index the takes end to end: back to (take, frame)
    old = set(keys.names)
    new = np.array([n not in old and (m or n) not in old for n, m in zip(extended.names, extended.mirror_of)])
    frames, sources = extended.frames.copy(), list(extended.takes)
    if new.any():
        frames[new], named = _take_frames(extended.frames[new], [t.n_frames for t in tracks], takes)
        for k, name in zip(np.flatnonzero(new), named):
            sources[k] = name
    return KeyShapes(extended.neutral, extended.deltas, extended.names, frames, extended.key_regions,
                     extended.regions, tuple(sources), extended.neutral_frame, extended.neutral_take,
                     extended.method, extended.stable, extended.mirror_of)


@dataclass(frozen=True)
class Coverage:
    """How well a key set reaches a take.

    errors : dict region -> (n_frames,) float, each frame's RMS error of its best blend, % of the
        inter-ocular distance (NaN without a face); max_error : the target;
    added : dict region -> list of float, the take's RMS error with 0, 1, 2, … of its own frames
        added as keys (the error-vs-added-keys curve; ``added[r][0]`` is the key set as it is),
        at least a few keys past the target
    """

    errors: dict[str, np.ndarray]
    max_error: float
    added: dict[str, list[float]]
    fps: float

    def out_of_reach(self, region: str) -> np.ndarray:
        """(n,) int: the frames whose error in ``region`` exceeds the target."""
        return np.flatnonzero(np.nan_to_num(self.errors[region]) > self.max_error)

    def keys_to_add(self, region: str) -> int | None:
        """The fewest keys from the take that bring ``region`` within the target (None: more
        than the curve holds)."""
        below = [i for i, e in enumerate(self.added[region]) if e < self.max_error]
        return below[0] if below else None

    def summary(self) -> dict:
        """Per region: RMS error over the take, frames out of reach (count, share) and the keys
        ``--extend`` would add."""
        out = {}
        for region, e in self.errors.items():
            ok = np.isfinite(e)
            far = self.out_of_reach(region)
            out[region] = {"rms_error": float(np.sqrt(np.mean(e[ok] ** 2))) if ok.any() else None,
                           "frames_out_of_reach": int(far.size),
                           "share_out_of_reach": float(far.size / max(int(ok.sum()), 1)),
                           "keys_to_add": self.keys_to_add(region),
                           "error_vs_added_keys": [round(float(v), 4) for v in self.added[region]]}
        return out


def coverage(keys: KeyShapes, track: Track, *, max_error: float = MAX_ERROR, upper: float | None = DEFAULT_UPPER,
             max_added: int = 24, past_target: int = 3) -> Coverage:
    """How well ``keys`` reach ``track``: per-frame errors and the error-vs-added-keys curve.

    The curve runs until ``past_target`` keys beyond those that reach ``max_error`` (or
    ``max_added`` keys in all).
    """
    if (track.n_landmarks, track.n_dims) != (keys.n_landmarks, keys.n_dims):
        raise InputError(f"the take has {track.n_landmarks} landmarks in {track.n_dims}D but the key set was made "
                         f"from {keys.n_landmarks} in {keys.n_dims}D")
    stable = keys.stable if keys.stable is not None else stable_points(keys.n_landmarks)
    aligned = Track(_aligned_together([track], keys.neutral, stable), track.fps, visibility=track.visibility)
    errors = region_errors(keys, aligned, upper=upper)
    _, needed = extend_keyshapes(keys, aligned, max_error=max_error, max_keys=max_added, upper=upper)
    longest = min(max(len(c) for c in needed.values()) - 1 + past_target, max_added)
    _, curves = extend_keyshapes(keys, aligned, max_error=1e-9, max_keys=longest, upper=upper)
    return Coverage(errors, float(max_error), curves, track.fps)


@dataclass(frozen=True)
class Solved:
    """A take decomposed on a key set.

    weights : Weights (n_frames, n_keys); poses : Poses (head); aligned : Track (head removed);
    gaps : GapReport (frames without a face and what was done with them); gaze : Gaze or None
    (per-eye yaw and pitch, MediaPipe tracks only)
    """

    weights: Weights
    poses: Poses
    aligned: Track
    gaps: GapReport
    gaze: Gaze | None = None




def solve_take(track: Track, keys: KeyShapes, *, smoothness: float = DEFAULT_SMOOTHNESS,
               upper: float | None = DEFAULT_UPPER, convex: bool = False,
               max_bridge: float = 0.5) -> Solved:
    """Align ``track`` onto the key set's neutral shape and solve the weights.

    Parameters
    ----------
    track : Track in image coordinates, same landmarks as the key set
    keys : KeyShapes
    smoothness, upper, convex : see :func:`keyshape.decompose._solve.solve_weights`. The default
        is the zero-lag smoothed solve bounded to ``0 <= w <= 1``; ``smoothness=0, upper=None``
        is the paper's per-frame NNLS.
    max_bridge : seconds; with smoothing, gaps up to this long between faces are bridged by
        the smooth solve, longer ones (and gaps at the ends) hold the neutral pose (weights 0)

    Raises
    ------
    ConvergenceError
        The smoothed solve stopped short of its certificate (extreme ``smoothness``).
    """
    if track.n_landmarks != keys.n_landmarks or track.n_dims != keys.n_dims:
        raise InputError(
            f"the track has {track.n_landmarks} landmarks in {track.n_dims}D but the key set was made "
            f"from {keys.n_landmarks} in {keys.n_dims}D"
        )
    stable = keys.stable if keys.stable is not None else stable_points(track.n_landmarks)
    aligned, poses = align(track, reference=keys.neutral, stable=stable)
    gaps = gap_report(track.valid, max_bridge=int(round(max_bridge * track.fps)))
    values = np.full((track.n_frames, keys.n_keys), np.nan)
    with converged(smoothness):  # a smoothed solve that stops short is an error, not weights
        for start, stop in segments(gaps):  # held gaps split the take: no data, nothing to bridge
            solved = solve_weights(aligned[start:stop], keys, upper=upper, smoothness=smoothness,
                                   convex=convex).values
            values[start:stop] = fill_edges(solved, track.valid[start:stop])
    if smoothness > 0:
        values = hold_neutral(values, gaps)
    weights = Weights(values, keys.names, track.fps, track.frame_index, track.time)
    gaze = estimate_gaze(aligned.points, reference=keys.neutral) if track.n_landmarks == 478 else None
    return Solved(weights, poses, aligned, gaps, gaze)


def fit_errors(tracks: Track | Sequence[Track], keys: KeyShapes, *,
               upper: float | None = DEFAULT_UPPER) -> tuple[dict[str, float], str]:
    """RMS reconstruction error per region of the key set's best bounded fit of the take(s).

    Returns ``({region: error}, unit)``, errors in % of the inter-ocular distance (or of the
    face size for schemes without eye corners; see :func:`keyshape.metrics.face_scale`).
    """
    tracks = [tracks] if isinstance(tracks, Track) else list(tracks)
    stable = keys.stable if keys.stable is not None else stable_points(keys.n_landmarks)
    points = _aligned_together(tracks, keys.neutral, stable)
    errors = reconstruction_error(Track(points, tracks[0].fps, visibility=_seen(tracks)), keys, upper=upper)
    length, unit = face_scale(keys.neutral)
    return {region: 100 * e / length for region, e in errors.items()}, unit


def head_poses(track: Track) -> Poses:
    """Head motion of a take relative to its own automatically chosen neutral frame."""
    return head_and_gaze(track)[0]


def head_and_gaze(track: Track) -> tuple[Poses, Gaze | None]:
    """Head poses and (MediaPipe tracks) per-eye gaze, relative to the take's own neutral frame,
    chosen as :func:`discover_keys` chooses it (so ``retarget --track`` turns the head and eyes as
    ``run`` does)."""
    stable = stable_points(track.n_landmarks)
    neutral = _neutral_frame(track, None, stable, resolve_regions(DEFAULT_REGIONS, track.n_landmarks))
    aligned, poses = align(track, reference=track.points[neutral], stable=stable)
    gaze = estimate_gaze(aligned.points, neutral_frame=neutral) if track.n_landmarks == 478 else None
    return poses, gaze


def arkit_scores(track: Track, *, source: str | Path = "track") -> Weights:
    """MediaPipe's ARKit-style scores as Weights ``(n_frames, 52)`` (``_neutral`` left out)."""
    if track.blendshapes is None or not track.blendshape_names:
        raise InputError(f"{source}: has no blendshape scores (tracks from `keyshape track` do)")
    keep = [i for i, n in enumerate(track.blendshape_names) if not n.startswith("_")]
    return Weights(track.blendshapes[:, keep], [track.blendshape_names[i] for i in keep], track.fps,
                   track.frame_index, track.time)


def key_scores(keys: KeyShapes, track: Track, weights: Weights | None = None, *, same_take: bool = True):
    """The tracker's ARKit scores at the key set's neutral and key frames, from ``track``.

    With ``weights`` (the take's solved key weights), the take's scores of every frame come
    along too, and the mapping is fitted on the whole take (``KeyScores.take``); then the keys
    may come from other takes (a reused key set: ``same_take=False``, their frames are not read).

    Returns
    -------
    KeyScores or None
        None when the track has no scores (another tracker's landmarks), or, without
        ``weights``, when a key frame lies outside it (the keys come from another take).
    """
    from ..targets import KeyScores

    if track.blendshapes is None or not track.blendshape_names:
        return None
    names = tuple(track.blendshape_names)
    take = None if weights is None else (track.blendshapes, np.asarray(weights.values, dtype=float))
    frames = np.asarray(keys.frames, dtype=np.int64)
    if not same_take or max(int(frames.max(initial=0)), keys.neutral_frame) >= track.n_frames:
        if take is None:
            return None
        return KeyScores(np.full(len(names), np.nan), np.full((keys.n_keys, len(names)), np.nan), names, *take)
    neutral, rows = track.blendshapes[keys.neutral_frame], track.blendshapes[frames].copy()
    if keys.mirrored.any():  # a mirrored key's scores: its source's change from the neutral, sides swapped
        swap = [names.index(_other_side(n)) if _other_side(n) in names else i for i, n in enumerate(names)]
        rows[keys.mirrored] = neutral + (rows[keys.mirrored] - neutral)[:, swap]
    return KeyScores(neutral, rows, names, *(take or (None, None)))


def _other_side(name: str) -> str:
    """ARKit's ``...Left`` <-> ``...Right`` (the actor's sides); other names are their own."""
    for side, other in (("Left", "Right"), ("Right", "Left")):
        if name.endswith(side):
            return name[: -len(side)] + other
    return name

