"""Reading VRM avatars (private half of :func:`keyshape.io.rig.load_vrm`): expressions as targets.

A ``.vrm`` is a glTF 2.0 binary whose extension describes the avatar: ``VRMC_vrm`` for VRM 1.0,
``VRM`` for VRM 0.x. keyshape reads its meshes with morph targets as the glTF reader does
(:func:`keyshape.io._gltf_read.read_parts`: world space, skinned meshes as stored) and turns every
**expression** into one rig target, the mix of morph targets it binds::

    delta(expression) = Σ_binds weight · delta(mesh of the bind, morph target index)

* VRM 1.0: ``expressions.preset`` (``aa ih ou ee oh``, ``blink``, ``happy``, ...) and
  ``expressions.custom``, named by their key; a bind is ``{node, index, weight}`` (``weight`` in
  [0, 1], the node's mesh).
* VRM 0.x: ``blendShapeMaster.blendShapeGroups``; a bind is ``{mesh, index, weight}`` with
  ``weight`` in [0, 100]. A preset group is named in UniVRM's spelling of its ``presetName``
  (``A I U E O``, ``Blink``, ``Blink_L``, ``Joy``, ...), what VMC receivers expect; other groups
  by their ``name``. VRM 0.x avatars face −Z; they are turned 180° about +Y so that the rig faces
  +Z as every keyshape rig does.

Morph targets named after one of the 52 ARKit shapes ("perfect sync" avatars) are kept as targets
of their own too, unless an expression already has that name (ignoring case).

Material-colour and texture-transform binds, ``isBinary`` and the override flags are not read.

References
----------
VRM Consortium, *VRM 1.0 specification*, ``VRMC_vrm`` (``expressions``, ``morphTargetBinds``);
*VRM 0.x specification*, ``VRM`` extension (``blendShapeMaster``, ``blendShapeGroups``, ``binds``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..containers import Rig
from ..exceptions import InputError, RigError
from .livelink import LIVELINK_NAMES

__all__ = ["VrmAvatar", "VrmExpression", "read_vrm", "PRESETS_1", "PRESETS_0"]

# VRM 1.0 preset names, in the specification's order.
PRESETS_1 = ("happy", "angry", "sad", "relaxed", "surprised", "aa", "ih", "ou", "ee", "oh", "blink",
             "blinkLeft", "blinkRight", "lookUp", "lookDown", "lookLeft", "lookRight", "neutral")
# VRM 0.x presetName -> (UniVRM's spelling, the VRM 1.0 preset it corresponds to)
PRESETS_0 = {
    "neutral": ("Neutral", "neutral"), "a": ("A", "aa"), "i": ("I", "ih"), "u": ("U", "ou"),
    "e": ("E", "ee"), "o": ("O", "oh"), "blink": ("Blink", "blink"), "joy": ("Joy", "happy"),
    "angry": ("Angry", "angry"), "sorrow": ("Sorrow", "sad"), "fun": ("Fun", "relaxed"),
    "lookup": ("LookUp", "lookUp"), "lookdown": ("LookDown", "lookDown"), "lookleft": ("LookLeft", "lookLeft"),
    "lookright": ("LookRight", "lookRight"), "blink_l": ("Blink_L", "blinkLeft"),
    "blink_r": ("Blink_R", "blinkRight"),
}


@dataclass(frozen=True)
class VrmExpression:
    """One expression of an avatar.

    Attributes
    ----------
    name : str
        The avatar's own name for it (the rig target's name, what VMC sends).
    preset : str or None
        The VRM 1.0 preset it is (``"aa"``, ``"blinkLeft"``, ``"happy"``; a VRM 0.x ``Joy`` is
        ``"happy"``), None for a custom expression.
    binds : tuple of (mesh, morph target, weight)
        Mesh index into the glTF ``meshes``, morph target index, weight in [0, 1].
    """

    name: str
    preset: str | None
    binds: tuple[tuple[int, int, float], ...]


@dataclass(frozen=True)
class VrmAvatar:
    """A VRM avatar read as a rig.

    Attributes
    ----------
    rig : Rig
        ``n_targets = len(expressions) + len(arkit)``: the expressions first, in the file's order
        (VRM 1.0: presets, then custom), then the ARKit-named morph targets no expression names.
    version : str
        ``"1.0"`` (``VRMC_vrm``) or ``"0.x"`` (``VRM``).
    spec_version : str
        The file's own ``specVersion`` (``"1.0"``, ``"0.0"``), or ``""`` when absent.
    expressions : tuple of VrmExpression
    arkit : tuple of str
        The perfect-sync morph targets kept as targets of their own.
    """

    rig: Rig
    version: str
    spec_version: str
    expressions: tuple[VrmExpression, ...]
    arkit: tuple[str, ...]

    def name_of(self, preset: str) -> str | None:
        """The avatar's target for a VRM 1.0 preset (``"aa"`` → ``"A"`` on a VRM 0.x avatar), or None."""
        return next((e.name for e in self.expressions if e.preset == preset), None)


