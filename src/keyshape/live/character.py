"""Which targets a live session drives: the key names, a mapping, or a rig (with proposed targets)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..containers import KeyShapes, Rig

__all__ = ["LiveTargets", "live_targets"]


@dataclass(frozen=True)
class LiveTargets:
    """``mapping`` turns key weights into ``names`` (None: the key names themselves); ``rig`` is the
    character the viewer and the recording show, ``builtin`` whether it is keyshape's own head
    (driven by the key names)."""

    names: tuple[str, ...]
    mapping: object
    rig: Rig | None
    builtin: bool


def live_targets(keys: KeyShapes, *, rig: Path | None = None, mapping: Path | None = None,
                 auto_targets: bool = False, correspondence: Path | None = None, front: str = "auto",
                 need_rig: bool = False) -> LiveTargets:
    """The targets for ``keys``, as ``keyshape run`` chooses them.

    * ``mapping`` alone: MAP.json's targets (no character of its own);
    * ``rig``: its targets by the key names, through ``mapping``, or proposed (``auto_targets``);
    * neither: the key names; with ``need_rig`` (viewer, recording) keyshape's stylised head.
    """
    from ..targets import Mapping

    if rig is None:
        if mapping is not None:  # the viewer and the recording show keyshape's head, by the key names
            loaded = Mapping.from_file(mapping)
            character = _builtin(keys) if need_rig else None
            return LiveTargets(tuple(loaded.targets), loaded, character, character is not None)
        character = _builtin(keys) if need_rig else None
        return LiveTargets(tuple(keys.names), None, character, character is not None)
    if auto_targets:
        from ..targets import auto_targets as propose

        auto = propose(keys, rig, correspondence=correspondence, front=front)
        return LiveTargets(tuple(auto.mapping.targets), auto.mapping, auto.rig, False)
    from ..io import load_rig

    character = load_rig(rig)
    loaded = (Mapping.from_file(mapping, targets=character.names) if mapping is not None
              else Mapping.by_name(keys.names, character.names))
    return LiveTargets(tuple(loaded.targets), loaded, character, False)


def _builtin(keys: KeyShapes) -> Rig:
    """The stylised head with a target per key and its gaze targets, as ``keyshape run`` writes it."""
    from ..targets import default_character, with_gaze_targets

    return with_gaze_targets(default_character(keys))
