"""A character's nodes in a glTF document: finding its head and eyes, and turning them.

:func:`find_head` and :func:`find_eyes` pick the nodes to turn, by name and place in the
node tree (skin joints first); :func:`local_matrix`, :func:`world_matrix` and
:func:`world_rotation` give rest transforms (the reader places meshes in the world with them);
:func:`head_local_rotations` turns a world-frame rotation per frame into the node's local
rotation track. Private to :mod:`keyshape.io` (the glTF reader and writers, and the
USD writer, which finds its head joint by the same names).

Rotations: a head rotation ``D`` is given in the file's world frame (glTF: +Y up, the
character facing +Z). On a node whose parent has the rest world rotation ``P`` and whose own
rest rotation is ``R``, the local rotation that turns the head by ``D`` about its pivot is
``Pᵀ D P R`` (then its world rotation is ``D P R``).
"""

from __future__ import annotations

import re

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from ..exceptions import RigError

_HEAD = re.compile(r"head", re.IGNORECASE)
_NOT_HEAD = re.compile(r"end|top|nub|null|tip|_ik|target", re.IGNORECASE)


def parents(document: pygltflib.GLTF2) -> dict[int, int]:
    """``{child: parent}`` node indices."""
    return {child: index for index, node in enumerate(document.nodes) for child in (node.children or [])}


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
        return head_joint(document, skinned, parent_of)
    common = _common_ancestors(face_nodes, parent_of)
    heads = [n for n in common if is_head(document.nodes[n].name)]
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
            named = sorted({n.name for n in document.nodes if n.name})
            raise RigError(f"no eye nodes named {list(names)}; nodes: {named[:40]}")
        return found[0], found[1]
    pool = descendants(document, head) if head is not None else range(len(document.nodes))
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


def descendants(document, node: int) -> list[int]:
    out, stack = [], [node]
    while stack:
        current = stack.pop()
        out.append(current)
        stack.extend(document.nodes[current].children or [])
    return out


def is_head(name) -> bool:
    return bool(name) and bool(_HEAD.search(name)) and not _NOT_HEAD.search(name)


def head_joint(document, skinned, parent_of) -> int | None:
    joints = {j for n in skinned for j in document.skins[document.nodes[n].skin].joints}
    heads = [j for j in joints if is_head(document.nodes[j].name)]
    return min(heads, key=lambda j: (_depth(j, parent_of), j)) if heads else None


def _depth(node: int, parent_of: dict[int, int]) -> int:
    depth = 0
    while node in parent_of:
        node, depth = parent_of[node], depth + 1
    return depth


def ancestry(node: int, parent_of: dict[int, int]) -> list[int]:
    chain = [node]
    while chain[-1] in parent_of:
        chain.append(parent_of[chain[-1]])
    return chain


def _common_ancestors(nodes: list[int], parent_of: dict[int, int]) -> list[int]:
    """Ancestors-or-self shared by every node, nearest first."""
    chains = [ancestry(n, parent_of) for n in nodes]
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


def world_matrix(document: pygltflib.GLTF2, node: int | None, parent_of: dict[int, int] | None = None
                 ) -> np.ndarray:
    """(4, 4) float: a node's rest world transform, its ancestors' composed from the root down
    (identity for None). ``parent_of`` (from :func:`parents`) saves recomputing it."""
    parent_of = parents(document) if parent_of is None else parent_of
    matrix = np.eye(4)
    chain = [] if node is None else ancestry(node, parent_of)
    for index in reversed(chain):
        matrix = matrix @ local_matrix(document.nodes[index])
    return matrix


def world_rotation(document: pygltflib.GLTF2, node: int | None) -> np.ndarray:
    """(3, 3) float: the rotation part of a node's rest world transform (identity for None)."""
    return rotation_part(world_matrix(document, node)[:3, :3])


def rotation_part(linear: np.ndarray) -> np.ndarray:
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
    node.rotation = Rotation.from_matrix(rotation_part(matrix[:3, :3])).as_quat().tolist()
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
