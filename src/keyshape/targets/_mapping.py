"""Retargeting: carry key-shape weights over to a character's targets.

The paper drives each sculpted target with the weight of the key shape it was sculpted
for ("a smile for a smile"). A :class:`Mapping` generalises that to a non-negative
matrix ``M (n_targets, n_keys)``: target weights are ``w_target = c + M · w_key`` per frame,
so one key may drive several targets, each with its own gain. The offset ``c (n_targets,)``
(zero unless given) is the rig's pose at the key set's neutral frame: an actor's "neutral" is
often not at rest (a slight smile), and a key with less of the smile then lowers the smile
target, so gains may be negative down to ``-c`` (``c + gain ≥ 0``).

A mapping file (``--map MAP.json``) is JSON: ``{key: {target: gain, ...}, ...}``, e.g.
``{"lower_03": {"jawOpen": 0.8, "mouthFunnel": 0.3}}``; the same object may be wrapped as
``{"format": "keyshape-map", "version": 1, "gains": {...}}`` (what :meth:`Mapping.save`
writes), or given as a matrix: ``{"keys": [...], "targets": [...], "matrix": [[...], ...]}``
with one row per target. The wrapped form may carry ``"offset": {target: value, ...}`` and
``"gaze": {target: {"score": name, "rest": value}, ...}``: targets driven frame by frame by the
tracker's score of that name less ``rest`` (gaze on its own channel, not through the keys; see
:func:`drive_gaze`).

Retargeting carries weights only: it assumes nothing about the rig's scale, orientation or
topology. The targets themselves say how far each vertex moves at weight 1; a key's gain scales
that. Weights are not clipped above (a gain above 1, or several keys on one target, may exceed 1);
with an offset they are clipped below at 0. A gain is at most 100 (``MAX_GAIN``), and every writer
refuses a weight outside ``0..5`` (``MAX_WEIGHT``, what keyshape reads back): an animation of
``inf`` or of a 300-digit number is never written.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..containers import Weights
from ..exceptions import InputError, RigError
from ..io.validate import MAX_GAIN

__all__ = ["Mapping", "retarget", "drive_gaze"]


def _names(source) -> tuple[str, ...]:
    """Names from a sequence of str or from anything with ``.names`` (KeyShapes, Weights, Rig)."""
    names = getattr(source, "names", source)
    if isinstance(names, str):
        raise InputError(f"expected a sequence of names; got the single string {names!r}")
    return tuple(str(n) for n in names)


@dataclass(frozen=True, eq=False)
class Mapping:
    """A key → target retargeting matrix.

    Attributes
    ----------
    matrix : (n_targets, n_keys) float, ≥ ``-offset`` and ≤ :data:`~keyshape.io.validate.MAX_GAIN` (100)
        ``matrix[t, k]`` is the gain with which key ``k`` drives target ``t``.
    sources : tuple of n_keys str
        Key names (the columns).
    targets : tuple of n_targets str
        Rig target names (the rows).
    offset : (n_targets,) float, ≥ 0
        Target weights when every key weight is 0 (the key set's neutral); zeros by default.
    gaze : tuple of (target, score, rest)
        Targets that follow a tracker score frame by frame instead of the keys (their rows and
        offsets are zero): ``w = clip(score − rest, 0, 1)`` (:func:`drive_gaze`); empty by default.

    Examples
    --------
    >>> m = Mapping.by_name(["smile", "blink"], ["blink", "smile"])
    >>> m.matrix
    array([[0., 1.],
           [1., 0.]])
    """

    matrix: np.ndarray
    sources: tuple[str, ...]
    targets: tuple[str, ...]
    offset: np.ndarray | None = None
    gaze: tuple = ()

    def __post_init__(self):
        sources, targets = _names(self.sources), _names(self.targets)
        matrix = np.asarray(self.matrix, dtype=float)
        if matrix.shape != (len(targets), len(sources)):
            raise InputError(
                f"matrix must have shape (n_targets, n_keys) = ({len(targets)}, {len(sources)}); "
                f"got {matrix.shape}"
            )
        offset = np.zeros(len(targets)) if self.offset is None else np.asarray(self.offset, dtype=float)
        if offset.shape != (len(targets),) or not np.isfinite(offset).all() or (offset < 0).any():
            raise InputError(f"offset must be {len(targets)} finite numbers >= 0; got {self.offset!r}")
        if not np.isfinite(matrix).all() or (matrix + offset[:, None] < 0).any() or (matrix > MAX_GAIN).any():
            raise InputError(f"mapping gains must be finite, >= 0 (>= -offset with an offset) and <= {MAX_GAIN:g}; "
                             f"got {np.nanmin(matrix, initial=0):g} ... {np.nanmax(matrix, initial=0):g}")
        for label, names in (("key", sources), ("target", targets)):
            duplicates = sorted({n for n in names if names.count(n) > 1})
            if duplicates:
                raise InputError(f"{label} names must be unique; repeated: {duplicates}")
        gaze = _gaze_entries(self.gaze, targets)
        driven = [targets.index(t) for t, _, _ in gaze]
        if driven and (matrix[driven].any() or offset[driven].any()):
            raise InputError(f"gaze targets {[t for t, _, _ in gaze]} follow their scores: no key gain or offset on them")
        object.__setattr__(self, "gaze", gaze)
        matrix, offset = matrix.copy(), offset.copy()
        matrix.flags.writeable = offset.flags.writeable = False
        object.__setattr__(self, "matrix", matrix)
        object.__setattr__(self, "offset", offset)
        object.__setattr__(self, "sources", sources)
        object.__setattr__(self, "targets", targets)

    n_keys = property(lambda self: self.matrix.shape[1])
    n_targets = property(lambda self: self.matrix.shape[0])

    @classmethod
    def by_name(cls, keys, targets, *, allow_extra: bool = False) -> Mapping:
        """Drive each target with the key of the same name, gain 1 (the paper's scheme).

        Parameters
        ----------
        keys : sequence of str, or KeyShapes / Weights
            Key names (anything with ``.names`` is accepted).
        targets : sequence of str, or Rig
            Rig target names, in rig order; the mapping's rows follow this order.
        allow_extra : bool, keyword-only
            Accept rig targets that no key drives (they stay at weight 0). By default
            they are an error, so a misspelt target does not go silently unused.

        Returns
        -------
        Mapping

        Raises
        ------
        RigError
            Listing keys without a same-named target and, unless ``allow_extra``,
            targets without a same-named key.
        """
        keys, targets = _names(keys), _names(targets)
        missing = [k for k in keys if k not in targets]
        extra = [] if allow_extra else [t for t in targets if t not in keys]
        if missing or extra:
            raise RigError(_by_name_message(missing, extra))
        matrix = np.array([[float(t == k) for k in keys] for t in targets]).reshape(len(targets), len(keys))
        return cls(matrix, keys, targets)

    @classmethod
    def from_dict(cls, gains: dict, *, targets=None, sources=None, offset: dict | None = None,
                  gaze: dict | None = None) -> Mapping:
        """A mapping from ``{key: {target: gain, ...}, ...}``.

        Parameters
        ----------
        gains : dict of str -> dict of str -> float
            Keys (columns, in dict order) and the targets each drives, with gains ≥ 0.
        targets : sequence of str or Rig, optional, keyword-only
            The rows, in this order (e.g. the rig's names, so that targets no key drives
            stay at 0). Default: targets in order of first mention.
        sources : sequence of str, optional, keyword-only
            The columns, in this order (keys driving nothing stay as zero columns).
            Default: the dict's keys.
        offset : dict of str -> float, optional, keyword-only
            Target weights at the neutral (see :class:`Mapping`); a gain may then be as low as
            ``-offset[target]``.
        gaze : dict of str -> {"score": str, "rest": float}, optional, keyword-only
            Targets driven by a tracker score frame by frame (see :class:`Mapping`).

        Returns
        -------
        Mapping

        Raises
        ------
        RigError
            If ``targets`` is given and the dict mentions targets not in it (listed).

        Examples
        --------
        >>> m = Mapping.from_dict({"upper_00": {"browUp_L": 1.0, "browUp_R": 0.5}})
        >>> m.targets, m.matrix[:, 0].tolist()
        (('browUp_L', 'browUp_R'), [1.0, 0.5])
        """
        sources = tuple(str(k) for k in gains) if sources is None else _names(sources)
        unknown_keys = [k for k in gains if str(k) not in sources]
        if unknown_keys:
            raise InputError(f"gains name keys {unknown_keys} not among the sources {list(sources)}")
        offset = {str(t): _gain(v, "offset", str(t), 0.0) for t, v in (offset or {}).items()}
        gaze = _parse_gaze(gaze)
        mentioned = list(dict.fromkeys([*(str(t) for row in gains.values() for t in row), *offset,
                                        *(t for t, _, _ in gaze)]))
        rows = mentioned if targets is None else _names(targets)
        unknown = [t for t in mentioned if t not in rows]
        if unknown:
            raise RigError(f"mapping names targets the rig does not have: {unknown}; rig targets: {list(rows)}")
        matrix = np.zeros((len(rows), len(sources)))
        for key, row in gains.items():
            k = sources.index(str(key))
            for target, gain in row.items():
                matrix[rows.index(str(target)), k] = _gain(gain, str(key), target, offset.get(str(target), 0.0))
        return cls(matrix, sources, rows, np.array([offset.get(t, 0.0) for t in rows]), gaze)

    @classmethod
    def from_file(cls, path, *, targets=None) -> Mapping:
        """Read a mapping JSON file (see the module docstring for its forms).

        Parameters
        ----------
        path : str or Path
        targets : sequence of str or Rig, optional, keyword-only
            The rig's target names: rows follow them, targets no key drives stay at 0,
            and targets the file names but the rig lacks are an error.

        Returns
        -------
        Mapping

        Raises
        ------
        InputError
            Unreadable file, not JSON, wrong structure or a bad gain (the message names
            the file and the entry).
        RigError
            The file names targets the rig does not have (listed).

        Examples
        --------
        >>> import tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "map.json")
        >>> _ = Mapping.from_dict({"lower_03": {"jawOpen": 0.8, "mouthFunnel": 0.3}}).save(path)
        >>> Mapping.from_file(path, targets=["mouthFunnel", "jawOpen", "eyeBlinkLeft"]).matrix.ravel().tolist()
        [0.3, 0.8, 0.0]
        """
        path = Path(path)
        data = _read_json(path)
        try:
            if isinstance(data, dict) and "matrix" in data:
                mapping = cls._from_matrix(data)
                return mapping if targets is None else cls.from_dict(mapping.to_dict(), targets=targets,
                                                                    sources=mapping.sources)
            wrapped = isinstance(data, dict) and data.get("format") == MAP_FORMAT
            gains = data.get("gains") if wrapped else data
            _check_gains(gains)
            offset = data.get("offset") if wrapped else None
            if offset is not None and not isinstance(offset, dict):
                raise InputError(f'"offset" must be an object {{target: weight, ...}}; got {offset!r}')
            return cls.from_dict(gains, targets=targets, offset=offset, gaze=data.get("gaze") if wrapped else None)
        except (InputError, RigError) as error:
            raise type(error)(f"{path}: {error}") from None

    @classmethod
    def _from_matrix(cls, data: dict) -> Mapping:
        keys, targets = data.get("keys"), data.get("targets")
        if not isinstance(keys, list) or not isinstance(targets, list):
            raise InputError('a matrix mapping needs "keys" and "targets" lists beside "matrix"')
        try:
            matrix = np.array(data["matrix"], dtype=float)
        except (TypeError, ValueError):
            raise InputError('"matrix" must be a list of rows of numbers (one row per target)') from None
        return cls(matrix, keys, targets)

    def save(self, path, *, refined: dict | None = None) -> Path:
        """Write the mapping as JSON (``{"format": "keyshape-map", "version": 1, "gains": ...}``), atomically.

        ``refined``: what :func:`keyshape.targets.refine_mapping` did, kept as the file's
        ``"refined"`` entry (read by the report, ignored when the mapping is read back).
        """
        from ..io.atomic import atomic_path

        document = {"format": MAP_FORMAT, "version": 1, "gains": self.to_dict()}
        if self.offset.any():
            document["offset"] = {t: float(c) for t, c in zip(self.targets, self.offset) if c != 0}
        if self.gaze:
            document["gaze"] = {t: {"score": score, "rest": rest} for t, score, rest in self.gaze}
        if refined is not None:
            document["refined"] = refined
        text = json.dumps(document, indent=1)
        with atomic_path(path) as tmp:
            tmp.write_text(text + "\n", encoding="utf-8")
        return Path(path)

    def to_dict(self) -> dict:
        """``{key: {target: gain}}`` for the non-zero gains (the inverse of :meth:`from_dict`)."""
        return {
            key: {t: float(g) for t, g in zip(self.targets, self.matrix[:, k]) if g != 0}
            for k, key in enumerate(self.sources)
        }

    def __repr__(self) -> str:
        return f"Mapping(n_targets={self.n_targets}, n_keys={self.n_keys})"


MAP_FORMAT = "keyshape-map"


def _read_json(path: Path):
    if not path.is_file():
        raise InputError(f"{path}: mapping file not found")
    try:
        return json.loads(path.read_text(encoding="utf-8-sig"))  # a BOM is no JSON error
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise InputError(f"{path}: not a readable JSON mapping ({error.__class__.__name__}: {error})") from None


def _check_gains(gains) -> None:
    if not isinstance(gains, dict) or not gains:
        raise InputError('expected a JSON object {key: {target: gain, ...}, ...} with at least one key; '
                         f"got {type(gains).__name__}")
    for key, row in gains.items():
        if not isinstance(row, dict):
            raise InputError(f"key {key!r} must map to an object {{target: gain, ...}}; got {row!r}")


def _by_name_message(missing: list[str], extra: list[str]) -> str:
    parts = []
    if missing:
        parts.append(f"keys with no same-named rig target: {missing}")
    if extra:
        parts.append(f"rig targets with no same-named key: {extra} (--allow-extra on the command line, "
                     "allow_extra=True in Python, leaves them at 0)")
    return "; ".join(parts) + "; give a mapping to connect differently named keys and targets"


def _gain(value, key: str, target: str, offset: float = 0.0) -> float:
    try:
        gain = float(value)
    except (TypeError, ValueError):
        raise InputError(f"gain for key {key!r} -> target {target!r} must be a number; got {value!r}") from None
    if not np.isfinite(gain) or gain < -offset or gain > MAX_GAIN:
        floor = f"-{offset:g} (its offset)" if offset else "0"
        raise InputError(f"gain for key {key!r} -> target {target!r} must be a finite number in {floor}..{MAX_GAIN:g}; "
                         f"got {value!r}")
    return gain


def _parse_gaze(gaze) -> tuple:
    """``{target: {"score": str, "rest": float}}`` (a file's ``"gaze"``) as (target, score, rest) entries."""
    if gaze is None:
        return ()
    if not isinstance(gaze, dict):
        raise InputError(f'"gaze" must be an object {{target: {{"score": name, "rest": value}}, ...}}; got {gaze!r}')
    entries = []
    for target, entry in gaze.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("score"), str):
            raise InputError(f'gaze target {target!r} needs {{"score": name, "rest": value}}; got {entry!r}')
        entries.append((str(target), entry["score"], entry.get("rest", 0.0)))
    return tuple(entries)


def _gaze_entries(gaze, targets: tuple) -> tuple:
    """Checked (target, score, rest) entries: known, unique targets; ``rest`` a number in [0, 1]."""
    out = []
    for entry in gaze:
        try:
            target, score, rest = entry
            rest = float(rest)
        except (TypeError, ValueError):
            raise InputError(f"gaze entries must be (target, score, rest); got {entry!r}") from None
        if str(target) not in targets:
            raise RigError(f"mapping names gaze targets the rig does not have: {target!r}; rig targets: {list(targets)}")
        if not (np.isfinite(rest) and 0 <= rest <= 1) or not str(score):
            raise InputError(f"gaze target {target!r}: rest must be in [0, 1] and score a name; got {entry!r}")
        out.append((str(target), str(score), rest))
    repeated = sorted({t for t, _, _ in out if [u for u, _, _ in out].count(t) > 1})
    if repeated:
        raise InputError(f"gaze targets must be unique; repeated: {repeated}")
    return tuple(out)


def drive_gaze(anim: Weights, mapping: Mapping, scores, score_names) -> Weights:
    """``anim`` (``retarget``'s output) with the mapping's gaze targets following their scores.

    Each entry ``(target, score, rest)`` of ``mapping.gaze`` sets ``anim``'s ``target`` column to
    ``clip(s(f) − rest, 0, 1)``, ``s`` the tracker's score of that name per frame; frames without a
    face (NaN) are filled linearly from their neighbours and held at the ends. Targets whose score
    the tracker does not give stay as they are.

    Parameters
    ----------
    anim : Weights, ``(n_frames, n_targets)`` named ``mapping.targets`` (at least)
    mapping : Mapping
    scores : (n_frames, n_scores) float, NaN where no face; None (a track without scores):
        ``anim`` as it is
    score_names : sequence of n_scores str

    Returns
    -------
    Weights

    Raises
    ------
    InputError
        ``scores`` has another number of frames than ``anim``.
    """
    if not mapping.gaze or scores is None:
        return anim
    scores = np.asarray(scores, dtype=float)
    if scores.ndim != 2 or len(scores) != anim.n_frames:
        raise InputError(f"the gaze scores must have one row per frame ({anim.n_frames}); got {scores.shape}")
    names = [str(n) for n in score_names]
    values = np.array(anim.values, dtype=float)
    frames = np.arange(len(scores))
    for target, score, rest in mapping.gaze:
        if score not in names or target not in anim.names:
            continue
        column = np.clip(scores[:, names.index(score)] - rest, 0, 1)
        found = np.isfinite(column)
        values[:, anim.names.index(target)] = np.interp(frames, frames[found], column[found]) if found.any() else 0.0
    return anim.with_values(values, anim.names)


def retarget(weights: Weights, mapping: Mapping) -> Weights:
    """Target weights from key weights: ``w_target(t) = c + M · w_key(t)`` (``c = mapping.offset``).

    Parameters
    ----------
    weights : Weights
        ``values (n_frames, n_channels)`` named by keys; every ``mapping.sources`` name
        must be among them (order and extra channels do not matter). NaN (no face) is
        treated as 0, so such frames show the neutral.
    mapping : Mapping

    Returns
    -------
    Weights
        ``values (n_frames, n_targets)`` named ``mapping.targets``, same fps; with an offset,
        clipped below at 0.

    Raises
    ------
    RigError
        Listing the mapping's keys that ``weights`` does not have.

    Examples
    --------
    >>> w = Weights(np.array([[0.5, np.nan]]), ("smile", "blink"), fps=30)
    >>> retarget(w, Mapping.from_dict({"smile": {"grin": 2.0}, "blink": {"grin": 1.0}})).values
    array([[1.]])
    """
    missing = [k for k in mapping.sources if k not in weights.names]
    if missing:
        raise RigError(f"the mapping needs keys the weights do not have: {missing}; weights have {list(weights.names)}")
    columns = [weights.names.index(k) for k in mapping.sources]
    keyed = np.nan_to_num(weights.values[:, columns], nan=0.0)
    # f: frame, k: key, t: target
    values = np.einsum("fk,tk->ft", keyed, mapping.matrix)
    if mapping.offset.any():
        values = np.maximum(values + mapping.offset, 0.0)
    return weights.with_values(values, mapping.targets)


SMALLEST_GAIN = 1e-3  # a gain below this moves a target by less than 0.001 at full weight: none at all


def bounded_row(X: np.ndarray, y: np.ndarray, ridge: float) -> tuple[float, np.ndarray]:
    """``(c, g)`` minimising ``|X [c, g] - y|² + ridge n |g|²`` with ``0 <= c <= 1``, ``g >= 0``: one
    mapping row (a target's offset and gains) fitted as every mapping's must be, by BVLS.

    ``X (n, 1 + m)``: a column of ones, then the ``m`` key weights; ``y (n,)``.
    """
    from scipy.optimize import lsq_linear

    n, m = X.shape[0], X.shape[1] - 1
    if m == 0:
        return float(np.clip(y.mean(), 0, 1)), np.zeros(0)
    A = np.vstack([X, np.sqrt(ridge * n) * np.eye(1 + m)[1:]])
    b = np.concatenate([y, np.zeros(m)])
    lower, upper = np.zeros(1 + m), np.r_[1.0, np.full(m, np.inf)]
    coef = lsq_linear(A, b, bounds=(lower, upper), method="bvls").x
    return float(coef[0]), np.maximum(coef[1:], 0.0)
