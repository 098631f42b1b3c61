"""glTF 2.0: morph-target rigs in, morph-weight (and head-rotation) animation out.

Writing produces one binary ``.glb`` holding a single mesh whose morph targets are the
rig's deltas, named in ``mesh.extras.targetNames`` (the de-facto convention read by
three.js, Babylon.js and Blender), one node ``"face"`` holding it, and one animation:
a ``weights`` channel sampled at ``frame / fps`` with LINEAR interpolation, plus an
optional ``rotation`` channel for the head.

Coordinates follow glTF: metres, +Y up, +Z toward the viewer. Image-space rotations
(x right, y down, z away from the camera) are converted with ``C = diag(1, -1, -1)``:
``R_gltf = C R C``.

References
----------
The Khronos Group, *glTF 2.0 Specification*, sections 3.7.2.2 (morph targets) and
3.11 (animations).
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from ..containers import Poses, Rig, Weights
from ..exceptions import InputError, RigError
from .atomic import atomic_path

__all__ = ["write_glb", "read_glb_animation", "read_rig", "GlbAnimation"]

_FLOAT = pygltflib.FLOAT
_COMPONENT_DTYPES = {
    pygltflib.BYTE: np.int8,
    pygltflib.UNSIGNED_BYTE: np.uint8,
    pygltflib.SHORT: np.int16,
    pygltflib.UNSIGNED_SHORT: np.uint16,
    pygltflib.UNSIGNED_INT: np.uint32,
    pygltflib.FLOAT: np.float32,
}
_N_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_IMAGE_TO_GLTF = np.diag([1.0, -1.0, -1.0])  # C: image (x right, y down, z away) <-> glTF


class GlbAnimation(NamedTuple):
    """The animation stored in a ``.glb`` written by :func:`write_glb`.

    Attributes
    ----------
    names : tuple of n_targets str
    times : (n_frames,) float, seconds
    weights : (n_frames, n_targets) float
    rotations : (n_frames, 4) float unit quaternions (x, y, z, w) in glTF axes, or None
    """

    names: tuple[str, ...]
    times: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray | None


# --------------------------------------------------------------------------- writing


def write_glb(path, rig: Rig, weights: Weights, *, poses: Poses | None = None) -> Path:
    """Write a rig and its weight animation as a binary glTF 2.0 file, atomically.

    Parameters
    ----------
    path : str or Path
        Output file; must end in ``.glb``. Written to a temporary file in the same
        folder and moved into place, so a failure leaves no partial file.
    rig : Rig
        Neutral mesh and target deltas (written as they are: glTF metres, +Y up).
    weights : Weights
        ``values (n_frames, n_targets)`` named exactly ``rig.names``, in that order
        (use :func:`keyshape.retarget.retarget` first). NaN frames are written as 0.
    poses : Poses, optional
        Head pose per frame in image convention (2D or 3D rotations, ``n_frames`` as
        ``weights``); written as a ``rotation`` channel on the node. NaN frames hold the
        previous valid rotation (leading ones take the first valid; none at all: identity).

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
    _check_write_args(path, rig, weights, poses)
    rotations = None if poses is None else _pose_quaternions(poses)
    document = _build_document(rig, weights, rotations)
    data = b"".join(document.save_to_bytes())
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def _check_write_args(path: Path, rig: Rig, weights: Weights, poses: Poses | None) -> None:
    if path.suffix.lower() != ".glb":
        raise InputError(f"write_glb writes binary glTF: the path must end in .glb; got {str(path)!r}")
    if tuple(weights.names) != tuple(rig.names):
        missing = [n for n in rig.names if n not in weights.names]
        extra = [n for n in weights.names if n not in rig.names]
        raise RigError(
            f"weights must be named by the rig's targets, in rig order {list(rig.names)}; "
            f"got {list(weights.names)} (missing {missing}, extra {extra}); retarget them first"
        )
    if rig.n_targets == 0:
        raise RigError("the rig has no morph targets to animate")
    if poses is not None and poses.n_frames != weights.n_frames:
        raise InputError(
            f"poses must have one frame per weights frame ({weights.n_frames}); got {poses.n_frames}"
        )


