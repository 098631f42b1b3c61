"""Building and editing glTF documents (private half of :mod:`keyshape.io.gltf`).

:class:`Blob` appends accessors to one binary buffer, starting from nothing (a new file) or
from an existing file's data (:func:`pack` first gathers every buffer and external image of
the original into that one buffer, so the result is a self-contained ``.glb``). The rest
finds and animates a character's head node and tidies what the Khronos validator warns about.

Rotations: a head rotation ``D`` is given in the file's world frame (glTF: +Y up, the
character facing +Z). On a node whose parent has the rest world rotation ``P`` and whose own
rest rotation is ``R``, the local rotation that turns the head by ``D`` about its pivot is
``Pᵀ D P R`` (then its world rotation is ``D P R``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from ..exceptions import RigError
from ._gltf_read import COMPONENT_DTYPES, read_uri

_HEAD = re.compile(r"head", re.IGNORECASE)
_NOT_HEAD = re.compile(r"end|top|nub|null|tip|_ik|target", re.IGNORECASE)
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


def parents(document: pygltflib.GLTF2) -> dict[int, int]:
    """``{child: parent}`` node indices."""
    return {child: index for index, node in enumerate(document.nodes) for child in (node.children or [])}


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


# --------------------------------------------------------------------------- the head


def find_head(document: pygltflib.GLTF2, face_nodes: list[int], *, name: str | None = None) -> int | None:
    """The node to turn with the head: named ``name``, else found near the face meshes.

    Preference: for skinned face meshes, the skin joint named like ``head`` closest to the root;
    otherwise the nearest ancestor (or self) of every face node named like ``head``, joints
    first; otherwise a single unskinned face node itself. None when there is no such node.
    """
    if name is not None:
        found = [i for i, node in enumerate(document.nodes) if node.name == name]
        if not found:
            raise RigError(f"no node named {name!r} to carry the head rotation; nodes: "
                           f"{sorted({n.name for n in document.nodes if n.name})[:40]}")
        return found[0]
    parent_of = parents(document)
    joints = {j for skin in document.skins for j in skin.joints}
    skinned = [n for n in face_nodes if document.nodes[n].skin is not None]
    if skinned:
        return _head_joint(document, skinned, parent_of)
    common = _common_ancestors(face_nodes, parent_of)
    heads = [n for n in common if _is_head(document.nodes[n].name)]
    ranked = [n for n in heads if n in joints] + [n for n in heads if n not in joints]
    if ranked:
        return ranked[0]
    return face_nodes[0] if len(face_nodes) == 1 else None


def find_eyes(document: pygltflib.GLTF2, head: int | None, *, names: tuple[str, str] | None = None
              ) -> tuple[int, int] | None:
    """The (left, right) eye nodes: named ``names``, else found by name below ``head`` (or anywhere).

    A node is an eye when its name has ``eye`` (not lid, lash, brow, socket or an end bone) and a
    side: ``left``/``right`` or a separate ``l``/``r`` (``Eye_L``, ``eye.R``, ``LeftEye``). Left is
    the character's own left. Joints are preferred, then shorter names. None when either is missing.
    """
    if names is not None:
        found = [next((i for i, n in enumerate(document.nodes) if n.name == name), None) for name in names]
        if None in found:
            raise RigError(f"no eye nodes named {list(names)}; nodes: {sorted({n.name for n in document.nodes if n.name})[:40]}")
        return found[0], found[1]
    pool = _descendants(document, head) if head is not None else range(len(document.nodes))
    joints = {j for skin in document.skins for j in skin.joints}
    sides = []
    for side in ("left", "right"):
        nodes = [n for n in pool if _is_eye(document.nodes[n].name, side)]
        sides.append(min(nodes, key=lambda n: (n not in joints, len(document.nodes[n].name), n)) if nodes else None)
    return None if None in sides else (sides[0], sides[1])


_EYE = re.compile(r"eye", re.IGNORECASE)
_NOT_EYE = re.compile(r"lid|lash|brow|socket|end|top|nub|null|target|look", re.IGNORECASE)


def _is_eye(name, side: str) -> bool:
    if not name or not _EYE.search(name) or _NOT_EYE.search(name):
        return False
    lowered = name.lower()
    other = "right" if side == "left" else "left"
    letter = re.search(rf"(^|[._\-\s:]){side[0]}($|[._\-\s:])", lowered)
    return (side in lowered or bool(letter)) and other not in lowered


def _descendants(document, node: int) -> list[int]:
    out, stack = [], [node]
    while stack:
        current = stack.pop()
        out.append(current)
        stack.extend(document.nodes[current].children or [])
    return out


def _is_head(name) -> bool:
    return bool(name) and bool(_HEAD.search(name)) and not _NOT_HEAD.search(name)


def _head_joint(document, skinned, parent_of) -> int | None:
    joints = {j for n in skinned for j in document.skins[document.nodes[n].skin].joints}
    heads = [j for j in joints if _is_head(document.nodes[j].name)]
    return min(heads, key=lambda j: (_depth(j, parent_of), j)) if heads else None


def _depth(node: int, parent_of: dict[int, int]) -> int:
    depth = 0
    while node in parent_of:
        node, depth = parent_of[node], depth + 1
    return depth


def _ancestry(node: int, parent_of: dict[int, int]) -> list[int]:
    chain = [node]
    while chain[-1] in parent_of:
        chain.append(parent_of[chain[-1]])
    return chain


def _common_ancestors(nodes: list[int], parent_of: dict[int, int]) -> list[int]:
    """Ancestors-or-self shared by every node, nearest first."""
    chains = [_ancestry(n, parent_of) for n in nodes]
    shared = set(chains[0]).intersection(*chains[1:])
    return [n for n in chains[0] if n in shared]


def local_matrix(node: pygltflib.Node) -> np.ndarray:
    """(4, 4) float: the node's rest transform (``matrix`` or T·R·S)."""
    if node.matrix is not None:
        return np.asarray(node.matrix, dtype=float).reshape(4, 4).T  # glTF is column-major
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat(node.rotation or [0, 0, 0, 1]).as_matrix() * (node.scale or [1, 1, 1])
    out[:3, 3] = node.translation or [0, 0, 0]
    return out


