"""glTF 2.0: morph-target rigs in, morph-weight (and head-rotation) animation out.

Three writers, all producing one self-contained binary ``.glb``, atomically:

* :func:`write_glb` builds a new file from a :class:`~keyshape.containers.Rig`: one mesh
  whose morph targets are the rig's deltas, named in ``mesh.extras.targetNames`` (the
  convention read by three.js, Babylon.js and Blender), one node ``"face"`` holding it, and
  one animation: a ``weights`` channel sampled at ``frame / fps`` with LINEAR interpolation,
  plus an optional ``rotation`` channel for the head.
* :func:`animate_gltf` keeps an artist's **original** file (skinning, materials, textures,
  other meshes and animations) and adds one animation ``"keyshape"``, placed first (the one
  viewers play by default; the file's own animations follow): a ``weights`` channel
  on every node whose mesh carries the targets, and the head rotation on the character's
  head node (a joint or node named like ``head`` above the face meshes).
* :func:`write_gltf_targets` puts new morph targets (the sculpt kit's, one per key shape)
  on chosen meshes of an original file.

Coordinates follow glTF: metres, +Y up, the character facing +Z. Rigs are read in world
space (each mesh through its node's rest world transform; see :func:`read_rig`), and new
targets are written back in each mesh's own space. Image-space rotations (x right, y down,
z away from the camera) are converted with ``C = diag(1, -1, -1)``: ``R_gltf = C R C``.

References
----------
The Khronos Group, *glTF 2.0 Specification*, sections 3.7.2.2 (morph targets), 3.6.2.3
(sparse accessors) and 3.11 (animations).

Layout: this module holds the three writers and :func:`read_meshes`; the animation pieces
they share with the USD and Live Link writers (checks, rotations, channels) are in
:mod:`keyshape.io._gltf_anim`, document building and editing in :mod:`keyshape.io._gltf_edit`,
the head and eye nodes in :mod:`keyshape.io._gltf_nodes`, reading in :mod:`keyshape.io._gltf_read`.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pygltflib

from ..containers import Poses, Rig, Weights
from ..exceptions import InputError, RigError
from ..schemes import head_rotations, hold_valid, rotations_to_gltf
from . import _gltf_edit as edit
from ._gltf_anim import (
    add_node_rotation,
    add_rotation,
    check_eyes,
    check_names,
    check_poses,
    mesh_weights,
    new_animation,
    pose_quaternions,
    time_accessor,
    weights_output,
)
from ._gltf_nodes import (
    ancestry,
    descendants,
    find_eyes,
    find_head,
    head_joint,
    is_head,
    parents,
    world_matrix,
    world_rotation,
)
from ._gltf_read import (
    ANIMATION_NAMES,
    GlbAnimation,
    Part,
    choose_animation,
    load_document,
    mesh_matrices,
    morph_meshes,
    part_colours,
    read_accessor,
    read_glb_animation,
    read_parts,
    read_rig,
    target_names,
)
from .atomic import atomic_path
from .validate import check_weight_values

__all__ = ["write_glb", "animate_gltf", "write_gltf_targets", "read_glb_animation", "read_rig",
           "read_meshes", "read_colours", "read_face_scene", "read_head_motion", "head_mesh", "mesh_names",
           "eye_nodes", "check_gltf_file", "GlbAnimation", "Part"]

ANIMATION = ANIMATION_NAMES[0]


def check_gltf_file(path: str | Path) -> Path:
    """``path`` if it reads as glTF whose every index and byte range holds (a .glb's header too:
    :func:`~keyshape.io.validate.check_glb`, then
    :func:`~keyshape.io.validate.check_gltf_document`); else InputError naming it. For a file
    read later (the preview's, the viewer's), said before any work."""
    from .validate import check_glb

    path = Path(path)
    if path.suffix.lower() == ".glb":
        check_glb(path)
    load_document(path, editable=False)
    return path


# --------------------------------------------------------------------------- a new file


def write_glb(path, rig: Rig, weights: Weights, *, poses: Poses | None = None,
              colours: np.ndarray | None = None) -> Path:
    """Write a rig and its weight animation as a binary glTF 2.0 file, atomically.

    Parameters
    ----------
    path : str or Path
        Output file; must end in ``.glb``. Written to a temporary file in the same
        folder and moved into place, so a failure leaves no partial file.
    rig : Rig
        Neutral mesh and target deltas (written as they are: glTF metres, +Y up). Targets
        that move few vertices are stored as sparse accessors.
    weights : Weights
        ``values (n_frames, n_targets)`` named exactly ``rig.names``, in that order
        (use :func:`keyshape.targets._mapping.retarget` first). NaN frames are written as 0.
        With no frames, no animation is written (a plain rig, e.g. for sculpting).
    poses : Poses, optional
        Head pose per frame in image convention (2D or 3D rotations, ``n_frames`` as
        ``weights``); written as a ``rotation`` channel on the node. NaN frames hold the
        previous valid rotation (leading ones take the first valid; none at all: identity).
    colours : (n_vertices, 3) float in [0, 1], optional
        sRGB base colour per vertex, written as ``COLOR_0`` (linear, as glTF stores it) under a
        white material.

    Returns
    -------
    Path
        The written file.

    Raises
    ------
    RigError
        If the weight names are not the rig's target names in order.
    InputError
        If the suffix is not ``.glb`` or ``poses`` has another frame count.

    Examples
    --------
    >>> import tempfile, os
    >>> rig = Rig(np.eye(3), [[0, 1, 2]], np.ones((1, 3, 3)), ("open",))
    >>> anim = Weights(np.array([[0.0], [1.0]]), ("open",), fps=30)
    >>> out = write_glb(os.path.join(tempfile.mkdtemp(), "a.glb"), rig, anim)
    >>> read_glb_animation(out).weights[:, 0]
    array([0., 1.])
    """
    path = Path(path)
    _check_suffix(path)
    check_names(rig.names, weights)
    check_weight_values(path, weights.names, weights.values, weights.frame_index)
    if rig.n_targets == 0:
        raise RigError("the rig has no morph targets to animate")
    check_poses(poses, weights)
    rotations = None if poses is None else pose_quaternions(poses)
    if colours is not None:
        colours = np.asarray(colours, dtype=float)
        if colours.shape != (rig.n_vertices, 3) or not np.isfinite(colours).all():
            raise InputError(f"colours must be finite with shape ({rig.n_vertices}, 3); got {colours.shape}")
    return _save(path, _build_document(rig, weights, rotations, colours))


def _check_suffix(path: Path) -> None:
    if path.suffix.lower() != ".glb":
        raise InputError(f"glTF output is binary glTF: the path must end in .glb; got {str(path)!r}")


def _save(path: Path, document: pygltflib.GLTF2) -> Path:
    data = b"".join(document.save_to_bytes())
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def _build_document(rig: Rig, weights: Weights, rotations: np.ndarray | None,
                    colours: np.ndarray | None = None) -> pygltflib.GLTF2:
    document = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="keyshape"),
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(name="face", mesh=0)],
    )
    blob = edit.Blob(document)
    document.meshes.append(_mesh(blob, rig, colours))
    base = [0.8, 0.8, 0.8, 1.0] if colours is None else [1.0, 1.0, 1.0, 1.0]
    document.materials.append(
        pygltflib.Material(
            name="face",
            pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorFactor=base, metallicFactor=0.0, roughnessFactor=0.7
            ),
            doubleSided=True,
        )
    )
    if weights.n_frames:
        times = time_accessor(blob, weights)
        output = weights_output(blob, weights.values)
        document.animations.append(new_animation(times, [(0, output)], "performance"))
        if rotations is not None:
            add_rotation(document.animations[0], blob, times, 0, rotations)
    blob.finish()
    return document


def _mesh(blob: edit.Blob, rig: Rig, colours: np.ndarray | None = None) -> pygltflib.Mesh:
    array_buffer, element_buffer = pygltflib.ARRAY_BUFFER, pygltflib.ELEMENT_ARRAY_BUFFER
    position = blob.add(rig.vertices.astype(np.float32), "VEC3", target=array_buffer, bounds=True)
    index_dtype = np.uint16 if rig.n_vertices < 65535 else np.uint32
    indices = blob.add(rig.faces.reshape(-1).astype(index_dtype), "SCALAR", target=element_buffer)
    targets = [{"POSITION": blob.add_target(delta)} for delta in rig.deltas]
    attributes = pygltflib.Attributes(POSITION=position)
    if colours is not None:  # glTF's COLOR_0 is linear: sRGB decoded (IEC 61966-2-1)
        linear = np.where(colours <= 0.04045, colours / 12.92, ((np.clip(colours, 0, 1) + 0.055) / 1.055) ** 2.4)
        attributes.COLOR_0 = blob.add(linear.astype(np.float32), "VEC3", target=array_buffer)
    primitive = pygltflib.Primitive(attributes=attributes, indices=indices, material=0, targets=targets)
    return pygltflib.Mesh(
        name="face",
        primitives=[primitive],
        weights=[0.0] * rig.n_targets,
        extras={"targetNames": list(rig.names)},
    )


# --------------------------------------------------------------------------- an artist's file


def animate_gltf(source, weights: Weights, path, *, poses: Poses | None = None,
                 head: str | None = None, eyes: np.ndarray | None = None,
                 eye_nodes: tuple[str, str] | None = None) -> Path:
    """Add the performance to an artist's own glTF file, keeping everything else.

    Parameters
    ----------
    source : str or Path
        The character (``.glb`` or ``.gltf``) whose meshes carry named morph targets.
    weights : Weights
        ``values (n_frames, n_channels)`` named by the file's target names (any order, any
        subset; targets not named keep their default weight). NaN is written as 0.
    path : str or Path
        Output ``.glb``: the original scene with every buffer and image packed in, skinned
        meshes moved to the scene root (the spec ignores their parents' transforms anyway),
        earlier ``keyshape`` animations replaced, and one animation ``"keyshape"`` added as
        ``animations[0]`` (what viewers play by default), the file's own animations after it.
    poses : Poses, optional
        Head poses (image convention, as :func:`write_glb`), written as the ``rotation`` of
        the head node: ``Pᵀ D P R`` for a world-frame head rotation ``D``, the head's parent
        rest rotation ``P`` and its own rest rotation ``R``, so it turns about its pivot. Where no
        head node is found (and none is named), it is not written, with a warning.
    head : str, optional, keyword-only
        Name of the node to turn. Default: found (see ``_gltf_nodes.find_head``).
    eyes : (n_frames, 2, 3, 3) float, optional, keyword-only
        Eye rotations relative to the head, image convention (as ``poses.rotations``), the
        character's left eye first; NaN frames hold the previous valid rotation. Written as the
        ``rotation`` of the eye nodes (below the head, named like ``Eye_L``/``RightEye``; see
        ``_gltf_nodes.find_eyes``), composed with their rest rotation as the head's. A character
        without eye nodes gets none (its eyes belong to the face meshes).
    eye_nodes : (str, str), optional, keyword-only
        Names of the (left, right) eye nodes, when they cannot be found by name.

    Returns
    -------
    Path

    Raises
    ------
    RigError
        If the file has no named morph targets, ``weights`` names targets it lacks, or ``head``
        or ``eye_nodes`` name nodes the file does not have.
    """
    path, source = Path(path), Path(source)
    _check_suffix(path)
    check_weight_values(path, weights.names, weights.values, weights.frame_index)
    check_poses(poses, weights)
    check_eyes(eyes, weights)
    document, buffers = load_document(source)
    meshes = morph_meshes(document, source)
    _check_known(document, meshes, weights, source)
    blob = edit.pack(document, buffers, source)
    edit.drop_animations(document, ANIMATION_NAMES)
    edit.root_skinned_meshes(document)
    if weights.n_frames:
        animation, nodes = _performance(document, blob, meshes, weights, source)
        _turn_head(document, blob, animation, nodes, poses, head, source)
        _turn_eyes(document, blob, animation, nodes, eyes, (head, eye_nodes), source)
        document.animations.insert(0, animation)  # viewers (three.js, ...) play animations[0]
    blob.finish()
    edit.prune(document)
    return _save(path, document)


def _check_known(document, meshes, weights: Weights, source) -> None:
    known = {name for m in meshes for name in target_names(document.meshes[m])}
    if not known:
        raise RigError(f"{str(source)!r} has no morph targets: it cannot be driven as a blendshape rig")
    unknown = [n for n in weights.names if n not in known]
    if unknown:
        raise RigError(f"weights name targets {str(source)!r} does not have: {unknown}; "
                       f"its targets: {sorted(known)}")


def _performance(document, blob, meshes, weights, source) -> tuple[pygltflib.Animation, list[int]]:
    """The ``keyshape`` animation with a ``weights`` channel per face node, and those nodes."""
    times = time_accessor(blob, weights)
    outputs, by_mesh = [], {}
    nodes = edit.morph_nodes(document, meshes)
    if not nodes:
        raise RigError(f"{str(source)!r}: no node shows the meshes with morph targets; nothing to animate")
    for node in nodes:
        mesh = document.nodes[node].mesh
        if mesh not in by_mesh:
            by_mesh[mesh] = weights_output(blob, mesh_weights(document.meshes[mesh], weights))
        outputs.append((node, by_mesh[mesh]))
    return new_animation(times, outputs, ANIMATION), nodes


def eye_nodes(source) -> tuple[str, str] | None:
    """Names of the (left, right) eye nodes :func:`animate_gltf` would turn with the gaze, or None.

    None when the file has no such nodes: its eyes move only through morph targets (``eyeLook*``).
    """
    document, _ = load_document(source, editable=False)
    nodes = edit.morph_nodes(document, morph_meshes(document, source))
    found = find_eyes(document, find_head(document, nodes))
    return None if found is None else (document.nodes[found[0]].name, document.nodes[found[1]].name)


def _turn_head(document, blob, animation, nodes, poses, head, source) -> None:
    if poses is None:
        return
    index = find_head(document, nodes, name=head)
    if index is None:
        warnings.warn(f"{str(source)!r}: no head node found (no joint or node named like 'head' above the "
                      "face meshes): the head rotation is not written; name the node to turn", UserWarning,
                      stacklevel=4)
        return
    add_node_rotation(document, blob, animation, index, head_rotations(poses, hold=True))


def _turn_eyes(document, blob, animation, nodes, eyes, names, source) -> None:
    if eyes is None:
        return
    head, eye_nodes = names
    found = find_eyes(document, find_head(document, nodes, name=head), names=eye_nodes)
    if found is None:  # a character without eye nodes: its eyes are part of the face meshes
        return
    eyes = np.asarray(eyes, dtype=float)
    for side, node in enumerate(found):
        add_node_rotation(document, blob, animation, node, rotations_to_gltf(hold_valid(eyes[:, side])))


# --------------------------------------------------------------------------- new targets


def read_meshes(path, *, meshes=None) -> tuple[Rig, list[Part]]:
    """The chosen meshes of a glTF file as one rig, and where each primitive sits in it.

    Parameters
    ----------
    path : str or Path
    meshes : sequence of int or str, optional, keyword-only
        Mesh indices or names. Default: the meshes with morph targets; when none has any (a
        plain character to sculpt on or transfer onto), the head's mesh (:func:`head_mesh`), else
        every mesh.

    Returns
    -------
    rig : Rig
        Neutral vertices ``(n_vertices, 3)`` and the meshes' existing targets, if any, in world
        space as :func:`read_rig` reads them (each mesh through the rest world transform of the
        first node that shows it; skinned meshes as stored).
    parts : list of Part
    """
    document, buffers = load_document(path, editable=False)
    chosen = _choose_meshes(document, meshes, path, buffers)
    return read_parts(document, buffers, chosen, path)


def read_colours(path, *, meshes=None) -> np.ndarray:
    """Base colours and opacity ``(n_vertices, 4)`` (RGBA in [0, 1]) of the vertices :func:`read_meshes` returns.

    From each primitive's material (base colour factor, base-colour texture where PNG or JPEG,
    ``COLOR_0``, alpha mode): what the character looks like, for the renders that find its landmarks.
    """
    document, buffers = load_document(path, editable=False)
    return part_colours(document, buffers, _choose_meshes(document, meshes, path, buffers), path)


def read_face_scene(path) -> tuple[Rig, np.ndarray]:
    """What a picture of the character's face shows: its morph-target meshes and the still
    meshes about them (hair, separate eyes, glasses), with their colours.

    A mesh without morph targets joins when nine tenths of its vertices lie in the morph
    meshes' bounding box grown by a quarter about its centre (the hair of a full-body avatar
    does; its outfit and shoes do not).

    Returns
    -------
    rig : Rig
        The morph meshes as :func:`read_rig` reads them, then the still meshes' vertices
        (their deltas zero), ``n_vertices`` in all.
    colours : (n_vertices, 4) float
        RGBA in [0, 1], as :func:`read_colours`.
    """
    document, buffers = load_document(path, editable=False)
    morph = morph_meshes(document, path)
    if not morph:
        raise RigError(f"{str(path)!r} has no morph targets: it cannot be driven as a blendshape rig")
    rig = read_parts(document, buffers, morph, path)[0]
    lo, hi = rig.vertices.min(axis=0), rig.vertices.max(axis=0)
    centre, reach = (lo + hi) / 2, (hi - lo) / 2 * 1.25 + 1e-9
    still = []
    for m in range(len(document.meshes)):
        if m in morph:
            continue
        vertices = read_parts(document, buffers, [m], path)[0].vertices
        if len(vertices) and (np.abs(vertices - centre) <= reach).all(axis=1).mean() >= 0.9:
            still.append(m)
    colours = part_colours(document, buffers, morph + still, path)
    if not still:
        return rig, colours
    other = read_parts(document, buffers, still, path)[0]
    deltas = np.concatenate([rig.deltas, np.zeros((rig.n_targets, other.n_vertices, 3))], axis=1)
    merged = Rig(np.vstack([rig.vertices, other.vertices]), np.vstack([rig.faces, other.faces + rig.n_vertices]),
                 deltas, rig.names)
    return merged, colours


def read_head_motion(path) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the head turns about and how, in the world: ``(pivot, rotations)``, or None.

    From the first ``rotation`` channel of the animation :func:`read_glb_animation` reads (the
    head's, in files keyshape writes): the node's stored local rotations ``L`` become the
    world rotations ``D = P L Rᵀ Pᵀ`` (``P`` its parent's rest world rotation, ``R`` its own
    rest rotation; the inverse of what the writers store), about the node's rest position.

    Returns
    -------
    pivot : (3,) float
        The turning node's rest world position (metres).
    rotations : (n_frames, 3, 3) float
        World rotations of the head, identity at rest.
    """
    from scipy.spatial.transform import Rotation

    animation = read_glb_animation(path)
    if animation.rotations is None:
        return None
    document, _ = load_document(path, editable=False)
    chosen = choose_animation(document, None, path)
    node = next(c.target.node for c in chosen.channels if c.target.path == "rotation")
    p = world_rotation(document, parents(document).get(node))
    rest = Rotation.from_quat(document.nodes[node].rotation or [0, 0, 0, 1]).as_matrix()
    local = Rotation.from_quat(np.asarray(animation.rotations, dtype=float).reshape(-1, 4)).as_matrix()
    # f: frame; D_f = P L_f R^T P^T
    rotations = np.einsum("ij,fjk,lk,ml->fim", p, local, rest, p)
    return world_matrix(document, node)[:3, 3].copy(), rotations


