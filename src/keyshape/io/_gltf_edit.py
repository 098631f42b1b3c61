"""Building and editing glTF documents (private half of :mod:`keyshape.io.gltf`).

:class:`Blob` appends accessors to one binary buffer, starting from nothing (a new file) or
from an existing file's data (:func:`pack` first gathers every buffer and external image of
the original into that one buffer, so the result is a self-contained ``.glb``). The rest
tidies an original file: skinned meshes moved to the scene root, animations or channels
dropped, and what nothing refers to any more pruned (:func:`prune`), as the Khronos validator
asks. Finding and turning the head and eye nodes is in :mod:`keyshape.io._gltf_nodes`
(its functions are re-exported here).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pygltflib

from ._gltf_nodes import (
    as_trs,
    continuous_hemisphere,
    find_eyes,
    find_head,
    head_local_rotations,
    local_matrix,
    parents,
    world_rotation,
)
from ._gltf_read import COMPONENT_DTYPES, read_uri

__all__ = ["Blob", "SPARSE_BELOW", "component_type", "json_number", "pack", "root_skinned_meshes",
           "morph_nodes", "drop_weight_channels", "drop_animations", "prune",
           # from _gltf_nodes
           "parents", "find_head", "find_eyes", "local_matrix", "world_rotation", "as_trs",
           "head_local_rotations", "continuous_hemisphere"]

_MIME = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".webp": "image/webp",
         ".ktx2": "image/ktx2"}
# Store a target sparsely when fewer than this fraction of its vertices move
# (16 bytes per moved vertex instead of 12 per vertex).
SPARSE_BELOW = 0.7


def _padded(data: bytes) -> bytes:
    return data + b"\0" * ((-len(data)) % 4)


def component_type(dtype) -> int:
    return {np.dtype(v): k for k, v in COMPONENT_DTYPES.items()}[np.dtype(dtype)]


def json_number(value):
    return int(value) if np.issubdtype(type(value), np.integer) else float(value)


class Blob:
    """Accumulates buffer views and accessors in the one binary buffer of a document.

    Parameters
    ----------
    document : pygltflib.GLTF2
    initial : bytes
        Data already in buffer 0 (views keep their offsets); empty for a new file.
    """

    def __init__(self, document: pygltflib.GLTF2, initial: bytes = b""):
        self.document = document
        self.chunks: list[bytes] = [_padded(initial)]
        self.length = len(self.chunks[0])

    def view(self, data: bytes, *, target=None) -> int:
        """Append ``data`` as a buffer view; return its index."""
        self.document.bufferViews.append(
            pygltflib.BufferView(buffer=0, byteOffset=self.length, byteLength=len(data), target=target))
        self.chunks.append(_padded(data))
        self.length += len(self.chunks[-1])
        return len(self.document.bufferViews) - 1

    def add(self, array: np.ndarray, accessor_type: str, *, target=None, bounds=False) -> int:
        """Append ``array`` (n, ...) as a tightly packed accessor; return its index."""
        array = np.ascontiguousarray(array)
        view = self.view(array.tobytes(), target=target)
        return self._accessor(array, accessor_type, bufferView=view, bounds=bounds)

    def add_target(self, delta: np.ndarray) -> int:
        """A morph-target ``POSITION`` accessor for ``delta (n_vertices, 3)``: sparse when few move."""
        delta = np.ascontiguousarray(delta, dtype=np.float32)
        moved = np.flatnonzero(np.any(delta != 0, axis=1))
        if not 0 < len(moved) < SPARSE_BELOW * len(delta):
            return self.add(delta, "VEC3", target=pygltflib.ARRAY_BUFFER, bounds=True)
        index_dtype = np.uint16 if len(delta) <= 65535 else np.uint32
        sparse = pygltflib.Sparse(
            count=len(moved),
            indices=pygltflib.AccessorSparseIndices(
                bufferView=self.view(moved.astype(index_dtype).tobytes()), byteOffset=0,
                componentType=component_type(index_dtype)),
            values=pygltflib.AccessorSparseValues(bufferView=self.view(delta[moved].tobytes()), byteOffset=0),
        )
        return self._accessor(delta, "VEC3", bufferView=None, bounds=True, sparse=sparse)

    def _accessor(self, array, accessor_type, *, bufferView, bounds, sparse=None) -> int:
        accessor = pygltflib.Accessor(bufferView=bufferView, componentType=component_type(array.dtype),
                                      count=int(array.shape[0]), type=accessor_type, sparse=sparse)
        if bufferView is None:
            accessor.byteOffset = None
        if bounds:
            flat = array.reshape(array.shape[0], -1)
            accessor.min = [json_number(v) for v in flat.min(axis=0)]
            accessor.max = [json_number(v) for v in flat.max(axis=0)]
        self.document.accessors.append(accessor)
        return len(self.document.accessors) - 1

    def finish(self) -> None:
        """Make the accumulated data the document's one (GLB-stored) buffer."""
        blob = b"".join(self.chunks)
        self.document.buffers = [pygltflib.Buffer(byteLength=len(blob))]
        self.document.set_binary_blob(blob)


