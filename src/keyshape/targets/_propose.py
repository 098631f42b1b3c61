"""Automatic target shapes: propose the character's version of every key shape.

Two routes, chosen by what the character already has:

* **transfer** (:func:`propose_targets`): the character is a neutral mesh (or its targets are to
  be ignored). Each key's landmark motion is carried onto the mesh and spread over it
  (:mod:`keyshape.targets._transfer`); the result is a :class:`~keyshape.containers.Rig` with one target
  per key, named after it, driven by :meth:`Mapping.by_name <keyshape.targets._mapping.Mapping.by_name>`.
* **mapping** (:func:`propose_mapping`): the character has blendshapes of its own (ARKit names
  or any set). Each key becomes the non-negative combination of the rig's targets whose motion
  at the corresponding points best reproduces the key's landmark motion::

      m_k = argmin_{m ≥ 0} ‖A m − b_k‖²_κ + Σ_t λ_t m_t²

  with ``A[:, t]`` target ``t``'s displacement at the corresponded landmarks and ``b_k`` the
  key's displacement there (in the character's space and proportions, zero on the landmarks of
  the other regions), rows weighted by each landmark's confidence ``κ`` (low on silhouettes), and
  ``λ_t`` growing with the motion target ``t`` makes where no landmark sees it (so an
  ``eyeLookDown`` that turns the eyeball is not proposed to explain a small lid motion). It is
  solved by NNLS (Lawson & Hanson 1974) on the ridge-augmented system.
  The gains ``m_k`` form the columns of a :class:`~keyshape.targets._mapping.Mapping` that the user can
  read and edit (``MAP.json``).

:func:`auto_targets` picks the route and the correspondence (a file, the built-in one of the
default character, or found by rendering the character and tracking the render).

References
----------
.. [1] C. L. Lawson and R. J. Hanson, *Solving Least Squares Problems*, Prentice-Hall 1974.
.. [2] J. Noh and U. Neumann, "Expression cloning", SIGGRAPH 2001.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from ..containers import KeyShapes, Rig
from ..exceptions import InputError, RigError
from ._character import stylised_head
from ._correspond import Correspondence, read_correspondence
from ._correspond_auto import NoFaceFound, find_correspondence
from ._head_parts import JAW_LANDMARKS, UPPER_LANDMARKS, jaw_deltas
from ._mapping import SMALLEST_GAIN, Mapping, bounded_row
from ._transfer import landmark_motion, spread, transfer_expressions

__all__ = ["AutoTargets", "KeyScores", "auto_targets", "default_character", "gaze_channels", "propose_mapping",
           "propose_targets", "proposer", "resolve_correspondence"]

Route = Literal["auto", "transfer", "mapping"]


def resolve_correspondence(correspondence, rig: Rig, n_landmarks: int, *, front: str = "auto",
                           colours: np.ndarray | None = None) -> Correspondence:
    """A :class:`Correspondence` for ``rig`` from an object, a JSON path, or None (found automatically).

    None renders the rig's neutral from the front and tracks it with MediaPipe
    (:func:`keyshape.targets.find_correspondence`, looking for its front unless ``front`` names
    it), which serves MediaPipe key shapes only.
    """
    if isinstance(correspondence, Correspondence):
        return correspondence.check(rig.n_vertices, n_landmarks)
    if correspondence is not None:
        return read_correspondence(correspondence, rig.vertices, rig.faces,
                                   n_landmarks=n_landmarks).check(rig.n_vertices, n_landmarks)
    if n_landmarks not in (468, 478):
        raise InputError(f"the key shapes have {n_landmarks} landmarks: only MediaPipe landmarks (478) are "
                         "found automatically; give a correspondence file (landmark -> vertex)")
    found = find_correspondence(rig.vertices, rig.faces, front=front, colours=colours)
    keep = found.landmarks < n_landmarks
    return Correspondence(found.landmarks[keep], found.vertices[keep], found.weights[keep], n_landmarks,
                          found.residual[keep], rest_scores=found.rest_scores)


def _as_rig(character) -> Rig:
    if isinstance(character, Rig):
        return character
    if isinstance(character, tuple) and len(character) == 2:
        vertices, faces = character
        vertices = np.asarray(vertices, dtype=float)
        return Rig(vertices, faces, np.zeros((0, *vertices.shape)), ())
    return _load(Path(character), 1.0)


def propose_targets(keys: KeyShapes, character, *, correspondence=None, falloff: float = 1.0,
                    rescale: bool = True, rigid: Sequence[np.ndarray] = (), front: str = "auto") -> Rig:
    """The character with one proposed target per key shape, by expression transfer.

    Parameters
    ----------
    keys : KeyShapes
    character : Rig, (vertices, faces) or a rig path
        Its neutral is used; its own targets, if any, are dropped.
    correspondence : Correspondence, path of a JSON file, or None, keyword-only
        None: found automatically (MediaPipe on a front render; MediaPipe key shapes only).
    falloff, rescale, rigid
        See :func:`keyshape.targets._transfer.transfer_expressions`.

    Returns
    -------
    Rig
        ``vertices`` and ``faces`` of the character, ``deltas (n_keys, n_vertices, 3)``,
        ``names = keys.names``.
    """
    rig = _as_rig(character)
    corr = resolve_correspondence(correspondence, rig, keys.n_landmarks, front=front)
    deltas = transfer_expressions(keys, rig.vertices, rig.faces, corr, falloff=falloff, rescale=rescale,
                                  rigid=rigid)
    return Rig(rig.vertices, rig.faces, deltas, keys.names)


def default_character(keys: KeyShapes) -> Rig:
    """The stylised head with one proposed target per key shape (MediaPipe key shapes).

    Returns
    -------
    Rig
        ``names = keys.names``; drive it with :meth:`Mapping.by_name <keyshape.targets.Mapping.by_name>`.
    """
    head = stylised_head()
    vertices, faces = head.rig.vertices, head.rig.faces
    corr = head.correspondence(keys.n_landmarks)
    field = spread(vertices, faces, corr, landmark_motion(keys, corr, vertices, faces))
    field = _at_amplitude(keys, field, head.landmark_vertices, vertices)
    return Rig(vertices, faces, _with_interior(head, field), keys.names)


def _at_amplitude(keys: KeyShapes, field: np.ndarray, landmark_vertices: np.ndarray, vertices: np.ndarray, *,
                  max_gain: float = 1.6) -> np.ndarray:
    """Each key's field scaled, where it falls short, to move the key's landmarks as far as the actor's.

    Amplitude is measured relative to face size (the RMS radius of the face's landmarks, in the
    image plane, on each side): the per-feature rescaling of the transfer sizes the caricature's
    small mouth's motion down with it (about 0.8-0.9 of the actor's on the demo's keys). The gain
    per key is the least-squares ratio ``g = ⟨a, a⟩ / ⟨c, a⟩`` of the actor's landmark speeds
    ``a`` to the character's ``c`` over the key's region, kept in ``[1, max_gain]`` (the big
    eyes' larger motion is left as it is).
    """
    n = min(len(landmark_vertices), keys.n_landmarks)
    actor = keys.neutral[:n, :2]
    character = vertices[landmark_vertices[:n], :2]
    radius_a = np.sqrt(((actor - actor.mean(axis=0)) ** 2).sum(axis=1).mean())
    radius_c = np.sqrt(((character - character.mean(axis=0)) ** 2).sum(axis=1).mean())
    gains = np.ones(keys.n_keys)
    for k, region in enumerate(keys.key_regions):
        ids = np.asarray(keys.regions[region])
        ids = ids[ids < n]
        a = np.linalg.norm(keys.deltas[k, ids, :2], axis=1) / radius_a
        c = np.linalg.norm(field[k, landmark_vertices[ids], :2], axis=1) / radius_c
        gains[k] = (a @ a) / max(float(c @ a), 1e-18)
    return field * np.clip(gains, 1.0, max_gain)[:, None, None]


def _with_interior(head, field: np.ndarray) -> np.ndarray:
    """The head's deltas with its mouth interior following the lips (the skin's and the eyes' as given).

    The lower teeth, the tongue and the cavity's floor take the rigid motion of the jaw's
    landmarks; the upper teeth and the cavity's roof that of the upper lip's. Keys often move the
    whole mouth (the actor's residual head motion is in them): upper teeth held still would then
    stand in front of lips moved back.
    """
    def motion(landmarks, part, weights):
        ids = head.landmark_vertices[np.asarray(landmarks)]
        return jaw_deltas(head.rig.vertices[part], field[:, ids], head.rig.vertices[ids], weights)

    out = field.copy()
    for name in ("lower_teeth", "tongue"):
        out[:, head.parts[name]] = motion(JAW_LANDMARKS, head.parts[name], np.ones(len(head.parts[name])))
    teeth = head.parts["upper_teeth"]
    out[:, teeth] = motion(UPPER_LANDMARKS, teeth, np.ones(len(teeth)))
    cavity = head.parts["cavity"]
    y = head.rig.vertices[cavity, 1]
    floor = np.clip((y.max() - y) / np.ptp(y) * 1.6 - 0.3, 0.0, 1.0)  # the roof follows the upper lip
    out[:, cavity] = motion(JAW_LANDMARKS, cavity, floor) + motion(UPPER_LANDMARKS, cavity, 1 - floor)
    for name in ("left_eye", "right_eye"):
        out[:, head.parts[name]] = 0.0
    return out


GAZE_TARGETS = ("eyeLook*",)


@dataclass(frozen=True, eq=False)
class KeyScores:
    """The tracker's ARKit-style scores at the key set's frames (MediaPipe's 52 blendshape scores).

    Attributes
    ----------
    neutral : (n_scores,) float
        At the neutral frame.
    keys : (n_keys, n_scores) float
        At each key's frame, in key order.
    names : tuple of n_scores str
        ARKit names (``eyeBlinkLeft``, ``jawOpen``, ...; ``_neutral`` is ignored).
    take : (n_frames, n_scores) float or None
        The scores of every frame of the take (NaN where no face), with
    weights : (n_frames, n_keys) float or None
        the take's solved key weights: the mapping is then fitted on the whole take
        (:func:`_take_mapping`), not read off the key frames alone.
    """

    neutral: np.ndarray
    keys: np.ndarray
    names: tuple
    take: np.ndarray | None = None
    weights: np.ndarray | None = None


def propose_mapping(keys: KeyShapes, rig, *, correspondence=None, ridge: float = 3e-3, min_gain: float = 0.05,
                    max_gain: float | None = 2.0, normalize: bool = False, rescale: bool = True,
                    exclude: Sequence[str] = GAZE_TARGETS, scores: KeyScores | None = None,
                    front: str = "auto") -> Mapping:
    """A key → target mapping onto a rig's own blendshapes.

    Two ways, chosen by the evidence at hand:

    * with the tracker's ARKit scores at the key frames (``scores``) and a rig whose targets carry
      ARKit names (``jawOpen``, ``eyeBlink_L`` ...), each key's gains are the scores at its frame
      minus those at the neutral frame, on the targets of the key's own region, and the neutral's
      scores become the mapping's offset (:func:`_score_mapping`). On a rendered closed loop
      (``benchmarks/bench_rendered_loop.py``) this gives 35 % vertex error where the geometric
      fit gives 116 %: the actor's neutral is rarely at rest, and landmark motion alone does not
      tell ARKit's overlapping shapes apart (:func:`auto_targets` also maps the gaze targets this
      way when the rig has no eye nodes);
    * otherwise, by non-negative least squares on the landmark motion (below).

    Parameters
    ----------
    keys : KeyShapes
    rig : Rig or rig path
        With at least one target.
    correspondence : Correspondence, path of a JSON file, or None, keyword-only
        None: found automatically (see :func:`propose_targets`).
    ridge : float, keyword-only
        Strength of the per-target ridge penalty ``λ_t m_t²`` (see the module docstring): a
        target is shrunk by about ``1 / (1 + ridge)`` when the landmarks see its motion well, and
        much more when most of its motion is where no landmark is.
    min_gain : float, keyword-only
        Gains below ``min_gain`` times the key's largest gain are dropped, and the rest refitted,
        so the mapping stays short enough to read.
    max_gain : float or None, keyword-only
        Upper bound of every gain (bounded least squares, BVLS): targets are made for weights
        up to 1, and a much larger gain means a target is being bent to a use it was not made for.
    normalize : bool, keyword-only
        Scale each target's gains so the key that drives it most drives it fully (gain 1): keys
        are the performance's extreme frames, so the character reaches its full expression. For
        stylised rigs whose targets exaggerate (the geometric fit gives small gains there); off,
        the gains reproduce the actor's amplitude.
    rescale : bool, keyword-only
        See :func:`keyshape.targets._transfer.landmark_motion`.
    exclude : sequence of str, keyword-only
        Target-name patterns (``fnmatch``, case-insensitive) never proposed. Default: ARKit's gaze
        targets, since eye gaze comes from the irises (:mod:`keyshape.capture.gaze`), not from key shapes.

    Returns
    -------
    Mapping
        ``matrix (n_targets, n_keys) ≥ 0``, ``sources = keys.names``, ``targets = rig.names``.
        A key no target can reproduce (e.g. a mouth key on a rig whose targets move only the
        brows) gets an all-zero column.

    Raises
    ------
    RigError
        A rig without targets (use :func:`propose_targets`).

    References
    ----------
    .. [1] Lawson & Hanson (1974), NNLS; P. B. Stark and R. L. Parker, "Bounded-variable least-squares:
       an algorithm and applications", Computational Statistics 10, 1995 (BVLS).
    """
    rig = _as_rig(rig)
    if rig.n_targets == 0:
        raise RigError("the rig has no blendshapes to combine: propose target shapes instead (transfer route)")
    corr = resolve_correspondence(correspondence, rig, keys.n_landmarks, front=front)
    if scores is not None and _score_channels(scores.names, rig.names).any():
        return _score_mapping(keys, rig, corr, scores, ~_excluded(rig.names, exclude))
    basis, wanted, n_points = _mapping_system(keys, rig, corr, rescale)
    penalty = _penalties(n_points, rig.deltas, ridge)
    allowed = ~_excluded(rig.names, exclude)
    gains = np.zeros((rig.n_targets, keys.n_keys))
    for k, b in enumerate(wanted):
        gains[allowed, k] = _fit_gains(basis[:, allowed], b, penalty[allowed], min_gain, max_gain)
    gains[gains < 1e-9] = 0.0  # rounding noise of the solvers
    if normalize:
        strongest = gains.max(axis=1, keepdims=True)
        gains /= np.where(strongest > 0, strongest, 1.0)
    return Mapping(gains, keys.names, rig.names)


def gaze_channels(score_names, rig_names, *, rest: dict | None = None,
                  patterns: Sequence[str] = GAZE_TARGETS) -> tuple:
    """A rig's gaze targets on their own channel: ``(target, score, rest)`` entries of a :class:`Mapping`.

    Gaze is not an expression: the eyes turn whatever the face does, and the key shapes (made of
    the face's landmarks, not the irises) cannot carry it, so a key → target mapping can only give
    gaze targets a constant. Each gaze target (``eyeLookIn_L`` ...) instead follows its ARKit score
    (``eyeLookInLeft``) frame by frame, less the tracker's reading of the character itself at rest
    (``rest``, :attr:`Correspondence.rest_scores`); :func:`~keyshape.targets._mapping.drive_gaze`
    applies them.

    Parameters
    ----------
    score_names : sequence of str (ARKit names)
    rig_names : sequence of str
    rest : dict str -> float or None, keyword-only
    patterns : target-name patterns (``fnmatch``, case-insensitive) that are gaze, keyword-only

    Returns
    -------
    tuple of (target, score, rest)
        One per gaze target that a score names (an unsided score would drive both halves).
    """
    table = _score_channels(score_names, rig_names) * _excluded(rig_names, patterns)[:, None]
    rest = rest or {}
    entries = []
    for t in np.flatnonzero(table.any(axis=1)):
        score = str(score_names[int(np.flatnonzero(table[t])[0])])
        entries.append((str(rig_names[t]), score, float(np.clip(rest.get(score, 0.0), 0, 1))))
    return tuple(entries)


def _score_channels(score_names, rig_names) -> np.ndarray:
    """``(n_targets, n_scores)`` 0/1: which score drives which rig target, by ARKit name.

    ``eyeBlinkLeft`` drives ``eyeBlinkLeft``, ``eyeBlink_L`` or ``EyeBlinkLeft``; an unsided score
    (``browInnerUp``) drives both halves of a rig that splits it (``browInnerUp_L``, ``_R``).
    """
    from ..io.livelink import livelink_columns

    sources, _ = livelink_columns(rig_names)
    columns = {column.lower(): indices for column, indices in sources.items()}
    table = np.zeros((len(rig_names), len(score_names)))
    for j, name in enumerate(score_names):
        for t in columns.get(str(name).lower(), ()):
            table[t, j] = 1.0
    return table


def _score_mapping(keys: KeyShapes, rig: Rig, corr: Correspondence, scores: KeyScores,
                   allowed: np.ndarray) -> Mapping:
    """Gains ``max(s(key) − s(neutral), 0)`` on the key's region's targets (below
    :data:`SMALLEST_GAIN`: none), offset ``s(neutral) − s(rest)``.

    A target belongs to the region whose corresponded landmarks it moves most; targets no score
    names (or ``allowed`` excludes) stay undriven. ``s(rest)`` is how the tracker reads the
    character itself at rest (``corr.rest_scores``, from the render the correspondence was found
    on; zero when unknown): a character whose brows MediaPipe reads as raised at rest needs less
    brow raise to look like the actor's neutral. On the rendered ICT loop this takes the error
    from 34.8 % to 24 % (BENCHMARKS.md).
    """
    table = _score_channels(scores.names, rig.names) * allowed[:, None]
    neutral = np.clip(table @ np.nan_to_num(np.asarray(scores.neutral, dtype=float)), 0, 1)
    rest = getattr(corr, "rest_scores", None)
    region = _target_regions(keys, rig, corr) if corr is not None else _regions_by_name(keys, rig.names)
    at_rest = np.zeros(len(rig.names))
    if rest:
        at_rest = np.clip(table @ np.array([float(rest.get(n, 0.0)) for n in scores.names]), 0, 1)
        neutral = np.clip(neutral - at_rest, 0, 1)
    own = region[:, None] == np.asarray(keys.key_regions)[None, :]  # (n_targets, n_keys)
    if scores.take is not None and scores.weights is not None:
        fitted = _take_mapping(keys, rig, table, own, scores, at_rest)
        if fitted is not None:
            return fitted
    at_keys = np.clip(np.nan_to_num(np.asarray(scores.keys, dtype=float)) @ table.T, 0, 1)  # (n_keys, n_targets)
    base = np.clip(table @ np.nan_to_num(np.asarray(scores.neutral, dtype=float)), 0, 1)
    gains = np.where(own, np.maximum(at_keys.T - base[:, None], 0.0), 0.0)  # gains >= 0, as a map's are
    gains[gains < SMALLEST_GAIN] = 0.0
    return Mapping(gains, keys.names, rig.names, offset=neutral)


def _take_mapping(keys: KeyShapes, rig: Rig, table: np.ndarray, own: np.ndarray, scores: KeyScores,
                  at_rest: np.ndarray, *, ridge: float = 1e-3) -> Mapping | None:
    r"""The mapping fitted on the whole take: each target's reading ``y_t(f)`` (the tracker's score
    of frame ``f`` less the character's own at rest) regressed on the key weights of its region,

    .. math::

        \min_{0 \le c_t \le 1,\; g_t \ge 0} \sum_f \big(y_t(f) - c_t - \textstyle\sum_{k \in R(t)} g_{tk} w_k(f)\big)^2
        + \lambda n_f \lVert g_t \rVert^2

    by bounded least squares (BVLS): gains ``>= 0`` as every mapping's (``keyshape retarget --help``),
    a key adds to a target or leaves it. Gains below :data:`SMALLEST_GAIN` are dropped and the rest
    refitted. Every frame is evidence, not only the key frames: what a key does on average over the
    take, its frame's own noise averaged out. None when the take has too few frames with a face and
    weights.
    """
    S = np.asarray(scores.take, dtype=float)
    W = np.asarray(scores.weights, dtype=float)
    if S.ndim != 2 or W.shape != (len(S), keys.n_keys):
        return None
    ok = np.isfinite(S).all(axis=1) & np.isfinite(W).all(axis=1)
    if ok.sum() < 2 * (keys.n_keys + 1):
        return None
    Y = np.clip(S[ok] @ table.T, 0, 1) - at_rest  # (n_frames, n_targets)
    X = np.column_stack([np.ones(int(ok.sum())), W[ok]])
    gains, offset = np.zeros((rig.n_targets, keys.n_keys)), np.zeros(rig.n_targets)
    for t in np.flatnonzero(table.any(axis=1)):
        columns = np.flatnonzero(own[t])
        for _ in range(2):  # fit, then refit without the gains too small to matter
            offset[t], gains[t, columns] = bounded_row(X[:, [0, *(columns + 1)]], Y[:, t], ridge)
            small = gains[t, columns] < SMALLEST_GAIN
            gains[t, columns[small]] = 0.0
            if not small.any():
                break
            columns = columns[~small]
    return Mapping(gains, keys.names, rig.names, offset=offset)


def _regions_by_name(keys: KeyShapes, names) -> np.ndarray:
    """``(n_targets,)`` str: each ARKit target's key region by its name, without a correspondence:
    ``eye*``, ``brow*`` and ``cheekSquint*`` go to the region holding the eyelids (MediaPipe's 159),
    the rest to the one holding the lips (13); the first region when none holds them."""
    regions = list(keys.regions)

    def holding(landmark: int) -> str:
        return next((r for r in regions if landmark in set(np.asarray(keys.regions[r]).tolist())), regions[0])

    upper, lower = holding(159), holding(13)
    return np.array([upper if str(n).lower().startswith(("eye", "brow", "cheeksquint")) else lower for n in names])


def _target_regions(keys: KeyShapes, rig: Rig, corr: Correspondence) -> np.ndarray:
    """``(n_targets,)`` str: the key region whose corresponded landmarks each target moves most."""
    moved = (corr.points(rig.deltas) ** 2).sum(axis=2)  # (n_targets, n_corr)
    names = list(keys.regions)
    energy = np.stack([moved[:, np.isin(corr.landmarks, np.asarray(keys.regions[r]))].sum(axis=1) for r in names],
                      axis=1)
    return np.array(names)[energy.argmax(axis=1)]


def _mapping_system(keys: KeyShapes, rig: Rig, corr: Correspondence, rescale: bool):
    """``A (n_rows, n_targets)``, ``b (n_keys, n_rows)`` and the number of points used.

    Rows are the constrained points' coordinates (x, y for 2D key shapes), each weighted by the
    square root of the point's confidence (weighted least squares).
    """
    motion = landmark_motion(keys, corr, rig.vertices, rig.faces, rescale=rescale)
    used = np.flatnonzero(motion.constrained)
    dims = slice(0, motion.n_dims)  # 2D keys say nothing about depth
    trust = np.sqrt(motion.confidence[used])[None, :, None]
    # t: target, c: point, d: dimension -> A (c·d, t)
    basis = (corr.points(rig.deltas)[:, used, dims] * trust).reshape(rig.n_targets, -1).T
    wanted = (motion.deltas[:, used, dims] * trust).reshape(keys.n_keys, -1)
    return basis, wanted, len(used)


def _excluded(names: Sequence[str], patterns: Sequence[str]) -> np.ndarray:
    from fnmatch import fnmatch

    return np.array([any(fnmatch(n.lower(), p.lower()) for p in patterns) for n in names], dtype=bool)


def _penalties(n_points: int, deltas: np.ndarray, ridge: float) -> np.ndarray:
    """Ridge weights ``λ_t (n_targets,)`` that make motion the landmarks cannot see expensive.

    ``λ_t = ridge · n_points · mean_{v moving} |D_t(v)|²``, the mean over the vertices target ``t``
    moves noticeably (more than a tenth of its largest motion). A target the landmarks see well
    has ``‖A_t‖² ≈ n_points · mean |D_t|²`` and is shrunk by about ``1 / (1 + ridge)``; one whose
    motion is mostly elsewhere (an eyeball turning for ``eyeLookDown``, which barely moves the
    lids) is shrunk much more, so unseen motion is not proposed on thin evidence.
    """
    deltas = np.asarray(deltas, dtype=float)
    length2 = (deltas**2).sum(axis=2)  # (n_targets, n_vertices)
    moving = length2 > 0.01 * length2.max(axis=1, keepdims=True)
    mean_moving = (length2 * moving).sum(axis=1) / np.maximum(moving.sum(axis=1), 1)
    return ridge * n_points * mean_moving


def _fit_gains(basis: np.ndarray, wanted: np.ndarray, penalty: np.ndarray, min_gain: float,
               max_gain: float | None) -> np.ndarray:
    """Bounded NNLS with a ridge term, then drop small gains and refit on the rest: ``(n_targets,)``."""
    gains = _ridge_nnls(basis, wanted, penalty, max_gain)
    if gains.max(initial=0) > 0 and min_gain > 0:
        keep = gains >= min_gain * gains.max()
        gains = np.zeros_like(gains)
        gains[keep] = _ridge_nnls(basis[:, keep], wanted, penalty[keep], max_gain)
    return gains


def _ridge_nnls(basis: np.ndarray, wanted: np.ndarray, penalty: np.ndarray, max_gain: float | None) -> np.ndarray:
    """``argmin_{0 ≤ m ≤ max_gain} ‖A m − b‖² + Σ_t λ_t m_t²``: NNLS (or BVLS) on ``[A; diag(√λ)] m ≈ [b; 0]``."""
    from scipy.optimize import lsq_linear, nnls

    n = basis.shape[1]
    if n == 0 or not np.abs(wanted).max(initial=0) > 0:
        return np.zeros(n)
    stacked = np.vstack([basis, np.diag(np.sqrt(penalty))])
    target = np.concatenate([wanted, np.zeros(n)])
    gains = nnls(stacked, target, maxiter=50 * n)[0]
    if max_gain is None or gains.max() <= max_gain:
        return gains
    return lsq_linear(stacked, target, bounds=(0.0, float(max_gain)), method="bvls").x


def proposer(*, correspondence=None, falloff: float = 1.0, rigid: Sequence[np.ndarray] = ()):
    """A ``propose(keys, neutral) -> (n_keys, n_vertices, 3)`` callable for the sculpt kit.

    The kit (:func:`keyshape.app._sculpt.sculpt_targets`) then starts every target as the proposal
    instead of the neutral.
    """
    def propose(keys: KeyShapes, neutral: Rig) -> np.ndarray:
        return propose_targets(keys, neutral, correspondence=correspondence, falloff=falloff,
                               rigid=rigid).deltas

    return propose


# --------------------------------------------------------------------------- the one call for run / demo


@dataclass(frozen=True, eq=False)
class AutoTargets:
    """A character ready to drive with key weights.

    Attributes
    ----------
    rig : Rig
        The character; for the transfer route its targets are the proposals, named after the keys.
    mapping : Mapping
        Keys → ``rig.names``: by name for the transfer route, the proposed gains for the mapping route.
    route : "transfer" or "mapping"
    correspondence : Correspondence or None
        None for a VRM avatar (its mapping comes from the tracker's scores alone).
    """

    rig: Rig
    mapping: Mapping
    route: str
    correspondence: Correspondence


def auto_targets(keys: KeyShapes, rig=None, *, correspondence=None, route: Route = "auto",
                 unit: float = 1.0, falloff: float = 1.0, normalize: bool = False,
                 scores: KeyScores | None = None, front: str = "auto",
                 colours: np.ndarray | None = None, meshes=None) -> AutoTargets:
    """Propose the character's targets for ``keys`` in one call.

    Parameters
    ----------
    keys : KeyShapes
    rig : Rig, rig path, or None
        None: the built-in stylised head (:func:`keyshape.targets._character.stylised_head`), which
        needs MediaPipe key shapes.
    correspondence : Correspondence, JSON path, or None, keyword-only
        None: the built-in one for the default character, else found automatically.
    route : "auto", "transfer" or "mapping", keyword-only
        "auto": mapping when the rig has targets, transfer otherwise.
    unit : float, keyword-only
        Metres per OBJ unit of a rig path (see :func:`keyshape.io.rig.load_rig`).
    falloff : float, keyword-only
        Transfer route: see :func:`keyshape.targets._transfer.spread`.
    normalize : bool, keyword-only
        Mapping route: see :func:`propose_mapping`.
    front : str, keyword-only
        The axis the character's face looks along, for the automatic correspondence (see
        :func:`keyshape.targets.find_correspondence`); "auto" looks for it.
    colours : (n_vertices, 3) float, optional, keyword-only
        The character's base colours for that render; default: read from a glTF rig path's
        materials (:func:`keyshape.io.gltf.read_colours`), else clay.
    meshes : sequence of int or str, optional, keyword-only
        Of a glTF rig path: the meshes to read (see :func:`keyshape.io.gltf.read_meshes`; by
        default its morph-target meshes, else its head's mesh, else all).
    scores : KeyScores or None, keyword-only
        Mapping route: the tracker's ARKit scores at the key frames (see :func:`propose_mapping`).
        Gaze targets (``eyeLook*``) are never mapped from keys: the mapping's ``gaze`` entries
        (:func:`gaze_channels`) drive them frame by frame from their scores, unless the rig is a
        glTF file whose eyes turn by their own nodes (then the gaze from the irises turns those).

    Returns
    -------
    AutoTargets

    Examples
    --------
    The lead's ``run --auto-targets`` / ``demo`` wiring::

        auto = auto_targets(keys, args.rig)          # args.rig: a path or None
        anim = retarget(solved.weights, auto.mapping)
        write_glb(out / "animation.glb", auto.rig, anim, poses=solved.poses)
    """
    if route not in ("auto", "transfer", "mapping"):
        raise InputError(f"route must be 'auto', 'transfer' or 'mapping'; got {route!r}")
    if isinstance(rig, (str, Path)) and Path(rig).suffix.lower() == ".vrm" and correspondence is None \
            and route != "transfer":
        return _vrm_targets(keys, Path(rig), scores)
    character, corr, rigid = _character(keys, rig, correspondence, unit, front, colours, meshes)
    if route == "mapping" or (route == "auto" and character.n_targets > 0):
        # gaze targets are not mapped from keys: they follow their scores (gaze_channels), or the
        # irises turn the eyes' own nodes of a glTF rig that has them
        mapping = propose_mapping(keys, character, correspondence=corr, normalize=normalize, scores=scores)
        if scores is not None and not _eyes_on_nodes(rig):
            mapping = replace(mapping, gaze=gaze_channels(scores.names, character.names, rest=corr.rest_scores))
        return AutoTargets(character, mapping, "mapping", corr)
    if rig is None and correspondence is None and falloff == 1.0:
        proposed = default_character(keys)  # with its mouth interior following the jaw
    else:
        proposed = propose_targets(keys, character, correspondence=corr, rigid=rigid, falloff=falloff)
    return AutoTargets(proposed, Mapping.by_name(keys.names, proposed.names), "transfer", corr)


def _vrm_targets(keys: KeyShapes, path: Path, scores: KeyScores | None) -> AutoTargets:
    """A VRM avatar's mapping from the scores alone (no correspondence: ``correspondence`` None).

    A perfect-sync avatar (ARKit-named targets) takes the ARKit score route, each target's region
    by its name (:func:`_regions_by_name`), its gaze targets on their channels; a standard one its
    vowels, blinks and looks (:func:`keyshape.targets._vrm.vrm_mapping`).
    """
    from ..io.rig import load_rig
    from ._vrm import vrm_mapping

    avatar = load_rig(path)
    if scores is None:
        raise InputError(f"{path}: automatic targets onto a VRM avatar need the tracker's ARKit scores "
                         "(a MediaPipe track); give a mapping (--map) instead")
    if _score_channels(scores.names, avatar.names).any():
        allowed = ~_excluded(avatar.names, GAZE_TARGETS)
        mapping = _score_mapping(keys, avatar, None, scores, allowed)
        mapping = replace(mapping, gaze=gaze_channels(scores.names, avatar.names))
    else:
        mapping = vrm_mapping(keys, avatar.names, scores)
    return AutoTargets(avatar, mapping, "mapping", None)


def _eyes_on_nodes(rig) -> bool:
    """Whether the rig is a glTF file whose eyes the writer turns by their nodes (with the gaze)."""
    if isinstance(rig, (str, Path)) and Path(rig).suffix.lower() in (".glb", ".gltf"):
        from ..io.gltf import eye_nodes

        return eye_nodes(rig) is not None
    return False


def _character(keys: KeyShapes, rig, correspondence, unit: float, front: str,
               colours=None, meshes=None) -> tuple[Rig, Correspondence, tuple]:
    """The character, its correspondence and its rigid parts."""
    if rig is None:
        head = stylised_head()
        corr = head.correspondence(keys.n_landmarks) if correspondence is None else correspondence
        return head.rig, resolve_correspondence(corr, head.rig, keys.n_landmarks), ()
    if not isinstance(rig, (str, Path)):
        return rig, resolve_correspondence(correspondence, rig, keys.n_landmarks, front=front, colours=colours), ()
    path = Path(rig)
    colours = _colours(path, meshes) if colours is None else colours
    rig = _load(path, unit, meshes)
    try:
        return rig, resolve_correspondence(correspondence, rig, keys.n_landmarks, front=front, colours=colours), ()
    except NoFaceFound as error:
        raise no_face_on(error, path, meshes) from None


def no_face_on(error: NoFaceFound, path, meshes=None) -> NoFaceFound:
    """``error`` said of the character file ``path``, naming, for a glTF file of several meshes
    read whole (``meshes`` None), the ``--mesh`` values to choose its face's mesh from."""
    path = Path(path)
    hint = ""
    if meshes is None and path.suffix.lower() in (".glb", ".gltf"):
        from ..io.gltf import mesh_names

        names = mesh_names(path)
        if len(names) > 1:
            hint = f"; or choose the face's mesh with --mesh NAME, one of: {', '.join(names)}"
    return NoFaceFound(f"{path.name}: {error}{hint}")


def _colours(path: Path, meshes=None) -> np.ndarray | None:
    """The base colours of a glTF character's vertices (as :func:`_load` reads it); None for other files."""
    if path.suffix.lower() not in (".glb", ".gltf"):
        return None
    from ..io.gltf import read_colours

    return read_colours(path, meshes=meshes)


def _load(path: Path, unit: float, meshes=None) -> Rig:
    """A rig from a path; a glTF file without morph targets is read as a plain neutral (its head's mesh)."""
    if path.suffix.lower() in (".glb", ".gltf"):
        from ..io.gltf import read_meshes

        return read_meshes(path, meshes=meshes)[0]
    if meshes is not None:
        raise InputError(f"{path}: meshes are chosen in glTF files only; this is not one")
    from ..io.rig import load_rig

    return load_rig(path, unit=unit)
