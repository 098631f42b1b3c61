"""Reading glTF 2.0 (private half of :mod:`keyshape.io.gltf`): accessors, rigs, animations.

A glTF rig is every primitive of the meshes that carry morph targets, concatenated into one
:class:`~keyshape.containers.Rig`. Primitives that share one ``POSITION`` accessor (one vertex
buffer split by material) share one block of rig vertices. :class:`Part` records where each
primitive's vertices sit in the rig, so edited targets can be written back into the file.

Geometry is read in **world space**: each mesh is placed by the rest world transform of the
first node (lowest index) that shows it (:func:`mesh_matrices`), so a head exported under a
Z-up, centimetre or quantized hierarchy reads as the viewer shows it. Positions and target
deltas may be quantized (``KHR_mesh_quantization``: integer components, normalized or not);
:func:`read_accessor` decodes them and the node transform carries the dequantization.

References
----------
The Khronos Group, *glTF 2.0 Specification*, sections 3.6 (accessors, sparse accessors),
3.7.2.2 (morph targets) and 3.11 (animations).
"""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pygltflib

from ..containers import Rig
from ..exceptions import InputError, RigError
from ._gltf_nodes import parents, world_matrix
from .validate import check_gltf_document

COMPONENT_DTYPES = {
    pygltflib.BYTE: np.int8,
    pygltflib.UNSIGNED_BYTE: np.uint8,
    pygltflib.SHORT: np.int16,
    pygltflib.UNSIGNED_SHORT: np.uint16,
    pygltflib.UNSIGNED_INT: np.uint32,
    pygltflib.FLOAT: np.float32,
}
N_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
# Our own animations; when a file has several, these are read first.
ANIMATION_NAMES = ("keyshape", "performance")
# Geometry we cannot decode: the file can still be animated, not read as a rig.
_COMPRESSION = ("KHR_draco_mesh_compression", "EXT_meshopt_compression")


class GlbAnimation(NamedTuple):
    """A morph-weight animation read back from a glTF file.

    Attributes
    ----------
    names : tuple of n_targets str
        Union of the target names of every mesh the animation's ``weights`` channels drive.
    times : (n_frames,) float, seconds
    weights : (n_frames, n_targets) float
    rotations : (n_frames, 4) float or None
        Quaternions (x, y, z, w) of the animation's first ``rotation`` channel (the head's, in
        files keyshape writes), as stored (the node's local rotation), or None.
    """

    names: tuple[str, ...]
    times: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray | None


class Part(NamedTuple):
    """Where one primitive's vertices sit in a rig read from a glTF file.

    Attributes
    ----------
    mesh, primitive : int
        Indices into ``document.meshes`` and ``mesh.primitives``.
    start, count : int
        The primitive's vertices are ``rig.vertices[start:start + count]``.
    """

    mesh: int
    primitive: int
    start: int
    count: int


# --------------------------------------------------------------------------- files and accessors


