"""The peer's path as the floor: an ARKit rig driven by the tracker's own scores, less the character's rest reading.

MediaPipe's 52 ARKit scores are at hand for any rig whose targets carry ARKit names: each target
follows its score frame by frame, less what the tracker reads on the character itself at rest
(:attr:`~keyshape.targets.Correspondence.rest_scores`), ``w_t(f) = clip(s_t(f) − rest_t, 0, 1)``
(the mapping's score channels, :func:`~keyshape.targets._mapping.drive_gaze`). That is the
floor: what a user gets without keyshape. The key route (the scores read through the key
weights, :func:`~keyshape.targets._propose._take_mapping`, and render and compare,
:func:`~keyshape.targets.refine_mapping`) replaces the floor on a target only where the
take's own evidence says it helps (:func:`with_floor`). Opt-in (``run --auto-targets --floor``):
measured on the rendered loop (BENCHMARKS.md, issue 35) it is level on ICT-FaceKit and not yet
never-worse on a Ready Player Me avatar, the family held out.

Which step each target keeps is recorded in ``map.json``'s ``"refined"`` entry (``"steps"``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from ._mapping import Mapping
from ._propose import _excluded, gaze_channels

__all__ = ["KEY_TARGETS", "key_targets", "score_floor", "with_floor"]

#: The targets (ARKit score names) that follow the key route rather than the floor unless
#: render and compare judges them (chosen on ICT-FaceKit and its caricature, family 1 of
#: ``benchmarks/bench_rendered_loop.py``; BENCHMARKS.md, issue 35).
KEY_TARGETS: tuple[str, ...] = ()


def key_targets(rig_names) -> set[str]:
    """The rig's targets named by :data:`KEY_TARGETS` (any ARKit spelling)."""
    from ._propose import _score_channels

    table = _score_channels(KEY_TARGETS, tuple(rig_names))
    return {str(rig_names[t]) for t in np.flatnonzero(table.any(axis=1))}


def score_floor(targets, score_names, rest: dict | None = None, *, exclude: Sequence[str] = ()) -> tuple:
    """The floor's score channels: ``(target, score, rest)`` for every target of ``targets`` a score names.

    Parameters
    ----------
    targets : sequence of str
        The rig's target names (any ARKit spelling: ``jawOpen``, ``eyeBlink_L``, ``EyeBlinkLeft``).
    score_names : sequence of str
        The tracker's score names (MediaPipe's ARKit 52).
    rest : dict str -> float or None
        The tracker's reading of the character at rest, by score name.
    exclude : sequence of str, keyword-only
        Target-name patterns (``fnmatch``, case-insensitive) left to the route, e.g. the gaze
        targets of a rig whose eyes turn by their own nodes.

    Returns
    -------
    tuple of (target, score, rest)
        As :class:`~keyshape.targets.Mapping`'s ``gaze`` entries.
    """
    entries = gaze_channels(score_names, tuple(targets), rest=rest, patterns=("*",))
    left = _excluded([t for t, _, _ in entries], exclude) if exclude else np.zeros(len(entries), bool)
    return tuple(entry for entry, out in zip(entries, left) if not out)


def with_floor(route: Mapping, floor: tuple, keep) -> Mapping:
    """``route`` with every target of ``floor`` on its score channel but those in ``keep``.

    Parameters
    ----------
    route : Mapping
        The key route (rows, offsets, its own gaze channels).
    floor : tuple of (target, score, rest)
        :func:`score_floor`'s channels.
    keep : collection of str
        Targets that keep the route's row (and offset, or its own channel).

    Returns
    -------
    Mapping
        Rows and offsets zero on the floor's targets, which follow their scores.
    """
    keep = set(keep)
    own = {t: entry for entry in route.gaze for t in entry[:1]}
    channels = {t: (t, s, r) for t, s, r in floor if t not in keep}
    for t, entry in own.items():  # the route's own channels (gaze) stay as they are
        channels.setdefault(t, entry)
    rows = [route.targets.index(t) for t in channels]
    matrix, offset = np.array(route.matrix), np.array(route.offset)
    matrix[rows], offset[rows] = 0.0, 0.0
    return replace(route, matrix=matrix, offset=offset, gaze=tuple(channels[t] for t in route.targets if t in channels))