def world_rotation(document: pygltflib.GLTF2, node: int | None) -> np.ndarray:
    """(3, 3) float: the rotation part of a node's rest world transform (identity for None)."""
    parent_of = parents(document)
    matrix = np.eye(4)
    chain = [] if node is None else _ancestry(node, parent_of)
    for index in reversed(chain):
        matrix = matrix @ local_matrix(document.nodes[index])
    return _rotation_part(matrix[:3, :3])


def _rotation_part(linear: np.ndarray) -> np.ndarray:
    """Nearest rotation (polar decomposition; Higham 1986) of a 3 × 3 matrix."""
    u, _, vt = np.linalg.svd(linear)
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:
        rotation = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return rotation


def as_trs(node: pygltflib.Node) -> None:
    """Replace a node's ``matrix`` by translation/rotation/scale (animated nodes must use TRS)."""
    if node.matrix is None:
        return
    matrix = local_matrix(node)
    scale = np.linalg.norm(matrix[:3, :3], axis=0)
    node.translation = matrix[:3, 3].tolist()
    node.rotation = Rotation.from_matrix(_rotation_part(matrix[:3, :3])).as_quat().tolist()
    node.scale = scale.tolist()
    node.matrix = None


def head_local_rotations(document: pygltflib.GLTF2, head: int, deltas: np.ndarray) -> np.ndarray:
    """(n_frames, 4) quaternions (x, y, z, w): a node's (head's, an eye's) local rotation per frame.

    ``deltas (n_frames, 3, 3)`` are head rotations in the world frame; the result is
    ``Pᵀ D P R`` (module docstring), sign-continuous for LINEAR interpolation.
    """
    parent = parents(document).get(head)
    p = world_rotation(document, parent)
    rest = Rotation.from_quat(document.nodes[head].rotation or [0, 0, 0, 1]).as_matrix()
    # f: frame; P^T D_f P R, written as one einsum over the frames
    local = np.einsum("ji,fjk,kl,lm->fim", p, deltas, p, rest)
    return continuous_hemisphere(Rotation.from_matrix(local).as_quat())


def continuous_hemisphere(quats: np.ndarray) -> np.ndarray:
    """Flip signs so consecutive quaternions are in one hemisphere (shortest LINEAR slerp)."""
    out = quats.copy()
    for i in range(1, len(out)):
        if np.dot(out[i], out[i - 1]) < 0:
            out[i] = -out[i]
    return out


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
    accessors = _reindex_accessors(document)
    views = _reindex_views(document)
    if accessors or views:
        _rebuild_blob(document, views)


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


def _reindex_accessors(document) -> bool:
    slots = list(_accessor_slots(document))
    used = sorted({_get(s) for s in slots})
    if len(used) == len(document.accessors):
        return False
    new = {old: k for k, old in enumerate(used)}
    for slot in slots:
        _set(slot, new[_get(slot)])
    document.accessors = [document.accessors[i] for i in used]
    return True


def _view_slots(document):
    for accessor in document.accessors:
        if accessor.bufferView is not None:
            yield accessor, "bufferView", False
        if accessor.sparse is not None:
            yield accessor.sparse.indices, "bufferView", False
            yield accessor.sparse.values, "bufferView", False
    for image in document.images:
        if image.bufferView is not None:
            yield image, "bufferView", False


def _reindex_views(document) -> dict[int, int] | None:
    slots = list(_view_slots(document))
    used = sorted({_get(s) for s in slots})
    if len(used) == len(document.bufferViews):
        return None
    new = {old: k for k, old in enumerate(used)}
    for slot in slots:
        _set(slot, new[_get(slot)])
    kept = [document.bufferViews[i] for i in used]
    document.bufferViews = kept
    return new


def _rebuild_blob(document, views) -> None:
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
