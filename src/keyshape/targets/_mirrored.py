"""Targets of mirrored keys: the mirror image of the source key's target on a symmetric character.

A mirrored key (:func:`keyshape.keyshapes.add_mirrors`) needs no sculpting: its target is its
source's target reflected through the character's symmetry plane (:func:`keyshape.mesh.mirror_map`),
``d'_v = (I − 2nnᵀ) d_p(v)``. :func:`complete_mirrors` fills in every mirrored target the rig lacks
or holds at the neutral (all zeros: the sculpt kit writes them so), and leaves alone one the
artist has sculpted.
"""

from __future__ import annotations

from collections.abc import Mapping as MappingABC

import numpy as np

from ..containers import Rig
from ..defaults import MIRROR_SUFFIX
from ..mesh import mirror_field, mirror_map

__all__ = ["complete_mirrors", "mirror_sources"]


def mirror_sources(names, suffix: str = MIRROR_SUFFIX) -> dict[str, str]:
    """``{mirrored name: source name}`` for names ending in ``suffix`` whose source is among them too.

    The command line's ``retarget`` knows the keys only by their weight columns; a mirrored key is
    named ``f"{source}_mirror"`` (:data:`keyshape.defaults.MIRROR_SUFFIX`).

    Examples
    --------
    >>> mirror_sources(["lower_00", "lower_00_mirror", "upper_03_mirror"])
    {'lower_00_mirror': 'lower_00'}
    """
    names = list(names)
    return {n: n[: -len(suffix)] for n in names if n.endswith(suffix) and n[: -len(suffix)] in names}


def complete_mirrors(rig: Rig, mirror_of: MappingABC[str, str], *, atol: float = 1e-9) -> tuple[Rig, list[str]]:
    """``rig`` with the target of every mirrored key it lacks or holds at the neutral.

    Parameters
    ----------
    rig : Rig, a character with the source keys' targets
    mirror_of : mapping mirrored key name -> its source key's name (e.g. ``zip(keys.names,
        keys.mirror_of)`` without the empty ones)
    atol : a target whose every offset is below this is "at the neutral"

    Returns
    -------
    (Rig, list of the names made)
        Targets made are appended (a missing one) or replaced (a neutral one); nothing else
        changes. When nothing needs making the rig is returned as it is.

    Raises
    ------
    RigError
        When a target must be made but the character's mesh is not left-right symmetric.
    """
    todo = []
    for mirrored, source in mirror_of.items():
        if not source or source not in rig.names:
            continue
        if mirrored in rig.names and np.abs(rig.deltas[rig.names.index(mirrored)]).max(initial=0) > atol:
            continue  # sculpted by the artist
        if np.abs(rig.deltas[rig.names.index(source)]).max(initial=0) <= atol:
            continue  # the source is still neutral: nothing to mirror
        todo.append((mirrored, source))
    if not todo:
        return rig, []
    pairs, normal = mirror_map(rig.vertices)
    deltas, names = list(rig.deltas), list(rig.names)
    for mirrored, source in todo:
        made = mirror_field(rig.deltas[rig.names.index(source)], pairs, normal)
        if mirrored in names:
            deltas[names.index(mirrored)] = made
        else:
            deltas.append(made)
            names.append(mirrored)
    return Rig(rig.vertices, rig.faces, np.array(deltas), tuple(names)), [m for m, _ in todo]