# --------------------------------------------------------------------------- original files


def pack(document: pygltflib.GLTF2, buffers: list[bytes], path: Path) -> Blob:
    """Gather every buffer and external image of ``document`` into one :class:`Blob`."""
    data, offsets = b"", []
    for chunk in buffers:
        data = _padded(data)
        offsets.append(len(data))
        data += chunk
    for view in document.bufferViews:
        view.byteOffset = (view.byteOffset or 0) + offsets[view.buffer]
        view.buffer = 0
    for accessor in document.accessors:
        if accessor.bufferView is None:  # pygltflib reads a missing byteOffset as 0; glTF forbids it here
            accessor.byteOffset = None
    blob = Blob(document, data)
    for image in document.images:
        if image.uri is not None:
            image.mimeType = image.mimeType or _mime(image.uri)
            image.bufferView = blob.view(read_uri(image.uri, path))
            image.uri = None
    return blob


def _mime(uri: str) -> str:
    if uri.startswith("data:"):
        return uri[5:].split(";", 1)[0].split(",", 1)[0]
    return _MIME.get(Path(uri).suffix.lower(), "image/png")


def root_skinned_meshes(document: pygltflib.GLTF2) -> None:
    """Move skinned-mesh nodes to the scene roots (validator: NODE_SKINNED_MESH_NON_ROOT).

    The spec already ignores a skinned mesh's parent transforms (and its own), so the
    character looks the same; the joints still come from the skin.
    """
    parent_of = parents(document)
    for index, node in enumerate(document.nodes):
        if node.skin is None or node.mesh is None or index not in parent_of:
            continue
        root = _root(index, parent_of)
        document.nodes[parent_of[index]].children.remove(index)
        for scene in document.scenes:
            if root in (scene.nodes or []):
                scene.nodes.append(index)
        del parent_of[index]


def _root(node: int, parent_of: dict[int, int]) -> int:
    while node in parent_of:
        node = parent_of[node]
    return node


def morph_nodes(document: pygltflib.GLTF2, meshes: list[int]) -> list[int]:
    """Nodes that instance one of ``meshes``."""
    return [i for i, node in enumerate(document.nodes) if node.mesh in meshes]


def drop_weight_channels(document: pygltflib.GLTF2, nodes: list[int]) -> None:
    """Remove ``weights`` channels targeting ``nodes`` (their meshes' targets changed)."""
    for animation in document.animations:
        animation.channels = [c for c in animation.channels
                              if not (c.target.path == "weights" and c.target.node in nodes)]
    document.animations = [a for a in document.animations if a.channels]
    for animation in document.animations:
        _reindex_samplers(animation)


def drop_animations(document: pygltflib.GLTF2, names) -> None:
    """Remove animations called one of ``names`` (an earlier keyshape take in this file)."""
    document.animations = [a for a in document.animations if a.name not in names]


