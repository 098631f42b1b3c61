"""A take's ``animation.glb`` read without keyshape: its morph-target weights and node turns per frame.

numpy only (no ``bpy``): Blender ships numpy, and keyshape's tests read the same file with this
module and with ``keyshape.io`` alike. Only what keyshape writes is read: one animation (the one named
``keyshape`` or ``performance``, else the first), float accessors, ``weights`` and ``rotation``
channels. The turns are in glTF world axes, as :func:`anim.turn` takes them: the rotation that takes
a node from its rest (the file's node rotations) to frame ``f`` about its own pivot, its parents at
rest (an eye's without its head's).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


@dataclass(frozen=True)
class Animation:
    """What a take's glb animates, on the take's frames.

    ``weights``: ``{target: (n_frames,)}``; ``turns``: ``{node name: (n_frames, 3, 3)}`` the turns
    (glTF world axes, parents at rest) of every node with a ``rotation`` channel; ``rests``:
    ``{node name: (x, y, z, w)}``, those nodes' rest rotations (relative to their parents) as the file gives them.
    """

    weights: dict = field(default_factory=dict)
    turns: dict = field(default_factory=dict)
    rests: dict = field(default_factory=dict)


def read_animation(path, fps: float, n_frames: int) -> Animation:
    """The animation of the glb at ``path`` on the take's frames ``i < n_frames`` (``i / fps`` seconds)."""
    document, blob = _load(Path(path))
    animations = document.get("animations") or []
    if not animations:
        return Animation()
    chosen = next((a for a in animations if a.get("name") in ("keyshape", "performance")), animations[0])
    nodes = document.get("nodes") or []
    times = np.arange(n_frames) / fps
    weights, local = {}, {}
    for channel in chosen.get("channels", ()):
        target, sampler = channel.get("target", {}), chosen["samplers"][channel["sampler"]]
        if "node" not in target:
            continue
        node = target["node"]
        keys = _accessor(document, blob, sampler["input"]).ravel()
        values = _accessor(document, blob, sampler["output"])
        if target.get("path") == "weights":
            names = _target_names(document, nodes[node])
            values = values.reshape(len(keys), -1)
            for k, name in enumerate(names[: values.shape[1]]):
                weights.setdefault(name, _sample(keys, values[:, k : k + 1], times)[:, 0])
        elif target.get("path") == "rotation":
            quats = _continuous(values.reshape(len(keys), 4))
            quats = _sample(keys, quats, times)
            local[node] = _matrices(quats / np.linalg.norm(quats, axis=1, keepdims=True))
    rests = {nodes[i].get("name") or f"node_{i}": tuple(nodes[i].get("rotation", (0.0, 0.0, 0.0, 1.0))) for i in local}
    return Animation(weights, _world_turns(nodes, local), rests)


def _load(path: Path):
    """``(document, binary chunk)`` of a ``.glb`` (or a ``.gltf`` with an embedded or side buffer)."""
    data = path.read_bytes()
    if data[:4] != b"glTF":
        document = json.loads(data)
        uri = (document.get("buffers") or [{}])[0].get("uri")
        return document, (path.parent / uri).read_bytes() if uri and not uri.startswith("data:") else b""
    offset, document, blob = 12, None, b""
    while offset + 8 <= len(data):
        length, kind = struct.unpack_from("<II", data, offset)
        chunk = data[offset + 8 : offset + 8 + length]
        if kind == 0x4E4F534A:  # JSON
            document = json.loads(chunk)
        elif kind == 0x004E4942:  # BIN
            blob = chunk
        offset += 8 + length
    return document, blob


def _accessor(document, blob: bytes, index: int) -> np.ndarray:
    """A float accessor as ``(count, components)`` float64."""
    accessor = document["accessors"][index]
    if accessor.get("componentType") != 5126:
        raise ValueError(f"accessor {index}: keyshape writes float animation data only")
    width = _COMPONENTS[accessor["type"]]
    count = accessor["count"]
    view = document["bufferViews"][accessor["bufferView"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    stride = view.get("byteStride") or 4 * width
    raw = np.frombuffer(blob, dtype="<f4", count=(stride // 4) * (count - 1) + width, offset=start)
    return raw.reshape(-1)[np.arange(count)[:, None] * (stride // 4) + np.arange(width)].astype(float)


def _target_names(document, node) -> list:
    mesh = document["meshes"][node["mesh"]] if "mesh" in node else {}
    return list((mesh.get("extras") or {}).get("targetNames") or [])


def _sample(keys: np.ndarray, values: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``values (n_keys, c)`` at ``keys (n_keys,)`` seconds on the take's frames at ``times (n,)``: ``(n, c)``.

    One key per frame (what keyshape writes, at the video's own timestamps) is frame ``i``'s as it
    stands; other keys are interpolated linearly at the times, counted from the first key.
    """
    if len(keys) == len(times):
        return values
    return np.column_stack([np.interp(times, keys - keys[0], values[:, c]) for c in range(values.shape[1])])


def _continuous(quats: np.ndarray) -> np.ndarray:
    """``(n, 4)`` quaternions with each on the side of the one before (a lerp between them turns the short way)."""
    quats = quats.copy()
    for i in range(1, len(quats)):
        if np.dot(quats[i], quats[i - 1]) < 0:
            quats[i] = -quats[i]
    return quats


def _matrices(quats: np.ndarray) -> np.ndarray:
    """``(n, 4)`` unit quaternions in glTF order ``(x, y, z, w)`` as ``(n, 3, 3)`` rotations."""
    x, y, z, w = quats.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)


def _world_turns(nodes: list, local: dict) -> dict:
    """``{name: (n_frames, 3, 3)}``: each node of ``local {node: (n_frames, 3, 3)}`` (its animated
    rotations) turned about its pivot, its parents at rest, in world axes: ``P L_f Rᵀ Pᵀ``, ``P`` its
    parent's world rotation at rest, ``R`` its own rest rotation. A node below a turned node turns
    with it besides (as :func:`anim.turn` keys it: the eye's ``E`` after the head's ``D`` is ``D E``)."""
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", ())}
    turns = {}
    for node, rotations in local.items():
        above, i = np.eye(3), parent.get(node)
        while i is not None:
            above = _rest_rotation(nodes[i]) @ above
            i = parent.get(i)
        rest = _rest_rotation(nodes[node])
        turns[nodes[node].get("name") or f"node_{node}"] = np.einsum("ij,fjk,lk,ml->fim", above, rotations, rest, above)
    return turns


def _rest_rotation(node) -> np.ndarray:
    if "matrix" in node:
        m = np.array(node["matrix"], dtype=float).reshape(4, 4).T[:3, :3]
        u, _, vt = np.linalg.svd(m)
        return u @ vt
    return _matrices(np.array([node.get("rotation", [0.0, 0.0, 0.0, 1.0])], dtype=float))[0]
