"""A take in Gram form, filled a chunk of frames at a time, then solved as :func:`solve_weights` would.

Per region the solvers read of frame ``t`` only ``c_t = Aᵀ b_t`` (K numbers) and ``‖b_t‖²``
(:func:`keyshape.decompose._solve.reduce_rows`): the smoothed solve is a problem over the whole
take, but in these ``K``-dimensional terms. So a long take is aligned and reduced chunk by chunk,
and its landmarks (``n_frames × n_landmarks × n_dims``) never exist all at once.

With the landmarks' visibility (``weighted``), the smoothed weighted solve reads of each frame
its own Gram matrix ``G_t = Aᵀ V_t A`` (``K × K``: the visibility times the landmarks' outer
products), ``c_t = Aᵀ V_t b_t`` and ``b_tᵀ V_t b_t``
(:func:`keyshape.decompose._weighted.solve_weighted_gram`): ``K² + K + 1`` numbers a frame,
written by one compiled pass over a chunk's frames per region
(:func:`keyshape.decompose._kernels.weighted_gram_rows`, which also brings them to the canonical
frame), on every core, with no temporary of the chunk's size.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from ..containers import KeyShapes, Poses
from ..exceptions import InputError
from ._solve import _check_smoothness, _check_tol, _mu, _upper_bounds, reduce_rows, solve_reduced

__all__ = ["GramTake"]

_PARALLEL_FRAMES = 20_000  # below this many frames a region solves in well under a second: no threads
_PARALLEL_REDUCE = 1024  # frames of a part of GramTake.add's weighted reduction on a thread of its own


@dataclass(frozen=True, eq=False)
class _Region:
    keys: np.ndarray  # (K,) int, the region's keys
    span: slice  # its landmarks in GramTake.landmarks
    A: np.ndarray  # (m, K), the keys' deltas as columns
    C: np.ndarray  # (n_frames, K), c_t = Aᵀ b_t (Aᵀ V_t b_t when weighted)
    sq: np.ndarray  # (n_frames,), ‖b_t‖² (b_tᵀ V_t b_t)
    T: np.ndarray | None = None  # (n_landmarks, K (K + 1) / 2): the upper triangles of Σ over a landmark's
    #                              coordinates of a aᵀ, row by row (weighted)
    G: np.ndarray | None = None  # (n_frames, K, K): Aᵀ V_t A (weighted)
    gone: np.ndarray | None = None  # (n_frames,) bool: the region hidden (no data term; weighted)
    hidden: list | None = None  # [bool]: any landmark of the region seen less than fully (weighted)


class GramTake:
    """An aligned take on ``keys``, region by region, in the Gram form the solvers read.

    Parameters
    ----------
    keys : KeyShapes
    n_frames : int
    weighted : bool
        :meth:`add` also takes each frame's visibility, and a region with hidden landmarks is
        solved as the visibility-weighted solve (not ``convex``).

    Attributes
    ----------
    landmarks : (n_needed,) int
        The landmarks of the regions with keys, region after region: what :meth:`add` is given
        of each frame.
    valid : (n_frames,) bool
        The frames added with a face.

    Notes
    -----
    Without ``weighted`` every landmark counts fully. The weighted solve with ``convex`` needs
    the frames themselves: a take with hidden landmarks goes through :func:`solve_weights` for it.

    Examples
    --------
    >>> from keyshape.alignment import align
    >>> from keyshape.datasets import make_performance
    >>> from keyshape.decompose import solve_weights
    >>> perf = make_performance(n_frames=40)
    >>> keys = KeyShapes(perf.neutral, perf.key_deltas, ["a", "b", "c", "d"], perf.extreme_frames,
    ...                  perf.key_regions, perf.regions)
    >>> aligned = align(perf.track, reference=keys.neutral, stable=perf.stable)[0]
    >>> take = GramTake(keys, aligned.n_frames)
    >>> for lo in range(0, 40, 16):
    ...     take.add(lo, aligned.points[lo:lo + 16][:, take.landmarks])
    >>> whole = solve_weights(aligned, keys, smoothness=0.1, upper=1.0).values
    >>> bool(np.allclose(take.solve(smoothness=0.1, upper=1.0), whole, atol=1e-6))
    True
    """

    def __init__(self, keys: KeyShapes, n_frames: int, *, weighted: bool = False):
        self.weighted = bool(weighted)
        keyed = [(lm, ks) for r, lm in keys.regions.items() if len(ks := np.asarray(keys.keys_of(r)))]
        self.n_keys, self.n_frames = keys.n_keys, int(n_frames)
        self.landmarks = np.concatenate([lm for lm, _ in keyed]).astype(np.intp) if keyed else np.zeros(0, np.intp)
        self._neutral = keys.neutral[self.landmarks]
        edges = np.cumsum([0, *(len(lm) for lm, _ in keyed)])
        self._regions = [self._region(keys, np.asarray(lm), ks, slice(a, b)) for (lm, ks), a, b
                         in zip(keyed, edges[:-1], edges[1:])]
        self.valid = np.zeros(self.n_frames, dtype=bool)

    def _region(self, keys: KeyShapes, landmarks: np.ndarray, ks: np.ndarray, span: slice) -> _Region:
        # k: key, p: region landmark, d: dimension; A[(p, d), k] = deltas[k, p, d]
        A = keys.deltas[np.ix_(ks, landmarks)].reshape(len(ks), -1).T
        n, K = self.n_frames, len(ks)
        if not self.weighted:
            return _Region(ks, span, A, np.empty((n, K)), np.empty(n))
        a = A.reshape(len(landmarks), keys.n_dims, K)  # rows of A are (landmark, dimension) pairs
        H = np.einsum("pdk,pdl->pkl", a, a)
        upper = np.triu_indices(K)
        T = np.ascontiguousarray(H[:, upper[0], upper[1]])
        return _Region(ks, span, A, np.empty((n, K)), np.empty(n), T, np.empty((n, K, K)), np.zeros(n, bool), [False])

    def add(self, start: int, points: np.ndarray, seen: np.ndarray | None = None, *, poses: Poses | None = None,
            columns: np.ndarray | None = None) -> None:
        """Frames ``start ... start + n - 1``: ``points (n, n_needed, n_dims)`` float, the landmarks
        :attr:`landmarks`, aligned onto the key set's neutral, or (``weighted`` only) with ``poses``
        (n frames) in the image frame, brought to the canonical one by the reduction's kernel;
        NaN frames have no face. ``seen (n, n_needed)``: their visibility in [0, 1] (``weighted``
        only; None: all seen), or ``(n, n_seen)`` with ``columns (n_needed,)`` int, the landmarks'
        columns in it (a track's visibility rows, not copied).

        Weighted, each region's frames are reduced in one compiled pass
        (:func:`keyshape.decompose._kernels.weighted_gram_rows`), straight into its arrays."""
        n = len(points)
        stop = start + n
        face = np.isfinite(points[:, :1, 0]).all(axis=1) if points.shape[1] else np.ones(n, bool)
        if poses is not None:  # a NaN pose (a degenerate frame) is no face
            face &= np.isfinite(poses.scales) & np.isfinite(poses.rotations).all(axis=(1, 2)) \
                & np.isfinite(poses.translations).all(axis=1)
        if not self.weighted:
            if poses is not None:
                raise ValueError("poses are for a weighted take; align the points first (alignment.to_canonical)")
            deltas = points - self._neutral  # b_t of every region, side by side
            for region in self._regions:
                B = deltas[:, region.span].reshape(n, -1)  # a view: the region's b_t, flattened
                region.C[start:stop], region.sq[start:stop] = reduce_rows(region.A, B)
            self.valid[start:stop] = face
            return
        from . import _kernels  # (numba, loaded on the first weighted take, as in _solve)
        from ._weighted import HIDDEN

        if poses is None:
            d = points.shape[2]
            rotations, translations, scales = np.repeat(np.eye(d)[None], n, axis=0), np.zeros((n, d)), np.ones(n)
        else:
            rotations, translations, scales = poses.rotations, poses.translations, poses.scales
        if seen is None:
            seen, columns = np.ones((n, 1)), np.zeros(points.shape[1], np.intp)
        elif columns is None:
            columns = np.arange(points.shape[1])
        columns = np.asarray(columns, dtype=np.intp)

        def reduce(job: tuple[_Region, slice]) -> bool:
            region, part = job
            rows = slice(start + part.start, start + part.stop)
            return _kernels.weighted_gram_rows(points[part, region.span], rotations[part], translations[part],
                                               scales[part], face[part], self._neutral[region.span], seen[part],
                                               columns[region.span], region.A, region.T, HIDDEN, region.G[rows],
                                               region.C[rows], region.sq[rows], region.gone[rows])

        # every frame is reduced on its own: the frames are split in one part per core (for enough of them)
        parts = _parts(n, min(os.cpu_count() or 1, n // _PARALLEL_REDUCE) or 1)
        tasks = [(r, part) for r in self._regions for part in parts]
        if len(parts) > 1:
            with ThreadPoolExecutor(max_workers=len(parts)) as pool:  # the kernel releases the GIL
                partial = list(pool.map(reduce, tasks))
        else:
            partial = [reduce(t) for t in tasks]
        for (region, _), hidden in zip(tasks, partial):
            region.hidden[0] = region.hidden[0] or bool(hidden)
        self.valid[start:stop] = face

    def solve(self, start: int = 0, stop: int | None = None, *, upper: float | np.ndarray | None = None,
              smoothness: float = 0.0, convex: bool = False, tol: float = 1e-7) -> np.ndarray:
        """(stop - start, n_keys) weights of frames ``start ... stop - 1`` solved as one take.

        The same weights as :func:`keyshape.decompose.solve_weights` on those frames (to the
        solver's tolerance), with the same options: NaN rows without a face when ``smoothness``
        is 0; with smoothing gaps between faces bridged and the frames before the first or
        after the last face NaN.
        """
        stop = self.n_frames if stop is None else stop
        upper = _upper_bounds(upper, self.n_keys)
        smoothness, tol = _check_smoothness(smoothness), _check_tol(tol)
        valid = self.valid[start:stop]
        values = np.zeros((len(valid), self.n_keys))
        # Without smoothing every frame is its own problem: each region's frames are split in one
        # part per core, so the threads share the work evenly however the regions' sizes differ.
        parts = _parts(len(valid), _workers(len(valid)) if smoothness == 0.0 else 1)
        tasks = [(r, part) for r in self._regions for part in parts]

        def task(job: tuple[_Region, slice]) -> np.ndarray:
            r, part = job
            rows, here = slice(start + part.start, start + part.stop), valid[part]
            if r.G is not None and r.hidden[0]:  # hidden landmarks: the weighted solve
                from ._weighted import solve_weighted_frames, solve_weighted_gram

                if convex:
                    raise InputError("a take with hidden landmarks is solved from its frames with convex "
                                     "(solve_weights), not in Gram form")
                seen = here & ~r.gone[rows]
                if smoothness == 0.0:
                    return solve_weighted_frames(r.G[rows], r.C[rows], seen, upper[r.keys])
                out = solve_weighted_gram(r.G[rows], r.C[rows], r.sq[rows], seen, _mu(r.A.T @ r.A, smoothness),
                                          upper[r.keys], tol=tol)
                if out is not None:
                    return out
                raise InputError("the weighted smoothed solve failed: the region's keys are degenerate")
            sq = np.where(here, r.sq[rows], np.nan)  # NaN rows: frames without a face
            return solve_reduced(r.A.T @ r.A, r.C[rows], sq, upper[r.keys], smoothness, bool(convex), tol)

        for (r, part), solved in zip(tasks, _each(task, tasks, len(valid))):
            values[part, r.keys] = solved
        if smoothness == 0.0:
            values[~valid] = np.nan
        return values


def _workers(n_frames: int) -> int:
    """Threads for a take of ``n_frames``: one per core for a long take, else 1."""
    return (os.cpu_count() or 1) if n_frames >= _PARALLEL_FRAMES else 1


def _parts(n_frames: int, n_parts: int) -> list[slice]:
    """``n_parts`` consecutive slices of about equal size covering ``0 ... n_frames - 1``."""
    edges = np.linspace(0, n_frames, max(n_parts, 1) + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in pairwise(edges)]


def _each(solve, tasks: list, n_frames: int) -> list[np.ndarray]:
    """``solve(task)`` for every task (a region, or part of one), on one thread per core for a long
    take: the tasks are independent problems, and their compiled kernels and BLAS calls release the GIL."""
    workers = min(len(tasks), _workers(n_frames))
    if workers < 2:
        return [solve(t) for t in tasks]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(solve, tasks))