def mesh_names(path) -> list[str]:
    """The name of every mesh of a glTF file, in order (its index where it has none): the values
    ``meshes=`` (``--mesh``) takes."""
    document, _ = load_document(path, editable=False)
    return [m.name or str(i) for i, m in enumerate(document.meshes)]


def head_mesh(path) -> str | None:
    """The name of the mesh of a character's head, for a glTF file without morph targets; None
    when none is found (or the file has morph targets: those meshes are the face).

    Of a skinned character, the largest mesh (most vertices) at least half of whose vertices
    follow the head joint (the skin joint named like ``head`` nearest the root) or a joint below
    it (the eyes) most: a Ready Player Me avatar's ``Wolf3D_Head``, not its hair, outfit or
    body. Of an unskinned one, the largest mesh under a node named like ``head``.
    """
    document, buffers = load_document(path, editable=False)
    if morph_meshes(document, path):
        return None
    index = _head_mesh(document, buffers)
    return None if index is None else document.meshes[index].name


def _head_mesh(document, buffers) -> int | None:
    parent_of = parents(document)
    skinned = [n for n, node in enumerate(document.nodes) if node.mesh is not None and node.skin is not None]
    shown = skinned or [n for n, node in enumerate(document.nodes) if node.mesh is not None]
    size, best = 0, None
    for n in shown:
        node = document.nodes[n]
        primitive = document.meshes[node.mesh].primitives[0]
        count = read_accessor(document, buffers, primitive.attributes.POSITION).shape[0]
        if node.skin is not None:
            head = head_joint(document, [n], parent_of)
            joints_at, weights_at = primitive.attributes.JOINTS_0, primitive.attributes.WEIGHTS_0
            if head is None or joints_at is None or weights_at is None:
                continue
            joints = np.asarray(document.skins[node.skin].joints)
            slots = read_accessor(document, buffers, joints_at).astype(int)
            strongest = slots[np.arange(count), read_accessor(document, buffers, weights_at).argmax(axis=1)]
            below = set(descendants(document, head))
            held = np.isin(joints[np.clip(strongest, 0, len(joints) - 1)], list(below)).mean()
        else:
            held = float(any(is_head(document.nodes[a].name) for a in ancestry(n, parent_of)[1:]))
        if held >= 0.5 and count > size:
            size, best = count, node.mesh
    return best


