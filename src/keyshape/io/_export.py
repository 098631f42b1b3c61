"""Write an animation in the format a file name (or an explicit format) asks for.

============  ===============================  ==================================================
format        suffixes                         writer
============  ===============================  ==================================================
``glb``       ``.glb``                         :func:`keyshape.io.gltf.animate_gltf` onto the
                                               original glTF rig when there is one, else
                                               :func:`keyshape.io.gltf.write_glb`
``usd``       ``.usd`` ``.usda`` ``.usdc``     :func:`keyshape.io.usd.animate_usd` onto the
              ``.usdz``                        original USD rig when there is one, else
                                               :func:`keyshape.io.usd.write_usd` (``usd-core``)
``csv``       ``.csv``                         :func:`keyshape.io.weights_csv.save_weights_csv`
``livelink``  (``--format livelink``; a        :func:`keyshape.io.livelink.write_livelink_csv`
              ``.csv`` name)
``fbx``       ``.fbx``                         :func:`keyshape.io.blender.write_blender`: Blender's
``blend``     ``.blend``                       FBX exporter, or a Blender file (``bpy``, the
                                               ``blender`` extra, run in its own process)
``vrma``      ``.vrma``                        :func:`keyshape.io._vrma_write.write_vrma`: VRM
                                               Animation 1.0 for the ``.vrm`` avatar ``source``
============  ===============================  ==================================================
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

from ..containers import Poses, Rig, Weights
from ..exceptions import InputError

__all__ = ["Format", "export", "format_of"]


class Format(StrEnum):
    """The export formats."""

    GLB = "glb"
    USD = "usd"
    CSV = "csv"
    LIVELINK = "livelink"
    FBX = "fbx"
    BLEND = "blend"
    VRMA = "vrma"


_SUFFIXES = {".glb": Format.GLB, ".usd": Format.USD, ".usda": Format.USD, ".usdc": Format.USD,
             ".usdz": Format.USD, ".csv": Format.CSV, ".fbx": Format.FBX, ".blend": Format.BLEND,
             ".vrma": Format.VRMA}
_NEEDS_RIG = (Format.GLB, Format.USD, Format.FBX, Format.BLEND)
_BLENDER = (Format.FBX, Format.BLEND)


def format_of(path, format: str | Format | None = None) -> Format:
    """The format for ``path``: ``format`` when given (checked against the suffix), else the suffix.

    Examples
    --------
    >>> format_of("take.usda"), format_of("take.csv", "livelink")
    (<Format.USD: 'usd'>, <Format.LIVELINK: 'livelink'>)
    """
    suffix = Path(path).suffix.lower()
    if format is None:
        if suffix not in _SUFFIXES:
            raise InputError(f"cannot tell the format of {str(path)!r} from its suffix; use one of "
                             f"{sorted(_SUFFIXES)} or give a format ({', '.join(f.value for f in Format)})")
        return _SUFFIXES[suffix]
    try:
        chosen = Format(str(getattr(format, "value", format)).lower())
    except ValueError:
        raise InputError(f"unknown format {format!r}; choose from {', '.join(f.value for f in Format)}") from None
    expected = Format.CSV if chosen is Format.LIVELINK else chosen
    if _SUFFIXES.get(suffix) is not expected:
        wanted = sorted(s for s, f in _SUFFIXES.items() if f is expected)
        raise InputError(f"{str(path)!r}: format {chosen.value} is written to a file ending in {' or '.join(wanted)}")
    return chosen


def _source_kind(source) -> Format | None:
    """GLB for a glTF source file, USD for a USD one, else None (an OBJ rig: nothing to keep)."""
    suffix = "" if source is None else Path(source).suffix.lower()
    if suffix in (".glb", ".gltf"):
        return Format.GLB
    return Format.USD if suffix in (".usd", ".usda", ".usdc", ".usdz") else None


def export(animation: Weights, path, *, rig: Rig | None = None, poses: Poses | None = None,
           format: str | Format | None = None, source=None, head: str | None = None,
           eyes=None, colours=None) -> Path:
    """Write ``animation`` to ``path`` in the chosen format, atomically.

    Parameters
    ----------
    animation : Weights
        Target weights ``(n_frames, n_targets)``, named by rig targets (from
        :func:`keyshape.targets._mapping.retarget`): in rig order for ``glb`` and ``usd`` written from
        ``rig``; any subset of the original file's targets for ``glb`` onto ``source``.
    path : str or Path
    rig : Rig, optional, keyword-only
        Needed for ``usd``, and for ``glb``, ``fbx`` and ``blend`` without a glTF ``source``.
    poses : Poses, optional, keyword-only
        Head poses (image convention) for ``glb``, ``usd``, ``livelink`` and ``vrma``; ignored by
        ``csv``.
    format : str or Format, optional, keyword-only
        Default: from the suffix (``livelink`` must be asked for).
    source : str or Path, optional, keyword-only
        The file the rig came from: ``glb`` output onto a ``.glb``/``.gltf`` source and ``usd``
        output onto a USD source keep that file whole and add the animation; so do ``fbx`` and
        ``blend`` onto a glTF source (through Blender); ``vrma`` needs the ``.vrm`` avatar it
        animates
        (:func:`keyshape.io.gltf.animate_gltf`, :func:`keyshape.io.usd.animate_usd`).
    head : str, optional, keyword-only
        The node of ``source`` to turn with the head (default: found by name; see
        :func:`keyshape.io.gltf.animate_gltf`).
    eyes : (n_frames, 2, 3, 3) float, optional, keyword-only
        Eye rotations relative to the head (left eye first), for ``livelink``, ``vrma`` (its
        look-at) and for ``glb`` onto ``source`` (its eye nodes); files keyshape builds have no
        eyes and ignore them.
    colours : (n_vertices, 3) float in [0, 1], optional, keyword-only
        sRGB base colour per vertex of ``rig``, for ``glb`` written from it (``COLOR_0``).

    Returns
    -------
    Path

    Raises
    ------
    InputError
        Unknown format or suffix, ``rig`` missing where it is needed, or ``vrma`` without a
        ``.vrm`` source.
    """
    chosen = format_of(path, format)
    if chosen is Format.VRMA:
        if source is None or Path(source).suffix.lower() != ".vrm":
            raise InputError(f"{path}: a VRM Animation is written for a VRM avatar: give the .vrm it animates "
                             f"(the rig, --rig avatar.vrm)")
        from ._vrma_write import write_vrma

        return write_vrma(path, animation, source, poses=poses, eyes=eyes)
    kind = _source_kind(source)
    glb_source, usd_source = kind is Format.GLB, kind is Format.USD
    if chosen in _NEEDS_RIG and rig is None and kind is not chosen and not (chosen in _BLENDER and glb_source):
        raise InputError(f"writing {chosen.value} needs the rig")
    if chosen is Format.GLB:
        from .gltf import animate_gltf, write_glb

        if glb_source:
            return animate_gltf(source, animation, path, poses=poses, head=head, eyes=eyes)
        return write_glb(path, rig, animation, poses=poses, colours=colours)
    if chosen is Format.USD:
        from .usd import animate_usd, write_usd

        if usd_source:
            return animate_usd(source, animation, path, poses=poses)
        return write_usd(path, rig, animation, poses=poses)
    if chosen in _BLENDER:
        from .blender import write_blender

        return write_blender(path, animation, rig=rig, source=source if glb_source else None, poses=poses,
                             head=head, eyes=eyes)
    if chosen is Format.LIVELINK:
        from .livelink import write_livelink_csv

        return write_livelink_csv(path, animation, poses=poses, eyes=eyes)
    from .weights_csv import save_weights_csv

    return save_weights_csv(animation, path)
