"""Whether a character can be driven by key names at all, checked before the tracking starts.

A rig driven by name (no mapping, no ``auto_targets``) needs targets named after the key shapes:
``upper_00``, ``lower_03_mirror`` ... as ``keyshape sculpt`` writes them. A rig with its own shape
set (ARKit's ``jawOpen``, ``mouthSmileLeft``, ...) has none, and finding that out after minutes of
tracking, in a message listing every key and every target, helps nobody: this check says it in
one line, naming what drives such a rig.
"""

from __future__ import annotations

import re
from pathlib import Path

from ..containers import KeyShapes, Rig
from ..exceptions import RigError

__all__ = ["check_drivable", "key_name_pattern"]

_SHOWN = 3  # targets named in the message


def key_name_pattern(regions: list[str]) -> re.Pattern:
    """The names keys of these regions get: ``<region>_<nn>`` and their mirrors ``<region>_<nn>_mirror``.

    Examples
    --------
    >>> bool(key_name_pattern(["upper", "lower"]).fullmatch("lower_03_mirror"))
    True
    >>> bool(key_name_pattern(["upper", "lower"]).fullmatch("jawOpen"))
    False
    """
    alternatives = "|".join(re.escape(r) for r in regions)
    return re.compile(rf"(?:{alternatives})_\d{{2,}}(?:_mirror)?")


def check_drivable(rig: Rig, path: str | Path, *, regions: list[str], keys: KeyShapes | None = None) -> None:
    """Refuse a rig none of whose targets a key drives by name.

    Parameters
    ----------
    rig : Rig
        The character as read, ``names (n_targets,)``.
    path : str or Path
        Its file, for the message.
    regions : list of str
        The region names the keys will have (from the ``regions`` scheme), used when ``keys`` is None.
    keys : KeyShapes, optional
        The key set, when it is known already (``--keys``): its names are then the ones looked for.

    Raises
    ------
    RigError
        When no target is named after a key, in one line naming ``--auto-targets`` and ``--map``.

    Examples
    --------
    >>> import numpy as np
    >>> rig = Rig(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.ones((1, 3, 3)), ("jawOpen",))
    >>> check_drivable(rig, "face.glb", regions=["upper", "lower"])
    Traceback (most recent call last):
    ...
    keyshape.exceptions.RigError: face.glb: none of its 1 targets (jawOpen) is named after a key shape (upper_00, lower_00, ...): add --auto-targets to drive its own shapes, or give --map MAP.json
    """
    if keys is not None:
        named = set(keys.names) & set(rig.names)
        examples = list(keys.names[:2])
    else:
        pattern = key_name_pattern(regions)
        named = {n for n in rig.names if pattern.fullmatch(n)}
        examples = [f"{r}_00" for r in regions[:2]]
    if named:
        return
    shown = ", ".join(rig.names[:_SHOWN]) + (", ..." if rig.n_targets > _SHOWN else "")
    raise RigError(f"{Path(path).name}: none of its {rig.n_targets} targets ({shown}) is named after a key "
                   f"shape ({', '.join(examples)}, ...): add --auto-targets to drive its own shapes, or give "
                   "--map MAP.json")