def _choose_meshes(document, meshes, path, buffers=None) -> list[int]:
    if meshes is None:
        chosen = morph_meshes(document, path)
        if not chosen and buffers is not None:
            head = _head_mesh(document, buffers)
            chosen = [] if head is None else [head]
        return chosen or list(range(len(document.meshes)))
    names = [m.name for m in document.meshes]
    chosen = []
    for item in meshes:
        if isinstance(item, str) and item in names:
            chosen.append(names.index(item))
        elif isinstance(item, (int, np.integer)) and 0 <= item < len(names):
            chosen.append(int(item))
        else:
            raise RigError(f"{str(path)!r} has no mesh {item!r}; meshes: {names}")
    if not chosen:
        raise RigError(f"{str(path)!r}: no meshes chosen")
    return list(dict.fromkeys(chosen))


def write_gltf_targets(source, path, rig: Rig, *, meshes=None) -> Path:
    """Replace the morph targets of chosen meshes of ``source`` by the rig's, and write a ``.glb``.

    Parameters
    ----------
    source : str or Path
        The original ``.glb``/``.gltf``; everything else in it is kept.
    path : str or Path
        Output ``.glb`` (atomic).
    rig : Rig
        Vertices laid out as :func:`read_meshes` returns them for ``meshes`` (same count);
        its ``deltas (n_targets, n_vertices, 3)``, in world space as :func:`read_meshes` reads
        them, become the targets, named ``rig.names``, at weight 0: each mesh's are taken back
        to its own space (the inverse of its node's linear part) and stored as float32, beside
        positions that may stay quantized (``KHR_mesh_quantization`` is kept).
    meshes : sequence of int or str, optional, keyword-only
        As :func:`read_meshes`.

    Returns
    -------
    Path

    Raises
    ------
    RigError
        If the rig's vertex count differs from the chosen meshes', it has no targets, or a
        mesh's node transform cannot be inverted (a zero scale).
    """
    path, source = Path(path), Path(source)
    _check_suffix(path)
    document, buffers = load_document(source)
    chosen = _choose_meshes(document, meshes, source, buffers)
    _, parts = read_parts(document, buffers, chosen, source)
    _check_layout(rig, parts, source)
    to_local = _to_local(document, parts, source)
    blob = edit.pack(document, buffers, source)
    _set_targets(document, blob, rig, parts, to_local)
    edit.drop_weight_channels(document, edit.morph_nodes(document, chosen))
    edit.root_skinned_meshes(document)
    blob.finish()
    edit.prune(document)
    return _save(path, document)