def load_document(path, *, editable: bool = True):
    """The glTF document at ``path`` and the bytes of each of its buffers.

    ``editable=True`` gives a :class:`pygltflib.GLTF2` (to modify and save). ``editable=False``
    parses the file directly into read-only attribute-access dicts (:class:`_Json`), some 100×
    faster for large scenes; the readers below accept either.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such glTF file: {str(path)!r}")
    try:
        document = pygltflib.GLTF2().load(str(path)) if editable else _parse(path)
    except InputError:
        raise
    except Exception as error:  # pygltflib raises bare exceptions on malformed input
        raise InputError(f"cannot read {str(path)!r} as glTF: {error}") from error
    if document is None:
        raise InputError(f"cannot read {str(path)!r} as glTF")
    buffers = [_buffer_bytes(document, buffer, path) for buffer in document.buffers]
    check_gltf_document(path, document, buffers)  # every index and byte range, before any is followed
    return document, buffers


class _Json:
    """A JSON object read with attribute access (``accessor.count``); missing members are None.

    ``extras``, ``extensions`` and morph ``targets`` stay plain dicts, as pygltflib keeps them.
    """

    __slots__ = ("_members",)

    def __init__(self, members: dict):
        self._members = members

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return self._members.get(name)


_PLAIN = ("extras", "extensions", "targets")


def _wrap(value, key=None):
    if key in _PLAIN:
        return value
    if isinstance(value, dict):
        return _Json({k: _wrap(v, k) for k, v in value.items()})
    if isinstance(value, list):
        return [_wrap(v) for v in value]
    return value


class _Document(_Json):
    __slots__ = ("_blob",)

    def binary_blob(self) -> bytes:
        return self._blob


_TOP_LEVEL = ("accessors", "animations", "bufferViews", "buffers", "images", "materials", "meshes", "nodes",
              "scenes", "skins", "textures", "extensionsUsed", "extensionsRequired")


def _parse(path: Path) -> _Document:
    data = path.read_bytes()
    blob = b""
    if data[:4] == b"glTF":
        text, blob = _glb_chunks(data, path)
    else:
        text = data
    members = json.loads(text)
    if not isinstance(members, dict):
        raise InputError(f"{str(path)!r}: not a glTF document")
    document = _Document({k: _wrap(v, k) for k, v in members.items()})
    for key in _TOP_LEVEL:
        document._members.setdefault(key, [])
    document._blob = blob
    return document


def _glb_chunks(data: bytes, path: Path) -> tuple[bytes, bytes]:
    """The JSON and BIN chunks of a GLB container (glTF 2.0 spec, section 4.4)."""
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2 or length > len(data):
        raise InputError(f"{str(path)!r}: not a glTF 2.0 binary file (version {version}, {length} bytes declared)")
    chunks, offset = {}, 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<I4s", data, offset)
        chunks.setdefault(kind, data[offset + 8:offset + 8 + size])
        offset += 8 + size + (-size % 4)
    if b"JSON" not in chunks:
        raise InputError(f"{str(path)!r}: GLB without a JSON chunk")
    return chunks[b"JSON"], chunks.get(b"BIN\x00", b"")


def _buffer_bytes(document: pygltflib.GLTF2, buffer: pygltflib.Buffer, path: Path) -> bytes:
    if buffer.uri is None:
        return document.binary_blob() or b""
    return read_uri(buffer.uri, path)


def read_uri(uri: str, path: Path) -> bytes:
    """The bytes behind a buffer or image ``uri`` (data URI or a file beside ``path``)."""
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    from urllib.parse import unquote

    resource = path.parent / unquote(uri)
    if not resource.is_file():
        raise InputError(f"{str(path)!r} refers to a missing file {str(resource)!r}")
    return resource.read_bytes()


def read_accessor(document: pygltflib.GLTF2, buffers: list[bytes], index: int) -> np.ndarray:
    """Accessor ``index`` as a ``(count, n_components)`` float array (strides, sparse, normalized).

    Integer components (``BYTE``, ``UNSIGNED_BYTE``, ``SHORT``, ``UNSIGNED_SHORT``, as
    ``KHR_mesh_quantization`` stores positions and morph targets) are decoded as the spec says:
    normalized ones to ``value / max`` (signed clamped at -1), the others to their integer value.
    """
    accessor = document.accessors[index]
    dtype = np.dtype(COMPONENT_DTYPES[accessor.componentType]).newbyteorder("<")
    width = N_COMPONENTS[accessor.type]
    if accessor.bufferView is None:
        out = np.zeros((accessor.count, width))
    else:
        out = _read_view(document, buffers, accessor.bufferView, accessor.byteOffset or 0,
                         dtype, accessor.count, width)
    out = _dequantize(out, dtype) if accessor.normalized else out.astype(float)
    if accessor.sparse is not None:
        out = _apply_sparse(document, buffers, accessor, out, dtype, width)
    return out


def _read_view(document, buffers, view_index, offset, dtype, count, width) -> np.ndarray:
    """(count, width) elements of ``dtype`` from a buffer view, honouring ``byteStride``."""
    view = document.bufferViews[view_index]
    element = dtype.itemsize * width
    stride = view.byteStride or element
    if count == 0:
        return np.zeros((0, width), dtype)
    start = (view.byteOffset or 0) + offset
    raw = np.frombuffer(buffers[view.buffer], np.uint8, (count - 1) * stride + element, start)
    rows = np.lib.stride_tricks.as_strided(raw, shape=(count, element), strides=(stride, 1))
    return np.ascontiguousarray(rows).view(dtype).reshape(count, width)


def _dequantize(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """glTF normalized integers to floats (spec 3.6.2.3, 'Animations' 3.11; KHR_mesh_quantization):
    ``value / max``, at least -1 for signed types."""
    if dtype.kind == "f":
        return values.astype(float)
    scale = float(np.iinfo(dtype).max)
    return np.maximum(values.astype(float) / scale, -1.0)


def _apply_sparse(document, buffers, accessor, out, dtype, width) -> np.ndarray:
    sparse = accessor.sparse
    index_dtype = np.dtype(COMPONENT_DTYPES[sparse.indices.componentType]).newbyteorder("<")
    rows = _read_view(document, buffers, sparse.indices.bufferView, sparse.indices.byteOffset or 0,
                      index_dtype, sparse.count, 1)[:, 0].astype(np.int64)
    values = _read_view(document, buffers, sparse.values.bufferView, sparse.values.byteOffset or 0,
                        dtype, sparse.count, width)
    out = out.copy()
    out[rows] = _dequantize(values, dtype) if accessor.normalized else values
    return out


# --------------------------------------------------------------------------- rigs


def target_names(mesh: pygltflib.Mesh) -> list[str]:
    """Morph target names of a mesh: ``mesh.extras.targetNames`` (or, as some exporters write
    them, the first primitive's ``extras.targetNames``); empty when unnamed."""
    for extras in (mesh.extras, *(p.extras for p in mesh.primitives[:1])):
        names = (extras or {}).get("targetNames") if isinstance(extras, dict) else None
        if names:
            return [str(n) for n in names]
    return []


def morph_meshes(document: pygltflib.GLTF2, path) -> list[int]:
    """Indices of the meshes with morph targets, after checking each names all of them."""
    found = []
    for index, mesh in enumerate(document.meshes):
        counts = {len(p.targets) for p in mesh.primitives if p.targets}
        if not counts:
            continue
        names = target_names(mesh)
        if counts != {len(names)}:
            raise RigError(
                f"{str(path)!r}: mesh {index} ({mesh.name or 'unnamed'}) has {sorted(counts)} morph targets "
                f"but {len(names)} names in mesh.extras.targetNames; targets must be named to match keys"
            )
        found.append(index)
    return found


def read_parts(document, buffers, meshes, path) -> tuple[Rig, list[Part]]:
    """The primitives of ``meshes`` (indices) as one rig, and where each primitive sits in it.

    Target names are the union over the meshes (in order of first appearance); a primitive
    lacking a name contributes zero deltas for it. Vertices are in world space: each mesh's
    positions go through its :func:`mesh_matrices` entry ``M`` (``v' = L v + t``), its target
    deltas through the linear part ``L`` alone, and where ``det L < 0`` (a mirroring node)
    triangles are rewound so they still face outwards. Primitives share a block of vertices
    when they share their accessors *and* their transform.
    """
    _check_decodable(document, path)
    matrices = mesh_matrices(document)
    blocks, parts, faces, offset = {}, [], [], 0
    for m in meshes:
        mesh = document.meshes[m]
        names = target_names(mesh)
        matrix = matrices.get(m)
        for p, primitive in enumerate(mesh.primitives):
            key = (_block_key(primitive), None if matrix is None else matrix.tobytes())
            if key not in blocks:
                block = _read_block(document, buffers, primitive, names, path)
                blocks[key] = (offset, block if matrix is None else _to_world(block, matrix))
                offset += len(blocks[key][1][0])
            start, (vertices, _) = blocks[key]
            parts.append(Part(m, p, start, len(vertices)))
            tris = _read_faces(document, buffers, primitive, len(vertices), path)
            if matrix is not None and np.linalg.det(matrix[:3, :3]) < 0:
                tris = tris[:, [0, 2, 1]]
            faces.append(tris + start)
    return _assemble([b for _, b in blocks.values()], faces), parts


def part_colours(document, buffers, meshes, path) -> np.ndarray:
    """Base colours and opacity ``(n_vertices, 4)`` (RGBA in [0, 1]) of the vertices :func:`read_parts`
    returns, in its order.

    Each vertex takes its primitive's material: ``baseColorFactor``, times the base-colour texture
    sampled at the vertex's texture coordinates (nearest texel) where the image is PNG or JPEG,
    times ``COLOR_0`` where given. The alpha follows the material's ``alphaMode``: 1 when
    ``OPAQUE`` (the default), 0 or 1 against ``alphaCutoff`` when ``MASK``, as is when ``BLEND``.
    A primitive without a material is light grey, as the spec's default material is white.
    Shared vertex blocks take the first primitive's colours.
    """
    _check_decodable(document, path)
    matrices = mesh_matrices(document)
    seen, colours = set(), []
    for m in meshes:
        matrix = matrices.get(m)
        for primitive in document.meshes[m].primitives:
            key = (_block_key(primitive), None if matrix is None else matrix.tobytes())
            if key not in seen:
                seen.add(key)
                colours.append(_primitive_colours(document, buffers, primitive, path))
    return np.vstack(colours) if colours else np.zeros((0, 4))


def _primitive_colours(document, buffers, primitive, path) -> np.ndarray:
    n = read_accessor(document, buffers, primitive.attributes.POSITION).shape[0]
    if primitive.material is None:
        return np.tile([0.8, 0.8, 0.8, 1.0], (n, 1))
    material = document.materials[primitive.material]
    pbr = material.pbrMetallicRoughness
    factor = np.asarray(pbr.baseColorFactor if pbr and pbr.baseColorFactor else [1.0, 1.0, 1.0, 1.0], dtype=float)
    colours = np.tile(factor, (n, 1))
    texture = pbr.baseColorTexture if pbr else None
    if texture is not None:
        image = _texture_image(document, buffers, texture.index, path)
        uv_index = getattr(primitive.attributes, f"TEXCOORD_{texture.texCoord or 0}", None)
        if image is not None and uv_index is not None:
            uv = read_accessor(document, buffers, uv_index)
            height, width = image.shape[:2]
            column = np.clip((uv[:, 0] % 1.0 * width).astype(int), 0, width - 1)
            row = np.clip((uv[:, 1] % 1.0 * height).astype(int), 0, height - 1)
            colours = colours * image[row, column]
    if getattr(primitive.attributes, "COLOR_0", None) is not None:
        given = read_accessor(document, buffers, primitive.attributes.COLOR_0)
        colours = colours * (given if given.shape[1] == 4 else np.hstack([given, np.ones((n, 1))]))
    mode = material.alphaMode or "OPAQUE"
    if mode == "OPAQUE":
        colours[:, 3] = 1.0
    elif mode == "MASK":
        colours[:, 3] = colours[:, 3] >= (0.5 if material.alphaCutoff is None else material.alphaCutoff)
    return np.clip(colours, 0.0, 1.0)


def _texture_image(document, buffers, index, path) -> np.ndarray | None:
    """The texture's image ``(height, width, 4)`` RGBA in [0, 1], or None when it cannot be decoded here."""
    import io

    from PIL import Image, UnidentifiedImageError

    source = document.textures[index].source if index is not None and index < len(document.textures) else None
    if source is None:
        return None
    image = document.images[source]
    try:
        if image.bufferView is not None:
            view = document.bufferViews[image.bufferView]
            data = buffers[view.buffer][view.byteOffset or 0:(view.byteOffset or 0) + view.byteLength]
        elif image.uri:
            data = read_uri(image.uri, Path(path))
        else:
            return None
        with Image.open(io.BytesIO(bytes(data))) as picture:
            return np.asarray(picture.convert("RGBA"), dtype=float) / 255.0
    except (OSError, UnidentifiedImageError, InputError, RigError):
        return None  # a format Pillow does not read (KTX2, WebP without support): base colour only


def mesh_matrices(document) -> dict[int, np.ndarray]:
    """``{mesh: (4, 4) float}``: where each mesh sits in the world, for the meshes that move.

    A mesh is placed by the first node (lowest index) that shows it: that node's rest world
    transform, composed from its scene root down (each node's ``matrix`` or translation,
    rotation, scale). Meshes whose node transform is exactly the identity, that no node
    shows, or whose first node is **skinned** are left out (read as stored): the spec ignores a
    skinned mesh's node transform, and its vertices are in the skin's bind space, which
    exporters make the world at the bind pose (the joints' inverse bind matrices undo their
    bind-pose world transforms); skinning is not applied.
    """
    parent_of = parents(document)
    out = {}
    for index, node in enumerate(document.nodes):
        if node.mesh is None or node.mesh in out:
            continue
        matrix = None if node.skin is not None else world_matrix(document, index, parent_of)
        out[node.mesh] = matrix
    identity = np.eye(4)
    return {m: matrix for m, matrix in out.items() if matrix is not None and not np.array_equal(matrix, identity)}


def _to_world(block, matrix: np.ndarray):
    """A block's vertices ``(n, 3)`` through ``matrix (4, 4)``, its deltas through its linear part."""
    vertices, deltas = block
    linear = matrix[:3, :3]
    return vertices @ linear.T + matrix[:3, 3], {name: d @ linear.T for name, d in deltas.items()}


def _check_decodable(document, path) -> None:
    used = [e for e in (document.extensionsUsed or []) if e in _COMPRESSION]
    if used:
        raise RigError(f"{str(path)!r} uses {used}: compressed geometry cannot be read as a rig; "
                       "export it without compression")


def _block_key(primitive) -> tuple:
    targets = tuple((t or {}).get("POSITION") for t in (primitive.targets or []))
    return primitive.attributes.POSITION, targets


def _read_block(document, buffers, primitive, names, path):
    """Vertices ``(n, 3)`` and ``{name: delta (n, 3)}`` of one primitive."""
    if primitive.attributes.POSITION is None:
        raise RigError(f"{str(path)!r}: a mesh primitive has no POSITION attribute")
    vertices = read_accessor(document, buffers, primitive.attributes.POSITION)
    deltas = {}
    for name, target in zip(names, primitive.targets or []):
        index = (target or {}).get("POSITION")
        deltas[name] = read_accessor(document, buffers, index) if index is not None else np.zeros_like(vertices)
    return vertices, deltas


def _read_faces(document, buffers, primitive, n_vertices, path) -> np.ndarray:
    if primitive.indices is None:
        indices = np.arange(n_vertices)
    else:
        indices = read_accessor(document, buffers, primitive.indices)[:, 0].astype(np.int64)
    return triangles(indices, primitive.mode, path)


def triangles(indices: np.ndarray, mode, path="glTF") -> np.ndarray:
    """(n_faces, 3) triangles from a primitive's index list and its mode (4, 5 or 6)."""
    mode = pygltflib.TRIANGLES if mode is None else mode
    if mode == pygltflib.TRIANGLES:
        return indices[: len(indices) // 3 * 3].reshape(-1, 3)
    if mode == pygltflib.TRIANGLE_STRIP:
        tris = np.stack([indices[:-2], indices[1:-1], indices[2:]], axis=1)
        tris[1::2] = tris[1::2][:, [1, 0, 2]]  # keep the winding of odd triangles
        return tris
    if mode == pygltflib.TRIANGLE_FAN:
        return np.stack([np.full(len(indices) - 2, indices[0]), indices[1:-1], indices[2:]], axis=1)
    raise RigError(f"{str(path)!r}: a primitive has mode {mode} (points or lines); expected triangles")


def _assemble(blocks, faces) -> Rig:
    names = list(dict.fromkeys(name for _, deltas in blocks for name in deltas))
    vertices = np.concatenate([v for v, _ in blocks]) if blocks else np.zeros((0, 3))
    deltas = np.stack([
        np.concatenate([d.get(name, np.zeros_like(v)) for v, d in blocks]) for name in names
    ]) if names else np.zeros((0, *vertices.shape))
    return Rig(vertices, np.concatenate(faces) if faces else np.zeros((0, 3), int), deltas, tuple(names))


def read_rig(path) -> Rig:
    """Load the morph-target meshes of a glTF file as one :class:`Rig`.

    Every primitive of every mesh that has morph targets is kept and their vertices are
    concatenated, faces offset (primitives sharing a vertex buffer share their vertices).
    Target names come from each mesh's ``extras.targetNames``; a mesh lacking one of the union
    of names contributes zero deltas for it. Vertices are in **world space** (glTF: metres,
    +Y up), as a viewer shows the file at rest: each mesh's positions go through the rest world
    transform of the first node that shows it (its ancestors' and its own translation,
    rotation, scale or ``matrix``), its target deltas through that transform's linear part
    (morph targets act before the node transform, so a delta is a direction). Skinned meshes
    are read as stored (their bind space; the spec ignores their node transform and skinning is
    not applied). Quantized geometry (``KHR_mesh_quantization``) is decoded, the node transform
    supplying its scale. Meshes without morph targets (body, props) are ignored.

    Parameters
    ----------
    path : str or Path
        ``.glb`` or ``.gltf`` (external, embedded or GLB-stored buffers).

    Returns
    -------
    Rig

    Raises
    ------
    RigError
        If no mesh has morph targets, a mesh with targets does not name them, or its
        geometry is compressed.
    """
    document, buffers = load_document(path, editable=False)
    meshes = morph_meshes(document, path)
    if not meshes:
        raise RigError(f"{str(path)!r} has no morph targets: it cannot be driven as a blendshape rig")
    return read_parts(document, buffers, meshes, path)[0]


# --------------------------------------------------------------------------- animations


def read_glb_animation(path, *, animation: str | int | None = None) -> GlbAnimation:
    """Read back a morph-weight animation of a glTF file.

    Parameters
    ----------
    path : str or Path
        A ``.glb`` or ``.gltf`` file, such as one written by :func:`keyshape.io.gltf.write_glb`
        or :func:`keyshape.io.gltf.animate_gltf`.
    animation : str or int, optional, keyword-only
        Which animation (name or index). Default: one named ``keyshape`` or ``performance``,
        else the first with a ``weights`` channel.

    Returns
    -------
    GlbAnimation
        Weights of every mesh the animation drives, by target name; ``rotations`` of its first
        ``rotation`` channel.

    Raises
    ------
    InputError
        If the file has no such animation, or none with a ``weights`` channel.
    """
    document, buffers = load_document(path, editable=False)
    chosen = choose_animation(document, animation, path)
    return _read_animation(document, buffers, chosen)


def choose_animation(document, animation, path):
    animations = document.animations
    if isinstance(animation, int):
        if not 0 <= animation < len(animations):
            raise InputError(f"{str(path)!r} has {len(animations)} animations; no index {animation}")
        return animations[animation]
    with_weights = [a for a in animations if any(c.target.path == "weights" for c in a.channels)]
    if animation is not None:
        named = [a for a in with_weights if a.name == animation]
        if not named:
            raise InputError(f"{str(path)!r} has no animation {animation!r} with a 'weights' channel; "
                             f"it has {[a.name for a in with_weights]}")
        return named[0]
    if not with_weights:
        raise InputError(f"{str(path)!r} has no animation with a 'weights' channel")
    ours = [a for name in ANIMATION_NAMES for a in with_weights if a.name == name]
    return (ours or with_weights)[0]


def _read_animation(document, buffers, animation) -> GlbAnimation:
    columns, times = {}, None
    for channel in animation.channels:
        if channel.target.path != "weights":
            continue
        sampler = animation.samplers[channel.sampler]
        times = read_accessor(document, buffers, sampler.input)[:, 0] if times is None else times
        values = read_accessor(document, buffers, sampler.output).reshape(len(times), -1)
        names = target_names(document.meshes[document.nodes[channel.target.node].mesh])
        for k, name in enumerate(names):
            columns.setdefault(name, values[:, k])
    names = tuple(columns)
    weights = np.stack([columns[n] for n in names], axis=1) if names else np.zeros((len(times), 0))
    rotation = [c for c in animation.channels if c.target.path == "rotation"]
    rotations = None
    if rotation:
        rotations = read_accessor(document, buffers, animation.samplers[rotation[0].sampler].output)
    return GlbAnimation(names, times, weights, rotations)