def read_vrm(path) -> VrmAvatar:
    """Read a ``.vrm`` file (VRM 1.0 or 0.x) as a :class:`VrmAvatar`.

    Raises
    ------
    RigError
        One line naming the file: not a VRM (no ``VRMC_vrm``/``VRM`` extension), no mesh with morph
        targets, a bind to a missing node, mesh or morph target, a weight that is not a finite
        number, two expressions of one name, or a damaged glTF.
    """
    from ._gltf_read import load_document, mesh_matrices, read_accessor, read_parts

    try:
        document, buffers = load_document(path, editable=False)
    except InputError as error:
        raise RigError(str(error)) from None
    extensions = document.extensions if isinstance(document.extensions, dict) else {}
    if isinstance(extensions.get("VRMC_vrm"), dict):
        version, raw = "1.0", _expressions_1(extensions["VRMC_vrm"], document, path)
        spec = str(extensions["VRMC_vrm"].get("specVersion", ""))
    elif isinstance(extensions.get("VRM"), dict):
        version, raw = "0.x", _expressions_0(extensions["VRM"], path)
        spec = str(extensions["VRM"].get("specVersion", ""))
    else:
        raise RigError(f"{path}: not a VRM avatar (no VRMC_vrm or VRM extension in the glTF)")
    meshes = [i for i, mesh in enumerate(document.meshes) if any(p.targets for p in mesh.primitives)]
    if not meshes:
        raise RigError(f"{path}: the avatar has no mesh with morph targets: its expressions cannot move it")
    base, parts = read_parts(document, buffers, meshes, path)
    matrices = mesh_matrices(document)
    expressions = _checked(raw, document, meshes, path)

    cache: dict[tuple[int, int], np.ndarray] = {}

    def morph(mesh: int, index: int) -> np.ndarray:
        """(n_vertices, 3): morph target ``index`` of ``mesh`` in the rig's rows (world space)."""
        if (mesh, index) not in cache:
            out, seen = np.zeros_like(base.vertices), set()
            linear = matrices[mesh][:3, :3] if mesh in matrices else np.eye(3)
            for part in parts:
                if part.mesh != mesh or part.start in seen:
                    continue
                seen.add(part.start)  # primitives sharing vertices carry one delta
                targets = document.meshes[mesh].primitives[part.primitive].targets or []
                accessor = (targets[index] or {}).get("POSITION") if index < len(targets) else None
                if accessor is not None:
                    out[part.start:part.start + part.count] = read_accessor(document, buffers, accessor) @ linear.T
            cache[mesh, index] = out
        return cache[mesh, index]

    deltas = [sum((w * morph(m, k) for m, k, w in e.binds), np.zeros_like(base.vertices)) for e in expressions]
    taken = {e.name.lower() for e in expressions}
    arkit = tuple(n for n in base.names if n.lower() in _ARKIT_LOWER and n.lower() not in taken)
    deltas += [base.deltas[base.names.index(n)] for n in arkit]
    vertices, deltas = base.vertices, np.array(deltas).reshape(-1, *base.vertices.shape)
    if version == "0.x":  # faces -Z: turn 180 degrees about +Y
        turn = np.array([-1.0, 1.0, -1.0])
        vertices, deltas = vertices * turn, deltas * turn
    rig = Rig(vertices, base.faces, deltas, tuple(e.name for e in expressions) + arkit)
    return VrmAvatar(rig, version, spec, tuple(expressions), arkit)


