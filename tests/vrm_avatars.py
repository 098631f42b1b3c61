"""Minimal hand-written VRM avatars for the tests (numpy + struct, no Blender), with their known answers.

:func:`make_vrm` writes a ``.vrm`` (a GLB) holding two meshes with morph targets — a face (6
vertices, 4 triangles, moved by its node) and teeth (3 vertices, scaled by its node) — and the
standard expressions (the vowels, the blinks, joy/happy, a look with no binds, a custom one), in
VRM 1.0 (``VRMC_vrm``) or VRM 0.x (``VRM``) spelling. The 0.x file stores the same avatar facing −Z
(as VRM 0.x does), so both read to the same rig.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FACE_MORPHS = ("mouthOpen", "mouthWide", "mouthRound", "eyeClose_L", "eyeClose_R")
PERFECT_SYNC_MORPHS = ("jawOpen", "mouthSmileLeft")
TEETH_MORPHS = ("teethShow",)
FACE_TRANSLATION = np.array([0.0, 1.5, 0.1])
TEETH_SCALE = 0.5

# name (VRM 1.0) -> (VRM 0.x presetName, VRM 0.x name, binds as (mesh, morph, weight in [0, 1]))
EXPRESSIONS = {
    "aa": ("a", "A", [(0, 0, 1.0)]),
    "ih": ("i", "I", [(0, 1, 0.6), (0, 0, 0.2)]),
    "ou": ("u", "U", [(0, 2, 1.0)]),
    "ee": ("e", "E", [(0, 1, 1.0), (1, 0, 0.5)]),
    "oh": ("o", "O", [(0, 2, 0.5), (0, 0, 0.5)]),
    "blink": ("blink", "Blink", [(0, 3, 1.0), (0, 4, 1.0)]),
    "blinkLeft": ("blink_l", "Blink_L", [(0, 3, 1.0)]),
    "blinkRight": ("blink_r", "Blink_R", [(0, 4, 1.0)]),
    "happy": ("joy", "Joy", [(0, 1, 0.3), (1, 0, 0.25)]),
    "lookUp": ("lookup", "LookUp", []),
}
CUSTOM = {"smirk": [(0, 1, 0.4)]}  # VRM 0.x: group "Smirk", presetName "unknown"
# make_vrm(skeleton=True): VRM 1.0's required humanoid bones and a neck, (bone, parent, world position)
# in the T-pose facing +Z; the head at the face's height. Players (three-vrm) refuse avatars without them.
BONES = (("hips", None, (0, 0.9, 0)), ("spine", "hips", (0, 1.0, 0)), ("neck", "spine", (0, 1.4, 0)),
         ("head", "neck", (0, 1.5, 0)), ("leftUpperLeg", "hips", (0.1, 0.85, 0)),
         ("leftLowerLeg", "leftUpperLeg", (0.1, 0.45, 0)), ("leftFoot", "leftLowerLeg", (0.1, 0.05, 0)),
         ("rightUpperLeg", "hips", (-0.1, 0.85, 0)), ("rightLowerLeg", "rightUpperLeg", (-0.1, 0.45, 0)),
         ("rightFoot", "rightLowerLeg", (-0.1, 0.05, 0)), ("leftUpperArm", "spine", (0.2, 1.35, 0)),
         ("leftLowerArm", "leftUpperArm", (0.45, 1.35, 0)), ("leftHand", "leftLowerArm", (0.7, 1.35, 0)),
         ("rightUpperArm", "spine", (-0.2, 1.35, 0)), ("rightLowerArm", "rightUpperArm", (-0.45, 1.35, 0)),
         ("rightHand", "rightLowerArm", (-0.7, 1.35, 0)))


@dataclass(frozen=True)
class Avatar:
    """What a test avatar is, in world space facing +Z (the rig keyshape should read).

    Attributes
    ----------
    path : Path
    vertices : (9, 3) float, face then teeth
    morphs : dict (mesh, morph) -> (9, 3) float, each morph target's delta over all the rig's rows
    expressions : dict name -> list of (mesh, morph, weight in [0, 1]), names in the file's spelling
    """

    path: Path
    vertices: np.ndarray
    morphs: dict
    expressions: dict


def _geometry(perfect_sync: bool):
    rng = np.random.default_rng(37)
    face = np.array([[-1, 0, 0], [0, 0, 0.2], [1, 0, 0], [-1, 1, 0], [0, 1, 0.2], [1, 1, 0]], float) * 0.05
    face_faces = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
    teeth = np.array([[-0.5, 0, 0.1], [0.5, 0, 0.1], [0, 0.3, 0.1]]) * 0.05
    names = FACE_MORPHS + (PERFECT_SYNC_MORPHS if perfect_sync else ())
    face_morphs = rng.normal(0, 0.01, (len(names), 6, 3))
    teeth_morphs = rng.normal(0, 0.01, (1, 3, 3))
    return (face, face_faces, names, face_morphs), (teeth, np.array([[0, 1, 2]]), TEETH_MORPHS, teeth_morphs)


def make_vrm(path, version: str = "1.0", *, perfect_sync: bool = False, skeleton: bool = False) -> Avatar:
    """Write a test avatar to ``path`` (VRM ``"1.0"`` or ``"0.x"``) and return its known answers.

    ``skeleton``: also a humanoid skeleton of :data:`BONES` (nodes 3 on, beside the meshes, which
    it does not move), every required bone named in the humanoid, and a look-at through the look
    expressions, as players need."""
    path = Path(path)
    (face, face_faces, face_names, face_morphs), (teeth, teeth_faces, teeth_names, teeth_morphs) = \
        _geometry(perfect_sync)
    turn = np.array([-1.0, 1.0, -1.0]) if version == "0.x" else np.ones(3)  # 0.x stores the avatar facing -Z
    blob = bytearray()
    accessors, views = [], []

    def add(array: np.ndarray, kind: str, component: int, target: int | None = None, minmax: bool = False):
        data = array.astype("<f4" if component == 5126 else "<u2").tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data),
                      **({} if target is None else {"target": target})})
        blob.extend(data + b"\0" * (-len(data) % 4))
        accessor = {"bufferView": len(views) - 1, "componentType": component, "count": len(array), "type": kind}
        if minmax:
            accessor |= {"min": array.min(axis=0).tolist(), "max": array.max(axis=0).tolist()}
        accessors.append(accessor)
        return len(accessors) - 1

    meshes = []
    for name, vertices, faces, names, morphs in (("face", face, face_faces, face_names, face_morphs),
                                                  ("teeth", teeth, teeth_faces, teeth_names, teeth_morphs)):
        position = add(vertices * turn, "VEC3", 5126, 34962, minmax=True)
        indices = add(faces.reshape(-1), "SCALAR", 5123, 34963)
        targets = [{"POSITION": add(m * turn, "VEC3", 5126, 34962, minmax=True)} for m in morphs]
        meshes.append({"name": name, "primitives": [{"attributes": {"POSITION": position}, "indices": indices,
                                                      "targets": targets}],
                       "weights": [0.0] * len(targets), "extras": {"targetNames": list(names)}})
    nodes = [{"name": "Face", "mesh": 0, "translation": (FACE_TRANSLATION * turn).tolist()},
             {"name": "Teeth", "mesh": 1, "scale": [TEETH_SCALE] * 3},
             {"name": "Root", "children": [0, 1]}]
    bones = {}
    if skeleton:
        positions = {bone: np.array(position, float) for bone, _, position in BONES}
        for bone, parent, _ in BONES:
            local = (positions[bone] - (positions[parent] if parent else 0.0)) * turn
            nodes.append({"name": bone, "translation": local.tolist(), "children": []})
            bones[bone] = len(nodes) - 1
            if parent:
                nodes[bones[parent]]["children"].append(bones[bone])
        for node in nodes[3:]:
            if not node["children"]:
                del node["children"]
    expressions = {name: binds for name, (_, _, binds) in EXPRESSIONS.items()} | dict(CUSTOM)
    if perfect_sync:
        expressions["jawOpen"] = [(0, len(FACE_MORPHS), 1.0)]  # a custom expression; mouthSmileLeft stays a morph
    if version == "1.0":
        custom = {n: b for n, b in expressions.items() if n not in EXPRESSIONS}
        meta = {"name": "keyshape test avatar", "licenseUrl": "https://vrm.dev/licenses/1.0/", "authors": ["tests"]}
        extension = {"specVersion": "1.0", "meta": meta,
                     "humanoid": {"humanBones": {b: {"node": i} for b, i in bones.items()} if skeleton
                                  else {"head": {"node": 0}}},
                     **({"lookAt": {"type": "expression", "offsetFromHeadBone": [0.0, 0.06, 0.0]}}
                        if skeleton else {}),
                     "expressions": {
                         "preset": {n: {"morphTargetBinds": [{"node": m, "index": k, "weight": w} for m, k, w in b]}
                                    for n, b in expressions.items() if n in EXPRESSIONS},
                         "custom": {n: {"morphTargetBinds": [{"node": m, "index": k, "weight": w} for m, k, w in b]}
                                    for n, b in custom.items()}}}
        gltf_extensions, used = {"VRMC_vrm": extension}, ["VRMC_vrm"]
        named = expressions
    else:
        groups, named = [], {}
        for name, binds in expressions.items():
            preset, label = (EXPRESSIONS[name][0], EXPRESSIONS[name][1]) if name in EXPRESSIONS \
                else ("unknown", name[0].upper() + name[1:] if name == "smirk" else name)
            groups.append({"name": label, "presetName": preset,
                           "binds": [{"mesh": m, "index": k, "weight": 100.0 * w} for m, k, w in binds],
                           "materialValues": [], "isBinary": False})
            named[label] = binds
        gltf_extensions = {"VRM": {"specVersion": "0.0", "exporterVersion": "keyshape-tests",
                                   "meta": {"title": "keyshape test avatar"},
                                   **({"humanoid": {"humanBones": [{"bone": b, "node": i} for b, i in bones.items()]},
                                       "firstPerson": {"lookAtTypeName": "BlendShape"}} if skeleton else {}),
                                   "blendShapeMaster": {"blendShapeGroups": groups}}}
        used = ["VRM"]
    document = {"asset": {"version": "2.0", "generator": "keyshape tests"}, "scene": 0,
                "scenes": [{"nodes": [2, *([bones["hips"]] if skeleton else [])]}], "nodes": nodes,
                "meshes": meshes, "accessors": accessors,
                "bufferViews": views, "buffers": [{"byteLength": len(blob)}],
                "extensionsUsed": used, "extensions": gltf_extensions}
    write_glb(path, document, bytes(blob))
    world_face = face + FACE_TRANSLATION
    vertices = np.vstack([world_face, teeth * TEETH_SCALE])
    morphs = {}
    for k, m in enumerate(face_morphs):
        morphs[0, k] = np.vstack([m, np.zeros((3, 3))])
    for k, m in enumerate(teeth_morphs):
        morphs[1, k] = np.vstack([np.zeros((6, 3)), m * TEETH_SCALE])
    return Avatar(path, vertices, morphs, named)


def write_glb(path, document: dict, blob: bytes) -> Path:
    """A GLB container: ``document`` as the JSON chunk, ``blob`` as the BIN chunk."""
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    blob = blob + b"\0" * (-len(blob) % 4)
    body = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(blob), b"BIN\0") + blob
    Path(path).write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    return Path(path)


def read_glb(path) -> tuple[dict, bytes]:
    """The JSON document and BIN chunk of a GLB written by :func:`write_glb` (to break it in a test)."""
    data = Path(path).read_bytes()
    (size,) = struct.unpack_from("<I", data, 12)
    document = json.loads(data[20:20 + size])
    (blob_size,) = struct.unpack_from("<I", data, 20 + size)
    return document, data[28 + size:28 + size + blob_size]


def expected_delta(avatar: Avatar, binds) -> np.ndarray:
    """(9, 3): the weighted sum of the binds' morph deltas."""
    return sum((w * avatar.morphs[m, k] for m, k, w in binds), np.zeros_like(avatar.vertices))
