"""``keyshape solve`` on a track file: the take streamed through alignment into the solvers' Gram form.

:func:`solve_take` holds a take's landmarks twice (the track and its aligned copy; 100,000
frames of 478 points are 1.15 GB each in float64), though the solvers read of each frame only
``c_t = Aᵀ b_t`` and ``‖b_t‖²`` per region (:class:`keyshape.decompose.GramTake`). Here a chunk
of frames at a time is read, aligned on the stable points (Umeyama, batched), brought into the
canonical frame on the regions' landmarks only, and reduced; then the whole take is solved on
the reduced data, exactly as :func:`solve_take` solves it. A take with hidden landmarks (real
tracks read a few percent hidden nearly everywhere) keeps per frame its weighted Gram form
instead, ``Aᵀ V_t A``, ``Aᵀ V_t b_t`` and ``b_tᵀ V_t b_t`` (``K² + K + 1`` numbers), which is all
the smoothed weighted solve reads.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..alignment import procrustes, to_canonical
from ..capture.filters import GapReport, fill_edges, gap_report, hold_neutral, segments
from ..containers import KeyShapes, Poses, Weights
from ..decompose import GramTake
from ..defaults import DEFAULT_SMOOTHNESS, DEFAULT_UPPER
from ..exceptions import InputError
from ..io import TrackFile, load_track, open_track
from ..schemes import stable_points
from ._strict import converged

__all__ = ["solve_track_file", "SolvedFile"]

CHUNK = 4096  # frames read and aligned at a time (about 20 MB of float32 points at 478 landmarks)
_BLOCK_BYTES = 1 << 18  # unweighted: the regions' points brought to the canonical frame and reduced at a time


@dataclass(frozen=True)
class SolvedFile:
    """A track file decomposed on a key set: weights : Weights (n_frames, n_keys); gaps : GapReport."""

    weights: Weights
    gaps: GapReport


def solve_track_file(path: str | Path, keys: KeyShapes, *, smoothness: float = DEFAULT_SMOOTHNESS,
                     upper: float | None = DEFAULT_UPPER, convex: bool = False, max_bridge: float = 0.5,
                     chunk: int = CHUNK, visibility: str = "auto") -> SolvedFile:
    """The weights of a track file on ``keys``: :func:`solve_take`'s, without the take in memory.

    The points are streamed in chunks of ``chunk`` frames (:meth:`keyshape.io.track.TrackFile.chunks`).
    A take with hidden landmarks (visibility below 1 in a keyed region, as nearly every real
    track has) is streamed too, each frame reduced to its weighted Gram form (``Aᵀ V_t A``,
    ``Aᵀ V_t b_t``, ``b_tᵀ V_t b_t``: :class:`keyshape.decompose.GramTake` with ``weighted``),
    unless ``convex``: then its weighted solve needs the frames themselves, and it is loaded
    whole and goes through :func:`solve_take`, as a file that cannot be streamed (a landmark
    CSV) does. Options as :func:`solve_take`'s; ``visibility="off"``: the track's visibility is
    ignored (every landmark seen).
    """
    source = open_track(path)
    if source is not None and (source.n_landmarks != keys.n_landmarks or source.n_dims != keys.n_dims):
        raise InputError(f"the track has {source.n_landmarks} landmarks in {source.n_dims}D but the key set was "
                         f"made from {keys.n_landmarks} in {keys.n_dims}D")
    weighted = source is not None and visibility != "off" and not _all_seen(source, GramTake(keys, 0).landmarks)
    if source is None or (weighted and convex):
        from ._pipeline import solve_take  # with the key-shape search and tracking code: only this path needs it

        track = load_track(path) if source is None else source.load()
        if visibility == "off" and track.visibility is not None:
            track = replace(track, visibility=None)
        solved = solve_take(track, keys, smoothness=smoothness,
                            upper=upper, convex=convex, max_bridge=max_bridge)
        return SolvedFile(solved.weights, solved.gaps)
    take = GramTake(keys, source.n_frames, weighted=weighted)
    face = _reduce(source, keys, take, chunk)
    gaps = gap_report(face, max_bridge=int(round(max_bridge * source.fps)))
    values = np.full((source.n_frames, keys.n_keys), np.nan)
    with converged(smoothness):  # as in solve_take: converged weights or one line
        for start, stop in segments(gaps):  # held gaps split the take, as in solve_take
            solved = take.solve(start, stop, upper=upper, smoothness=smoothness, convex=convex)
            values[start:stop] = fill_edges(solved, face[start:stop])
    if smoothness > 0:
        values = hold_neutral(values, gaps)
    return SolvedFile(Weights(values, keys.names, source.fps, source.frame_index, source.time), gaps)


def _all_seen(source: TrackFile, landmarks: np.ndarray, frames: int = 1024) -> bool:
    """Whether every landmark ``landmarks`` is fully seen in every frame: read a block of frames at
    a time, stopping at the first that is not (a real track's first frames)."""
    if source.visibility is None:
        return True
    return all(bool((source.visibility[lo : lo + frames][:, landmarks] >= 1.0).all())
               for lo in range(0, source.n_frames, frames))


def _reduce(source: TrackFile, keys: KeyShapes, take: GramTake, chunk: int) -> np.ndarray:
    """Fill ``take`` from the file, chunk by chunk; returns the (n_frames,) bool frames with a face.

    Weighted, a chunk goes to :meth:`GramTake.add` whole, with its poses and its rows of the
    track's visibility (one compiled pass per region, on the cores), while the next chunk is read;
    else a block of frames at a time is brought to the canonical frame (in a core's cache) and
    reduced."""
    stable = keys.stable if keys.stable is not None else stable_points(keys.n_landmarks)
    stable = np.asarray(stable) % keys.n_landmarks
    needed = np.concatenate([stable, take.landmarks])  # of the 478 landmarks, the stable and the regions' ones
    reference, n_stable = keys.neutral[stable], len(stable)
    face = np.zeros(source.n_frames, dtype=bool)
    block = max(1, _BLOCK_BYTES // (8 * len(take.landmarks) * keys.n_dims))
    chunks = source.chunks(needed, frames=chunk)
    for start, seen, points in (_read_ahead(chunks) if take.weighted else chunks):
        face[start : start + len(seen)] = seen
        poses = procrustes(reference, points[:, :n_stable])  # x_image = s R x_canonical + t, per frame
        if take.weighted:
            take.add(start, points[:, n_stable:], source.visibility[start : start + len(seen)], poses=poses,
                     columns=take.landmarks)
            continue
        for lo in range(0, len(points), block):  # the regions' points block by block, in a core's cache
            part = slice(lo, lo + block)
            pose = Poses(poses.rotations[part], poses.translations[part], poses.scales[part])
            take.add(start + lo, to_canonical(points[part, n_stable:], pose))
    return face


def _read_ahead(chunks: Iterator[tuple]) -> Iterator[tuple]:
    """The items of ``chunks``, each next one read on a thread while the caller works on the last
    (the file's reads and the compiled reduction release the GIL); its errors are raised in order."""
    with ThreadPoolExecutor(max_workers=1) as pool:
        ahead = pool.submit(next, chunks, None)
        while (item := ahead.result()) is not None:
            ahead = pool.submit(next, chunks, None)
            yield item