def _expressions_1(vrm: dict, document, path) -> list[tuple[str, str | None, list]]:
    """``(name, preset, binds as (node, index, weight))`` of a ``VRMC_vrm`` extension."""
    expressions = vrm.get("expressions") or {}
    if not isinstance(expressions, dict):
        raise RigError(f"{path}: VRMC_vrm.expressions is not an object")
    out = []
    for group in ("preset", "custom"):
        entries = expressions.get(group) or {}
        if not isinstance(entries, dict):
            raise RigError(f"{path}: VRMC_vrm.expressions.{group} is not an object")
        for name, entry in entries.items():
            if group == "preset" and name not in PRESETS_1:
                raise RigError(f"{path}: VRMC_vrm.expressions.preset has {name!r}, not a VRM 1.0 preset")
            binds = _binds(entry, "morphTargetBinds", "node", f"expression {name!r}", path)
            nodes = document.nodes
            resolved = []
            for node, index, weight in binds:
                if not 0 <= node < len(nodes) or nodes[node].mesh is None:
                    raise RigError(f"{path}: expression {name!r} binds node {node}, which has no mesh")
                resolved.append((int(nodes[node].mesh), index, weight))
            out.append((str(name), name if group == "preset" else None, resolved))
    return out


def _expressions_0(vrm: dict, path) -> list[tuple[str, str | None, list]]:
    """``(name, preset, binds as (mesh, index, weight / 100))`` of a VRM 0.x ``VRM`` extension."""
    groups = (vrm.get("blendShapeMaster") or {}).get("blendShapeGroups") or []
    if not isinstance(groups, list):
        raise RigError(f"{path}: VRM.blendShapeMaster.blendShapeGroups is not a list")
    out = []
    for number, group in enumerate(groups):
        if not isinstance(group, dict):
            raise RigError(f"{path}: blendShapeGroups[{number}] is not an object")
        preset = str(group.get("presetName") or "unknown").lower()
        if preset in PRESETS_0:
            name, canonical = PRESETS_0[preset]
        else:
            name, canonical = group.get("name"), None
            if not isinstance(name, str) or not name:
                raise RigError(f"{path}: blendShapeGroups[{number}] has neither a preset nor a name")
        binds = _binds(group, "binds", "mesh", f"blend shape group {name!r}", path)
        out.append((name, canonical, [(m, k, w / 100.0) for m, k, w in binds]))
    return out


def _binds(entry, field: str, owner: str, what: str, path) -> list[tuple[int, int, float]]:
    if not isinstance(entry, dict):
        raise RigError(f"{path}: {what} is not an object")
    binds = entry.get(field) or []
    if not isinstance(binds, list):
        raise RigError(f"{path}: {what}: {field} is not a list")
    out = []
    for bind in binds:
        try:
            default = 1.0 if owner == "node" else 100.0  # the schemas' defaults
            where, index, weight = bind[owner], bind["index"], float(bind.get("weight", default))
        except (KeyError, TypeError, ValueError, AttributeError):
            raise RigError(f"{path}: {what} has a bind without a whole {owner}, index and numeric weight: "
                           f"{bind!r}") from None
        if not (isinstance(where, int) and isinstance(index, int) and np.isfinite(weight)):
            raise RigError(f"{path}: {what} has a bind without a whole {owner}, index and finite weight: {bind!r}")
        out.append((where, index, weight))
    return out


def _checked(raw, document, meshes, path) -> list[VrmExpression]:
    """The expressions, after checking names are unique and every bind reaches a morph target."""
    seen, out = set(), []
    for name, preset, binds in raw:
        if name in seen:
            raise RigError(f"{path}: two expressions are named {name!r}")
        seen.add(name)
        for mesh, index, _ in binds:
            if mesh not in meshes:
                raise RigError(f"{path}: expression {name!r} binds mesh {mesh}, which has no morph targets")
            n_targets = max(len(p.targets or []) for p in document.meshes[mesh].primitives)
            if not 0 <= index < n_targets:
                raise RigError(f"{path}: expression {name!r} binds morph target {index} of mesh {mesh}, "
                               f"which has {n_targets}")
        out.append(VrmExpression(name, preset, tuple(binds)))
    return out


_ARKIT_LOWER = frozenset(n.lower() for n in LIVELINK_NAMES)  # the 52 ARKit names, case folded
