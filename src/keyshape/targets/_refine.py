r"""Render and compare: the mapping's targets the tracker's scores barely see, refined on the landmarks.

The score route (:func:`keyshape.targets._propose._take_mapping`) reads each ARKit target off
MediaPipe's score of it. Some scores hardly move with their target: on ICT-FaceKit's renders,
raising ``mouthLowerDown`` by 1 raises its score by 0.00–0.01, ``eyeSquint`` 0.04, ``jawOpen``
0.06 (the smiles: 0.3), and ``browOuterUp`` and ``mouthPucker`` read with the wrong side or
sign at times. The landmarks see all of them. So the character is rendered as the route
drives it, frame by frame (its weights ``P(t)``, the head turned by the video's tracked rotation),
and once more for each refined target ``j`` raised by ``δ``; MediaPipe tracks every render, and
per frame

.. math::

    \min_{\Delta, \omega} \lVert \tilde r(t) - J(t) \Delta - R(t) \omega \rVert^2
    + \lambda \lVert \Delta \rVert^2 + \mu \lVert \omega \rVert^2,
    \qquad 0 \le P_j(t) + \Delta_j \le 1,

with ``r(t)`` the video's 2-D landmarks less the render's at ``P(t)`` (the renders put on the
video's picture by one similarity for the whole take, fitted on the stable points), ``r̃(t) =
r(t) − median_t r(t)``, ``J(t)`` the landmarks' response to each target (finite differences of
the renders) and ``R(t)`` their response to a small move, scale, roll, pitch and yaw of the head
(pitch and yaw from the render's depths), which takes up the error of the head pose the render
was turned by (bounded least squares, Stark & Parker 1995).

The take median is the actor's versus the character's proportions: what differs between the two
faces whatever the expression. Without it, a character whose mouth is 25 % wider than the
actor's reads as a constant ``mouthPucker`` of 0.35 (measured on the caricature head of
``benchmarks/bench_rendered_loop.py``). It also takes the targets' mean level from the
landmarks, so that stays with the scores: the landmarks refine how each target moves.

The refined weights are smoothed (Gaussian, σ = 3 frames) and fitted through the key weights,
a constant and one gain per key (ridge 10⁻³ per frame, :func:`fit_through_keys`). The same rows
are also fitted on the landmarks of every frame at once (:func:`fit_in_landmarks`: the key
weights carry each frame's evidence to the rows directly, no per-frame bounds), and the two are
averaged: they err differently, and half and half beats either. The result replaces the targets'
rows of the mapping: the character is still driven by the key weights alone, as the paper's
method has it. Measured on the rendered loop (BENCHMARKS.md, issue 13): ICT 22.3 % → 18.2 %,
the caricature 22.5 % → 17.8 % (MediaPipe's own scores: 35.1 % and 34.3 %: 0.52× on both).

References
----------
.. [1] P. B. Stark and R. L. Parker, "Bounded-variable least-squares: an algorithm and
   applications", Computational Statistics 10, 1995.
.. [2] S. Umeyama, "Least-squares estimation of transformation parameters between two point
   patterns", IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..containers import Rig, Track, Weights
from ._correspond import Correspondence
from ._mapping import SMALLEST_GAIN, Mapping, bounded_row, drive_gaze, retarget

__all__ = ["REFINED_SCORES", "Refinement", "fit_in_landmarks", "fit_through_keys", "refinable_targets",
           "refine_mapping", "solve_corrections"]

#: ARKit names of the targets refined on the landmarks: those whose score barely moves with them
#: in context (jaw, lower lip, squint), and the brows' outer raise and the pucker, which the
#: scores read with the wrong side or sign at times (measured on ICT: BENCHMARKS.md, issue 13).
REFINED_SCORES = ("jawOpen", "mouthLowerDownLeft", "mouthLowerDownRight", "eyeSquintLeft", "eyeSquintRight",
                  "browOuterUpLeft", "browOuterUpRight", "mouthPucker")

_HEAD_COLUMNS = 6  # pitch, yaw, move x, move y, scale, roll


@dataclass(frozen=True)
class Refinement:
    """What :func:`refine_mapping` did.

    Attributes
    ----------
    mapping : Mapping
        The mapping with the refined targets' rows (and offsets) replaced.
    targets : tuple of str
        The rig targets refined (empty: nothing was, see ``reason``).
    residual_px : (float, float)
        RMS per landmark of the residual (video less render, take median removed, the head's small
        moves fitted), in video pixels, at the route's weights and at the refined ones, before the
        fit through the keys; NaN when nothing was refined.
    reason : str
        Why nothing was refined ("" when something was).
    steps : dict str -> str
        With a floor (:func:`refine_mapping`'s ``floor``): which step each refined target keeps,
        ``"floor"`` (its score less the rest reading), ``"keys"`` (the route's row) or ``"refined"``.
    """

    mapping: Mapping
    targets: tuple[str, ...] = ()
    residual_px: tuple[float, float] = (float("nan"), float("nan"))
    reason: str = ""
    steps: dict = field(default_factory=dict)


def refinable_targets(rig_names) -> dict[str, int]:
    """The rig's targets named by :data:`REFINED_SCORES`: ``{rig target name: index}``.

    ARKit names in any of the usual spellings (``mouthLowerDown_L``, ``mouthLowerDownLeft``,
    ``MouthLowerDownLeft``); a target no such name gives is left to the scores.
    """
    from ..io.livelink import livelink_columns

    sources, _ = livelink_columns(rig_names)
    columns = {column.lower(): indices for column, indices in sources.items()}
    found = {}
    for score in REFINED_SCORES:
        for t in columns.get(score.lower(), ()):
            found[str(rig_names[t])] = int(t)
    return found


def solve_corrections(video: np.ndarray, base: np.ndarray, raised: np.ndarray, route: np.ndarray, *,
                      delta: float = 0.2, ridge: float = 1.0, turn: float = 1e-6,
                      stable: np.ndarray | None = None) -> tuple[np.ndarray, tuple[float, float]]:
    r"""Per-frame corrections ``Δ (n_frames, n)`` of ``n`` targets (the module docstring's problem).

    Parameters
    ----------
    video : (n_frames, n_points, 2) float
        The video's landmarks, pixels; NaN where no face.
    base : (n_frames, n_points, 3) float
        The render's at the route's weights (x, y in the render's pixels, z depth on the x scale).
    raised : (n, n_frames, n_points, 2) float
        The render's with each target raised by ``min(δ, 1 − P)`` (at least 10⁻³).
    route : (n_frames, n) float in [0, 1]
        The route's weights ``P(t)`` of the ``n`` targets.
    delta, ridge, turn : float, keyword-only
        ``δ``; ``λ`` in px² per unit weight²; ``μ`` for the head's small moves.
    stable : int array, optional, keyword-only
        The points the take's similarity is fitted on (default: all).

    Returns
    -------
    corrections : (n_frames, n) float
        ``Δ``, with ``0 ≤ P + Δ ≤ 1``; NaN on frames without a face in the video or the render.
    residual_px : (float, float)
        RMS residual per point (pixels of the video), the head's moves fitted, before and after.
    """
    from scipy.optimize import lsq_linear

    route = np.asarray(route, float)
    n_frames, n = route.shape
    out = np.full((n_frames, n), np.nan)
    systems = _frame_systems(video, base, raised, route, delta=delta, stable=stable)
    regular = np.diag([np.sqrt(ridge)] * n + [np.sqrt(turn)] * _HEAD_COLUMNS)
    before, after = [], []
    for f, jacobian, head, wanted in systems:
        design = np.column_stack([jacobian, head])
        low = np.concatenate([-route[f], [-1, -1], [-np.inf] * 4])
        high = np.concatenate([1 - route[f] + 1e-12, [1, 1], [np.inf] * 4])
        x = lsq_linear(np.vstack([design, regular]), np.concatenate([wanted, np.zeros(n + _HEAD_COLUMNS)]),
                       bounds=(low, high)).x
        out[f] = x[:n]
        alone = np.linalg.lstsq(head, wanted, rcond=None)[0]  # the head's moves alone
        before.append(np.mean((wanted - head @ alone) ** 2))
        after.append(np.mean((wanted - design @ x) ** 2))
    rms = (float(np.sqrt(2 * np.mean(before))), float(np.sqrt(2 * np.mean(after)))) if before else \
        (float("nan"), float("nan"))
    return out, rms


def _frame_systems(video, base, raised, route: np.ndarray, *, delta: float, stable) -> list:
    """Per frame seen in the video and every render: ``(f, J (2 n_points, n), H (2 n_points, 6),
    r̃ (2 n_points,))``, the targets' and the head's columns and the residual less its take median."""
    from ..alignment import procrustes

    video, base, raised = np.asarray(video, float)[..., :2], np.asarray(base, float), np.asarray(raised, float)
    n_points, n = video.shape[1], route.shape[1]
    stable = np.arange(n_points) if stable is None else np.asarray(stable)
    seen = np.isfinite(video).all(axis=(1, 2)) & np.isfinite(base).all(axis=(1, 2)) & \
        np.isfinite(raised).all(axis=(0, 2, 3))
    if seen.sum() < 2:
        return []
    take = procrustes(base[seen][:, stable, :2].reshape(-1, 2), video[seen][:, stable, :2].reshape(-1, 2))

    def align(points):  # (n_points, 2) render pixels -> video pixels
        return take.to_image(points[None])[0]

    frames = np.flatnonzero(seen)
    at = {f: align(base[f, :, :2]) for f in frames}
    residual = np.stack([video[f] - at[f] for f in frames])
    residual -= np.median(residual, axis=0)  # the two faces' proportions
    systems = []
    one, zero = np.ones(n_points), np.zeros(n_points)
    for i, f in enumerate(frames):
        steps = np.maximum(np.minimum(route[f] + delta, 1) - route[f], 1e-3)
        jacobian = np.column_stack([(align(raised[j, f, :, :2]) - at[f]).ravel() / steps[j] for j in range(n)])
        depth = base[f, :, 2] - base[f, :, 2].mean()
        centred = at[f] - at[f].mean(axis=0)
        head = np.column_stack([np.column_stack(pair).ravel() for pair in (
            (zero, -depth), (depth, zero),  # pitch, yaw
            (one, zero), (zero, one),  # move
            (centred[:, 0], centred[:, 1]), (-centred[:, 1], centred[:, 0]))])  # scale, roll
        if np.isfinite(jacobian).all() and np.isfinite(head).all():
            systems.append((f, jacobian, head, residual[i].ravel()))
    return systems


def fit_in_landmarks(video, base, raised, route: np.ndarray, key_weights: np.ndarray, *, delta: float = 0.2,
                     ridge: float = 0.1, stable=None) -> tuple[np.ndarray, np.ndarray]:
    r"""The refined targets' constant and gains fitted on the landmarks of every frame at once.

    With ``x(t) = [1, w(t)]`` (the key weights) and ``Θ = [c, G]`` the rows sought, each frame's
    residual less what the head's small moves explain (projected off their columns, ``Π_t``):

    .. math::

        \min_{0 \le c \le 1,\; G \ge 0}
        \sum_t \lVert \Pi_t \big(\tilde r(t) + J(t) P(t) - J(t)\, \Theta\, x(t)\big) \rVert^2
        + \lambda \bar d \lVert G \rVert^2

    ``d̄ = Σ_t tr(J̃ᵀJ̃) / n`` with ``J̃ = Π_t J(t)``, a target's information summed over the frames (so
    ``λ`` has no unit: a gain is shrunk by about ``v / (v + λ)`` for a key weight of variance ``v``;
    on the rendered loop, blended as :func:`refine_mapping` does, λ = 0.1–0.3 give 17.8–17.9 % on ICT
    and 17.5 % on the caricature, λ = 0.01 18.2 % and 17.9 %, on renders of the loop). One bounded least-squares
    problem of ``n (n_keys + 1)`` unknowns, no per-frame bounds: the key weights carry the evidence of every
    frame to the mapping directly, where :func:`solve_corrections` estimates each frame alone.

    Returns
    -------
    offset : (n,) float in [0, 1]
    gains : (n, n_keys) float, ``≥ 0``
    """
    route = np.asarray(route, float)
    W = np.nan_to_num(np.asarray(key_weights, float))
    n, size = route.shape[1], route.shape[1] * (W.shape[1] + 1)
    normal, moment = np.zeros((size, size)), np.zeros(size)
    for f, jacobian, head, residual in _frame_systems(video, base, raised, route, delta=delta, stable=stable):
        basis, _ = np.linalg.qr(head)
        J = jacobian - basis @ (basis.T @ jacobian)
        y = residual - basis @ (basis.T @ residual) + J @ route[f]
        x = np.concatenate([[1.0], W[f]])
        normal += np.kron(np.outer(x, x), J.T @ J)
        moment += np.kron(x, J.T @ y)
    information = np.trace(normal[:n, :n]) / n  # a target's information, summed over the frames
    penalty = np.full(size, ridge * information)
    penalty[:n] = 0.0  # the constant is not shrunk
    theta = _bounded_quadratic(normal + np.diag(penalty), moment, n).reshape(-1, n)
    return theta[0], theta[1:].T


def _bounded_quadratic(hessian: np.ndarray, moment: np.ndarray, n: int) -> np.ndarray:
    """``θ (size,)`` minimising ``θᵀ H θ − 2 mᵀ θ`` with the first ``n`` (the offsets) in [0, 1] and
    the rest (the gains) ``>= 0``: BVLS on ``|R θ − R⁻ᵀ m|²``, ``H = RᵀR``."""
    from scipy.linalg import solve_triangular
    from scipy.optimize import lsq_linear

    size = len(moment)
    factor = np.linalg.cholesky(hessian + 1e-12 * np.trace(hessian) / size * np.eye(size)).T  # upper R
    rhs = solve_triangular(factor, moment, trans="T")
    upper = np.r_[np.ones(n), np.full(size - n, np.inf)]
    return lsq_linear(factor, rhs, bounds=(np.zeros(size), upper), method="bvls").x


def fit_through_keys(refined: np.ndarray, key_weights: np.ndarray, *, ridge: float = 1e-3
                     ) -> tuple[np.ndarray, np.ndarray]:
    r"""Each refined target as a constant plus one gain per key: ``y_j(t) ≈ c_j + Σ_k g_jk w_k(t)``.

    .. math::

        \min_{0 \le c_j \le 1,\; g_j \ge 0} \sum_t \big(y_j(t) - c_j - g_j \cdot w(t)\big)^2
        + \lambda n_t \lVert g_j \rVert^2

    (bounded least squares: a mapping's gains are ``>= 0``).

    Parameters
    ----------
    refined : (n_frames, n) float
        The refined weights; rows with NaN are left out.
    key_weights : (n_frames, n_keys) float
        NaN read as 0 (as :func:`~keyshape.targets._mapping.retarget` does).
    ridge : float, keyword-only

    Returns
    -------
    offset : (n,) float in [0, 1]
    gains : (n, n_keys) float, ``≥ 0``
    """
    refined = np.asarray(refined, float)
    W = np.nan_to_num(np.asarray(key_weights, float))
    ok = np.isfinite(refined).all(axis=1)
    X = np.column_stack([np.ones(int(ok.sum())), W[ok]])
    rows = [bounded_row(X, refined[ok, j], ridge) for j in range(refined.shape[1])]
    return np.array([c for c, _ in rows]), np.array([g for _, g in rows]).reshape(refined.shape[1], W.shape[1])


def refine_mapping(mapping: Mapping, rig: Rig, correspondence: Correspondence, track: Track, weights: Weights, *,
                   colours: np.ndarray | None = None, delta: float = 0.2, ridge: float = 1.0, smooth: float = 3.0,
                   blend: float = 0.5, size: int = 512, progress: bool = True, floor: tuple | None = None
                   ) -> Refinement:
    """The mapping with :data:`REFINED_SCORES`' targets refined by render and compare (module docstring).

    Parameters
    ----------
    mapping : Mapping
        The score route's mapping (with its ``gaze`` entries).
    rig : Rig
        The character (a face MediaPipe finds on a render: the correspondence was found so).
    correspondence : Correspondence
        Where MediaPipe's 478 landmarks sit on ``rig``.
    track : Track
        The take's track (landmarks, head matrices, scores), as the key weights were solved on.
    weights : Weights
        The key weights ``(n_frames, n_keys)`` of the take.
    colours : (n_vertices, 3 or 4) float, optional, keyword-only
        What the character looks like (see :func:`keyshape.targets.find_correspondence`).
    delta, ridge : float, keyword-only
        See :func:`solve_corrections`.
    smooth : float, keyword-only
        Gaussian σ (frames) of the refined weights before the fit through the keys.
    blend : float in [0, 1], keyword-only
        The mapping rows are ``blend`` times :func:`fit_in_landmarks`'s plus ``1 − blend`` times
        those of the per-frame estimates (:func:`solve_corrections`, smoothed, then
        :func:`fit_through_keys`). The two err differently (the first unbounded, over the whole take;
        the second bounded to [0, 1] frame by frame): on renders of the rendered loop, face area,
        ICT / caricature, 18.5 / 17.8 % and 18.7 / 18.3 % alone, 17.9 / 17.5 % blended half and half
        (0.4 or 0.6: ±0.1). 0: the per-frame fit alone.
    size : int, keyword-only
        Side of the renders, pixels.
    progress : bool, keyword-only
    floor : tuple of (target, score, rest) or None, keyword-only
        The floor's score channels (:func:`keyshape.targets._floor.score_floor`). Given, each
        refined target keeps the step that best explains the video's landmarks on frames its
        rows were not fitted on (:func:`judge_steps`): the floor (its channel), the route's row, or
        the refined row; ``Refinement.steps`` says which.

    Returns
    -------
    Refinement
        Unchanged mapping (and a ``reason``) when the rig has none of the targets, the take has
        no head matrices, or MediaPipe finds the rendered face in too few frames.
    """
    from ..schemes import stable_points

    found = refinable_targets(rig.names)
    found = {name: t for name, t in found.items() if name in mapping.targets and
             name not in {g[0] for g in mapping.gaze}}
    if not found:
        return Refinement(mapping, reason="the rig has none of the targets refined on the landmarks")
    if track.head_matrix is None or not np.isfinite(track.head_matrix).any() or track.n_landmarks != 478:
        return Refinement(mapping, reason="the take has no MediaPipe head pose to turn the renders by")
    anim = drive_gaze(retarget(weights, mapping), mapping, track.blendshapes, track.blendshape_names)
    route = np.column_stack([anim.values[:, anim.names.index(n)] if n in anim.names else
                             np.zeros(len(anim.values)) for n in rig.names])
    route = np.clip(np.nan_to_num(route), 0, 1)
    indices = list(found.values())
    tracks = _render_and_track(rig, correspondence, track, route, indices, delta=delta, colours=colours,
                               size=size, progress=progress)
    if tracks is None:
        return Refinement(mapping, reason="MediaPipe found the rendered character in too few frames")
    base, raised = tracks
    corrections, rms = solve_corrections(track.points[..., :2], base, raised, route[:, indices], delta=delta,
                                         ridge=ridge, stable=stable_points(478))
    refined = route[:, indices] + corrections  # NaN on the frames not seen
    seen = np.isfinite(refined).all(axis=1)
    if seen.sum() < 2 * (mapping.n_keys + 1):
        return Refinement(mapping, reason="too few frames with a face in both the take and the renders")
    if smooth:
        refined = _smooth_seen(refined, seen, smooth)
    columns = [weights.names.index(k) for k in mapping.sources]
    per_frame = fit_through_keys(refined, weights.values[:, columns])
    at_once = fit_in_landmarks(track.points[..., :2], base, raised, route[:, indices], weights.values[:, columns],
                               delta=delta, stable=stable_points(478))
    offset = np.maximum(blend * at_once[0] + (1 - blend) * per_frame[0], 0.0)  # both >= 0; rounding can go -1e-20
    gains = blend * at_once[1] + (1 - blend) * per_frame[1]  # both >= 0
    gains[gains < SMALLEST_GAIN] = 0.0
    matrix, offsets = np.array(mapping.matrix), np.array(mapping.offset)
    rows = [mapping.targets.index(name) for name in found]
    matrix[rows], offsets[rows] = gains, offset
    refined_mapping = replace(mapping, matrix=matrix, offset=offsets)
    if floor is None:
        return Refinement(refined_mapping, tuple(found), rms)
    channels = {t: (t, score, rest) for t, score, rest in floor}
    names = track.blendshape_names or ()
    scores = np.nan_to_num(np.asarray(track.blendshapes, float)) if track.blendshapes is not None else None
    floored = np.column_stack([
        np.clip(scores[:, list(names).index(channels[n][1])] - channels[n][2], 0, 1)
        if scores is not None and n in channels and channels[n][1] in names else route[:, t]
        for n, t in found.items()])
    crossed = _cross_fitted(track.points[..., :2], base, raised, route[:, indices], corrections,
                            weights.values[:, columns], delta=delta, smooth=smooth, blend=blend)
    candidates = np.stack([floored, route[:, indices], crossed])  # (3, n_frames, n)
    best = judge_steps(track.points[..., :2], base, raised, route[:, indices], candidates, delta=delta,
                       stable=stable_points(478))
    steps = {name: STEPS[int(b)] for name, b in zip(found, best)}
    for name, step in steps.items():
        if step != "refined":
            r = mapping.targets.index(name)
            matrix[r], offsets[r] = mapping.matrix[r], mapping.offset[r]
    gaze = [g for g in mapping.gaze if g[0] not in found] + \
        [channels[n] for n, step in steps.items() if step == "floor" and n in channels]
    for name, step in steps.items():
        if step == "floor" and name in channels:
            r = mapping.targets.index(name)
            matrix[r], offsets[r] = 0.0, 0.0
    chosen = replace(mapping, matrix=matrix, offset=offsets,
                     gaze=tuple(g for t in mapping.targets for g in gaze if g[0] == t))
    return Refinement(chosen, tuple(found), rms, steps=steps)


STEPS = ("floor", "keys", "refined")


def _cross_fitted(video, base, raised, route, corrections, key_weights, *, delta: float, smooth: float, blend: float,
                  block: int = 30) -> np.ndarray:
    """The refined weights ``(n_frames, n)`` of each frame from rows fitted on the other half of the take
    (blocks of ``block`` frames, alternating): what the refinement predicts where it was not fitted."""
    from ..schemes import stable_points

    n_frames = len(route)
    fold = (np.arange(n_frames) // block) % 2
    out = np.full(route.shape, np.nan)
    W = np.nan_to_num(np.asarray(key_weights, float))
    X = np.column_stack([np.ones(n_frames), W])
    for held in (0, 1):
        fit = fold != held
        refined = np.where(fit[:, None], route + corrections, np.nan)
        seen = np.isfinite(refined).all(axis=1)
        if seen.sum() < 2 * (W.shape[1] + 1):
            return route.copy()
        if smooth:
            refined = _smooth_seen(refined, seen, smooth)
        per_frame = fit_through_keys(refined, W)
        masked = np.where(fit[:, None, None], np.asarray(video, float), np.nan)
        at_once = fit_in_landmarks(masked, base, raised, route, W, delta=delta, stable=stable_points(478))
        offset = blend * at_once[0] + (1 - blend) * per_frame[0]
        gains = blend * at_once[1] + (1 - blend) * per_frame[1]
        out[~fit] = np.clip(X[~fit] @ np.column_stack([offset, gains]).T, 0, 1)
    return out


def judge_steps(video, base, raised, route: np.ndarray, candidates: np.ndarray, *, delta: float = 0.2,
                stable=None) -> np.ndarray:
    r"""Which candidate weights of each target best explain the video's landmarks: ``(n,)`` int.

    Linearised at the rendered route ``P``: candidate ``X`` of target ``j`` leaves the residual
    ``Π_t (r̃(t) − J_j(t) d(t) + \overline{J_j d})`` per frame, ``d = X_j − P_j``, the head's small
    moves projected off (``Π_t``) and the take mean of the change removed (as the residual's take
    median is: the landmarks do not judge a target's mean level, the two faces' proportions do
    that). The candidate with the least summed squared residual wins.

    Parameters
    ----------
    video, base, raised, route
        As :func:`solve_corrections`.
    candidates : (n_candidates, n_frames, n) float
        Each target's candidate weights per frame (NaN: the frame left out).

    Returns
    -------
    (n,) int
        The index of the best candidate per target (the first on a tie).
    """
    route = np.asarray(route, float)
    n = route.shape[1]
    systems = _frame_systems(video, base, raised, route, delta=delta, stable=stable)
    frames = [f for f, *_ in systems]
    ok = np.isfinite(candidates[:, frames]).all(axis=(0, 2))
    systems = [s for s, good in zip(systems, ok) if good]
    if not systems:
        return np.ones(n, dtype=int)  # no evidence: the route as it is
    projected = []
    for f, jacobian, head, residual in systems:
        basis, _ = np.linalg.qr(head)
        projected.append((f, jacobian - basis @ (basis.T @ jacobian), residual - basis @ (basis.T @ residual)))
    cost = np.zeros((len(candidates), n))
    for j in range(n):
        for c, candidate in enumerate(candidates):
            change = np.stack([J[:, j] * (candidate[f, j] - route[f, j]) for f, J, _ in projected])
            change -= change.mean(axis=0)
            cost[c, j] = sum(float(((r - d) ** 2).sum()) for (_, _, r), d in zip(projected, change))
    return np.argmin(cost, axis=0)


def _smooth_seen(values: np.ndarray, seen: np.ndarray, sigma: float) -> np.ndarray:
    """``values (n_frames, n)`` smoothed over time on the frames ``seen`` (normalised convolution)."""
    from scipy.ndimage import gaussian_filter1d

    filled = np.where(seen[:, None], values, 0.0)
    mass = gaussian_filter1d(seen.astype(float), sigma, mode="nearest")
    out = gaussian_filter1d(filled, sigma, axis=0, mode="nearest") / np.maximum(mass, 1e-9)[:, None]
    out[~seen] = np.nan
    return out


def _front_turn(points: np.ndarray) -> np.ndarray:
    """The view ``(3, 3)`` that turns the character's face to +Z, Y up: of the axis-aligned views the
    correspondence tries (+Z, −Y, +Y, ...), the one nearest the rotation that best lays the corresponded
    points onto MediaPipe's canonical face. Snapped, because that fit tilts with the character's
    proportions (11° on the caricature head, whose chin and nose are shorter), which costs more
    than it finds."""
    from ..alignment import procrustes
    from ..capture.model_file import canonical_face
    from ._correspond_auto import _VIEWS, view_rotation

    canonical = canonical_face()[0]
    n = min(len(canonical), len(points))
    ok = np.isfinite(points[:n]).all(axis=1)
    fitted = procrustes(points[:n][ok], canonical[:n][ok]).rotations[0]
    views = [view_rotation(axis, up) for axis, up in _VIEWS]
    return max(views, key=lambda view: float(np.trace(view.T @ fitted)))


def _head_turns(head_matrix: np.ndarray) -> np.ndarray:
    """Rotations ``(n_frames, 3, 3)`` of MediaPipe's head matrices relative to their median (glTF
    axes, as the matrices are); identity where a matrix is missing."""
    from scipy.spatial.transform import Rotation

    linear = np.asarray(head_matrix, dtype=float)[:, :3, :3]
    ok = np.isfinite(linear).all(axis=(1, 2))
    out = np.tile(np.eye(3), (len(linear), 1, 1))
    if not ok.any():
        return out
    u, _, vt = np.linalg.svd(linear[ok])
    turns = Rotation.from_matrix(u @ vt)
    rest = Rotation.from_rotvec(np.median(turns.as_rotvec(), axis=0))
    out[ok] = (turns * rest.inv()).as_matrix()
    return out


def _render_and_track(rig: Rig, corr: Correspondence, track: Track, route: np.ndarray, indices: list[int], *,
                      delta: float, colours, size: int, progress: bool, min_seen: float = 0.5):
    """The render's landmarks at ``route`` ``(n_frames, 478, 3)`` and with each target in ``indices``
    raised by ``delta`` ``(n, n_frames, 478, 2)``; None when MediaPipe sees too few rendered frames."""
    from tqdm import tqdm

    from ..capture import track_video
    from ..exceptions import NoFaceError
    from ..render import frame_points, make_renderer
    from ..render.encode import VideoWriter
    from ._correspond_auto import _seen

    shown, faces = _seen(colours, np.asarray(rig.faces, dtype=np.int64))
    points = corr.points(rig.vertices[None])[0]
    pivot = np.nanmean(points, axis=0)
    front = _front_turn(points - pivot)
    turns = _head_turns(track.head_matrix) @ front  # (n_frames, 3, 3)
    camera = frame_points((points - pivot) @ front.T, margin=1.6)
    fps = track.fps if track.fps and np.isfinite(track.fps) else 30.0
    passes = [route]  # the route, then each target raised
    for t in indices:
        lifted = route.copy()
        lifted[:, t] = np.clip(lifted[:, t] + delta, 0, 1)
        passes.append(lifted)
    bar = tqdm(total=2 * len(passes) * len(route), desc="render and compare", unit="frame",
               disable=None if progress else True)
    results = []
    try:
        with tempfile.TemporaryDirectory(prefix="keyshape-refine-") as scratch, \
                make_renderer(faces, size, size, n_vertices=rig.n_vertices, backend="auto",
                              colours=shown) as renderer:
            for pose in passes:
                path = Path(scratch) / f"{len(results):02d}.mp4"
                with VideoWriter(path, size, size, fps, crf=16) as out:
                    for f in range(len(pose)):
                        posed = rig.pose(pose[f : f + 1])[0] - pivot
                        out.write(renderer.render(posed @ turns[f].T, camera))
                        bar.update()
                try:
                    tracked = track_video(path, progress=False)
                except NoFaceError:
                    return None
                bar.update(len(pose))
                if tracked.n_frames != len(route) or tracked.valid.mean() < min_seen:
                    return None
                results.append(tracked.points)
    finally:
        bar.close()
    return results[0], np.stack([r[..., :2] for r in results[1:]])