def _pose_quaternions(poses: Poses) -> np.ndarray:
    """Unit quaternions ``(n_frames, 4)`` (x, y, z, w) in glTF axes from image-space rotations."""
    rot = _as_3d(np.asarray(poses.rotations, dtype=float))
    rot = _fill_invalid(rot)
    rot = _IMAGE_TO_GLTF @ rot @ _IMAGE_TO_GLTF  # R_gltf = C R C (C is its own inverse)
    quats = Rotation.from_matrix(rot).as_quat() if len(rot) else np.zeros((0, 4))
    return _continuous_hemisphere(quats)


def _as_3d(rotations: np.ndarray) -> np.ndarray:
    """(n_frames, 3, 3): a 2D rotation is a rotation about the image z axis."""
    if rotations.shape[1] == 3:
        return rotations
    out = np.tile(np.eye(3), (len(rotations), 1, 1))
    out[:, :2, :2] = rotations
    return out


def _fill_invalid(rotations: np.ndarray) -> np.ndarray:
    """Hold the previous valid rotation over NaN frames; back-fill leading ones; else identity."""
    valid = np.isfinite(rotations).all(axis=(1, 2))
    if not valid.any():
        return np.tile(np.eye(3), (len(rotations), 1, 1))
    source = np.maximum.accumulate(np.where(valid, np.arange(len(valid)), -1))
    source[source < 0] = np.flatnonzero(valid)[0]
    return rotations[source]


def _continuous_hemisphere(quats: np.ndarray) -> np.ndarray:
    """Flip signs so consecutive quaternions are in one hemisphere (shortest LINEAR slerp)."""
    out = quats.copy()
    for i in range(1, len(out)):
        if np.dot(out[i], out[i - 1]) < 0:
            out[i] = -out[i]
    return out


class _Blob:
    """Accumulates buffer views and accessors in one binary buffer."""

    def __init__(self, document: pygltflib.GLTF2):
        self.document = document
        self.chunks: list[bytes] = []
        self.length = 0

    def add(self, array: np.ndarray, accessor_type: str, *, target=None, bounds=False) -> int:
        """Append ``array`` as a tightly packed view and return its accessor index."""
        data = np.ascontiguousarray(array).tobytes()
        self.document.bufferViews.append(
            pygltflib.BufferView(buffer=0, byteOffset=self.length, byteLength=len(data), target=target)
        )
        pad = (-len(data)) % 4
        self.chunks.append(data + b"\0" * pad)
        self.length += len(data) + pad
        accessor = pygltflib.Accessor(
            bufferView=len(self.document.bufferViews) - 1,
            componentType=_component_type(array.dtype),
            count=int(array.shape[0]),
            type=accessor_type,
        )
        if bounds:
            flat = array.reshape(array.shape[0], -1)
            accessor.min = [_json_number(v) for v in flat.min(axis=0)]
            accessor.max = [_json_number(v) for v in flat.max(axis=0)]
        self.document.accessors.append(accessor)
        return len(self.document.accessors) - 1

    def finish(self) -> None:
        blob = b"".join(self.chunks)
        self.document.buffers.append(pygltflib.Buffer(byteLength=len(blob)))
        self.document.set_binary_blob(blob)


def _component_type(dtype) -> int:
    return {np.dtype(v): k for k, v in _COMPONENT_DTYPES.items()}[np.dtype(dtype)]


def _json_number(value):
    return int(value) if np.issubdtype(type(value), np.integer) else float(value)


def _build_document(rig: Rig, weights: Weights, rotations: np.ndarray | None) -> pygltflib.GLTF2:
    document = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="keyshape"),
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(name="face", mesh=0)],
    )
    blob = _Blob(document)
    document.meshes.append(_mesh(blob, rig))
    document.materials.append(
        pygltflib.Material(
            name="face",
            pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorFactor=[0.8, 0.8, 0.8, 1.0], metallicFactor=0.0, roughnessFactor=0.7
            ),
            doubleSided=True,
        )
    )
    if weights.n_frames:
        document.animations.append(_animation(blob, weights, rotations))
    blob.finish()
    return document


def _mesh(blob: _Blob, rig: Rig) -> pygltflib.Mesh:
    array_buffer, element_buffer = pygltflib.ARRAY_BUFFER, pygltflib.ELEMENT_ARRAY_BUFFER
    position = blob.add(rig.vertices.astype(np.float32), "VEC3", target=array_buffer, bounds=True)
    index_dtype = np.uint16 if rig.n_vertices < 65535 else np.uint32
    indices = blob.add(rig.faces.reshape(-1).astype(index_dtype), "SCALAR", target=element_buffer)
    targets = [
        {"POSITION": blob.add(delta.astype(np.float32), "VEC3", target=array_buffer, bounds=True)}
        for delta in rig.deltas
    ]
    primitive = pygltflib.Primitive(
        attributes=pygltflib.Attributes(POSITION=position), indices=indices, material=0, targets=targets
    )
    return pygltflib.Mesh(
        name="face",
        primitives=[primitive],
        weights=[0.0] * rig.n_targets,
        extras={"targetNames": list(rig.names)},
    )