def _check_layout(rig: Rig, parts: list[Part], source) -> None:
    n_vertices = max((p.start + p.count for p in parts), default=0)
    if rig.n_vertices != n_vertices:
        raise RigError(f"{str(source)!r}: the chosen meshes have {n_vertices} vertices but the rig has "
                       f"{rig.n_vertices}; targets must be laid out as read_meshes() returns them")
    if rig.n_targets == 0:
        raise RigError("the rig has no targets to write")


def _to_local(document, parts: list[Part], source) -> dict[int, np.ndarray]:
    """``{mesh: (3, 3) float}``: the inverse linear part of each moved mesh's world transform.

    Row-vector world deltas ``d (n, 3)`` go back to the mesh's space as ``d @ inverse.T``.
    """
    matrices = mesh_matrices(document)
    out = {}
    for mesh in dict.fromkeys(p.mesh for p in parts):
        if mesh not in matrices:
            continue
        linear = matrices[mesh][:3, :3]
        if not np.linalg.cond(linear) < 1e12:  # also catches NaN and infinite
            raise RigError(f"{str(source)!r}: the node showing mesh {mesh} has a degenerate transform "
                           f"(a zero scale); new targets cannot be placed in it")
        out[mesh] = np.linalg.inv(linear)
    return out


def _set_targets(document, blob: edit.Blob, rig: Rig, parts: list[Part], to_local: dict[int, np.ndarray]
                 ) -> None:
    blocks: dict[int, list[dict]] = {}
    for part in parts:
        if part.start not in blocks:
            block = rig.deltas[:, part.start:part.start + part.count]
            if part.mesh in to_local:  # parts sharing a block share its transform (read_parts)
                block = block @ to_local[part.mesh].T
            blocks[part.start] = [{"POSITION": blob.add_target(delta)} for delta in block]
        primitive = document.meshes[part.mesh].primitives[part.primitive]
        primitive.targets = [dict(t) for t in blocks[part.start]]
        if isinstance(primitive.extras, dict):
            primitive.extras.pop("targetNames", None)
    for mesh_index in dict.fromkeys(p.mesh for p in parts):
        mesh = document.meshes[mesh_index]
        mesh.weights = [0.0] * rig.n_targets
        mesh.extras = {**(mesh.extras if isinstance(mesh.extras, dict) else {}),
                       "targetNames": list(rig.names)}