def _reindex_samplers(animation: pygltflib.Animation) -> None:
    used = sorted({c.sampler for c in animation.channels})
    new = {old: k for k, old in enumerate(used)}
    animation.samplers = [animation.samplers[i] for i in used]
    for channel in animation.channels:
        channel.sampler = new[channel.sampler]


# --------------------------------------------------------------------------- pruning

# Extensions that reference no accessors or buffer views outside the core fields we reindex.
_SAFE_EXTENSIONS = re.compile(r"^(KHR_materials_\w+|KHR_texture_transform|KHR_lights_punctual|"
                              r"KHR_mesh_quantization|KHR_materials_variants|KHR_texture_basisu|"
                              r"EXT_texture_webp|KHR_animation_pointer)$")


def prune(document: pygltflib.GLTF2) -> None:
    """Drop accessors and buffer views nothing refers to (replaced targets, dropped channels).

    Only when every extension the file uses is known not to refer to accessors or views
    itself; otherwise the file is left as it is (unused data is harmless).
    """
    if any(not _SAFE_EXTENSIONS.match(e) for e in document.extensionsUsed or []):
        return
    accessors = _drop_unused(_accessor_slots(document), document.accessors)
    if accessors is not None:
        document.accessors = accessors
    views = _drop_unused(_view_slots(document), document.bufferViews)
    if views is not None:
        document.bufferViews = views
    if accessors is not None or views is not None:
        _rebuild_blob(document)


def _accessor_slots(document):
    """(object, attribute or key, is_dict) for every core reference to an accessor."""
    for mesh in document.meshes:
        for primitive in mesh.primitives:
            yield from ((primitive.attributes, k, False) for k, v in vars(primitive.attributes).items()
                        if isinstance(v, int))
            if primitive.indices is not None:
                yield primitive, "indices", False
            for target in primitive.targets or []:
                yield from ((target, k, True) for k, v in target.items() if isinstance(v, int))
    for skin in document.skins:
        if skin.inverseBindMatrices is not None:
            yield skin, "inverseBindMatrices", False
    for animation in document.animations:
        for sampler in animation.samplers:
            yield sampler, "input", False
            yield sampler, "output", False


def _get(slot):
    owner, key, is_dict = slot
    return owner[key] if is_dict else getattr(owner, key)


def _set(slot, value) -> None:
    owner, key, is_dict = slot
    if is_dict:
        owner[key] = value
    else:
        setattr(owner, key, value)


def _drop_unused(slots, items: list) -> list | None:
    """The ``items`` some slot refers to, the slots renumbered to match; None if every item is used."""
    slots = list(slots)
    used = sorted({_get(s) for s in slots})
    if len(used) == len(items):
        return None
    new = {old: k for k, old in enumerate(used)}
    for slot in slots:
        _set(slot, new[_get(slot)])
    return [items[i] for i in used]


def _view_slots(document):
    """(object, attribute, is_dict) for every reference to a buffer view."""
    for accessor in document.accessors:
        if accessor.bufferView is not None:
            yield accessor, "bufferView", False
        if accessor.sparse is not None:
            yield accessor.sparse.indices, "bufferView", False
            yield accessor.sparse.values, "bufferView", False
    for image in document.images:
        if image.bufferView is not None:
            yield image, "bufferView", False


def _rebuild_blob(document) -> None:
    """Copy the kept views' bytes into a fresh blob (4-byte aligned) and fix their offsets."""
    old = document.binary_blob() or b""
    chunks, length = [], 0
    for view in document.bufferViews:
        data = old[view.byteOffset or 0:(view.byteOffset or 0) + view.byteLength]
        view.byteOffset, view.buffer = length, 0
        chunks.append(_padded(data))
        length += len(chunks[-1])
    blob = b"".join(chunks)
    document.buffers = [pygltflib.Buffer(byteLength=len(blob))]
    document.set_binary_blob(blob)