def _animation(blob: _Blob, weights: Weights, rotations: np.ndarray | None) -> pygltflib.Animation:
    times = blob.add(weights.times.astype(np.float32), "SCALAR", bounds=True)
    values = np.nan_to_num(weights.values, nan=0.0).astype(np.float32)
    # glTF morph-weight output: n_frames · n_targets scalars, frame-major.
    output = blob.add(values.reshape(-1), "SCALAR")
    samplers = [pygltflib.AnimationSampler(input=times, output=output, interpolation="LINEAR")]
    channels = [pygltflib.AnimationChannel(sampler=0, target=_target("weights"))]
    if rotations is not None:
        quats = blob.add(rotations.astype(np.float32), "VEC4")
        samplers.append(pygltflib.AnimationSampler(input=times, output=quats, interpolation="LINEAR"))
        channels.append(pygltflib.AnimationChannel(sampler=1, target=_target("rotation")))
    return pygltflib.Animation(name="performance", samplers=samplers, channels=channels)


def _target(path: str) -> pygltflib.AnimationChannelTarget:
    return pygltflib.AnimationChannelTarget(node=0, path=path)


# --------------------------------------------------------------------------- reading


def _load(path) -> tuple[pygltflib.GLTF2, list[bytes]]:
    """The glTF document at ``path`` and the bytes of each of its buffers."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such glTF file: {str(path)!r}")
    try:
        document = pygltflib.GLTF2().load(str(path))
    except Exception as error:  # pygltflib raises bare exceptions on malformed input
        raise InputError(f"cannot read {str(path)!r} as glTF: {error}") from error
    if document is None:
        raise InputError(f"cannot read {str(path)!r} as glTF")
    return document, [_buffer_bytes(document, buffer, path) for buffer in document.buffers]


def _buffer_bytes(document: pygltflib.GLTF2, buffer: pygltflib.Buffer, path: Path) -> bytes:
    if buffer.uri is None:
        return document.binary_blob() or b""
    if buffer.uri.startswith("data:"):
        return base64.b64decode(buffer.uri.split(",", 1)[1])
    resource = path.parent / buffer.uri
    if not resource.is_file():
        raise InputError(f"{str(path)!r} refers to a missing buffer file {str(resource)!r}")
    return resource.read_bytes()


def _read_accessor(document: pygltflib.GLTF2, buffers: list[bytes], index: int) -> np.ndarray:
    """Accessor ``index`` as a ``(count, n_components)`` float array (strides, sparse, normalized)."""
    accessor = document.accessors[index]
    dtype = np.dtype(_COMPONENT_DTYPES[accessor.componentType]).newbyteorder("<")
    width = _N_COMPONENTS[accessor.type]
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
    """glTF normalized integers to floats (spec 3.11, 'Animations', and 3.6.2.3)."""
    scale = float(np.iinfo(dtype).max)
    return np.maximum(values.astype(float) / scale, -1.0)


def _apply_sparse(document, buffers, accessor, out, dtype, width) -> np.ndarray:
    sparse = accessor.sparse
    index_dtype = np.dtype(_COMPONENT_DTYPES[sparse.indices.componentType]).newbyteorder("<")
    rows = _read_view(document, buffers, sparse.indices.bufferView, sparse.indices.byteOffset or 0,
                      index_dtype, sparse.count, 1)[:, 0].astype(np.int64)
    values = _read_view(document, buffers, sparse.values.bufferView, sparse.values.byteOffset or 0,
                        dtype, sparse.count, width)
    out = out.copy()
    out[rows] = _dequantize(values, dtype) if accessor.normalized else values
    return out


def read_glb_animation(path) -> GlbAnimation:
    """Read back the first morph-weight animation of a glTF file.

    Parameters
    ----------
    path : str or Path
        A ``.glb`` or ``.gltf`` file, such as one written by :func:`write_glb`.

    Returns
    -------
    GlbAnimation
        ``(names, times (n_frames,), weights (n_frames, n_targets), rotations (n_frames, 4) or None)``;
        ``rotations`` are the quaternions (x, y, z, w) of a rotation channel on the same node.

    Raises
    ------
    InputError
        If the file has no animation with a ``weights`` channel.
    """
    document, buffers = _load(path)
    for animation in document.animations:
        found = _weights_channel(animation)
        if found is not None:
            return _read_animation(document, buffers, animation, found)
    raise InputError(f"{str(path)!r} has no animation with a 'weights' channel")


def _weights_channel(animation: pygltflib.Animation):
    return next((c for c in animation.channels if c.target.path == "weights"), None)


def _read_animation(document, buffers, animation, channel) -> GlbAnimation:
    node = document.nodes[channel.target.node]
    mesh = document.meshes[node.mesh]
    names = tuple((mesh.extras or {}).get("targetNames", ()))
    sampler = animation.samplers[channel.sampler]
    times = _read_accessor(document, buffers, sampler.input)[:, 0]
    values = _read_accessor(document, buffers, sampler.output).reshape(len(times), -1)
    rotation = next(
        (c for c in animation.channels if c.target.path == "rotation" and c.target.node == channel.target.node),
        None,
    )
    rotations = None
    if rotation is not None:
        rotations = _read_accessor(document, buffers, animation.samplers[rotation.sampler].output)
    return GlbAnimation(names, times, values, rotations)


def read_rig(path) -> Rig:
    """Load the morph-target primitives of a glTF file as one :class:`Rig`.

    Every primitive (of any mesh) that has morph targets is kept and their vertices are
    concatenated, faces offset. Target names come from each mesh's
    ``extras.targetNames``; a primitive lacking one of the union of names contributes zero
    deltas for it. Vertices are taken **as stored**, in mesh-local coordinates: node
    transforms are not applied. Primitives without morph targets (body, props) are ignored.

    Parameters
    ----------
    path : str or Path
        ``.glb`` or ``.gltf``.

    Returns
    -------
    Rig

    Raises
    ------
    RigError
        If no primitive has morph targets, or a mesh with targets does not name them.
    """
    document, buffers = _load(path)
    parts = [
        _read_primitive(document, buffers, primitive, names)
        for mesh, names in _morph_meshes(document, path)
        for primitive in mesh.primitives
        if primitive.targets
    ]
    if not parts:
        raise RigError(f"{str(path)!r} has no morph targets: it cannot be driven as a blendshape rig")
    return _concatenate(parts)


def _morph_meshes(document, path):
    """(mesh, target names) for each mesh with morph targets."""
    found = []
    for index, mesh in enumerate(document.meshes):
        counts = {len(p.targets) for p in mesh.primitives if p.targets}
        if not counts:
            continue
        names = list((mesh.extras or {}).get("targetNames") or [])
        if not names or counts != {len(names)}:
            raise RigError(
                f"{str(path)!r}: mesh {index} ({mesh.name or 'unnamed'}) has {sorted(counts)} morph targets "
                f"but {len(names)} names in mesh.extras.targetNames; targets must be named to match keys"
            )
        found.append((mesh, names))
    return found


def _read_primitive(document, buffers, primitive, names):
    vertices = _read_accessor(document, buffers, primitive.attributes.POSITION)
    if primitive.indices is None:
        indices = np.arange(len(vertices))
    else:
        indices = _read_accessor(document, buffers, primitive.indices)[:, 0].astype(np.int64)
    faces = _triangles(indices, primitive.mode)
    deltas = {
        name: _read_accessor(document, buffers, target["POSITION"])
        if target.get("POSITION") is not None else np.zeros_like(vertices)
        for name, target in zip(names, primitive.targets)
    }
    return vertices, faces, deltas


def _triangles(indices: np.ndarray, mode) -> np.ndarray:
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
    raise RigError(f"morph-target primitive has mode {mode} (points or lines); expected triangles")


def _concatenate(parts) -> Rig:
    names = list(dict.fromkeys(name for _, _, deltas in parts for name in deltas))
    offsets = np.cumsum([0] + [len(v) for v, _, _ in parts])
    vertices = np.concatenate([v for v, _, _ in parts])
    faces = np.concatenate([f + off for (_, f, _), off in zip(parts, offsets)])
    deltas = np.stack([
        np.concatenate([d.get(name, np.zeros_like(v)) for v, _, d in parts]) for name in names
    ])
    return Rig(vertices, faces, deltas, tuple(names))
