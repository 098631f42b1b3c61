"""Animation in Blender: shape-key weights and head (eye) rotations keyed once per frame.

Shared by the add-on (importing a take) and keyshape's FBX / .blend writer (the job it runs in
Blender). Every curve gets one LINEAR key per frame of the take, at frames ``start + i``.

Rotations arrive in glTF world axes (+Y up, facing +Z), as keyshape writes them into glTF: a turn
``D`` of a node about its own pivot, its parents at rest. Blender's glTF importer maps glTF
``(x, y, z)`` to Blender ``(x, -z, y)`` (``G`` below), so the turn in Blender's world is ``G D Gᵀ``.
"""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Matrix

GLTF_TO_BLENDER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def set_frame_rate(scene, fps: float, n_frames: int, start: int = 1) -> None:
    """The scene plays at ``fps`` (``fps / fps_base``, e.g. 30 / 1.001) over the take's frames."""
    if abs(fps - round(fps)) < 1e-3:  # 24.99999 read back from a CSV's times is 25
        fps = float(round(fps))
    whole = max(1, round(fps))
    scene.render.fps, scene.render.fps_base = whole, whole / fps
    scene.frame_start, scene.frame_end = start, start + max(n_frames, 1) - 1


def silence(objects) -> None:
    """Unassign the objects' (and their shape keys') actions and mute their NLA tracks: only the
    take plays, and the file's own clips stay in the file (muted) for the artist."""
    for owner in _owners(objects):
        data = owner.animation_data
        if data is None:
            continue
        if data.action is not None:
            data.action.use_fake_user = True
            data.action = None
        for track in data.nla_tracks:
            track.mute = True


def _owners(objects):
    for obj in objects:
        yield obj
        keys = getattr(obj.data, "shape_keys", None) if obj.type == "MESH" else None
        if keys is not None:
            yield keys


def shape_key_meshes(objects) -> list:
    """The mesh objects with shape keys (besides the basis)."""
    return [o for o in objects if o.type == "MESH" and o.data.shape_keys and len(o.data.shape_keys.key_blocks) > 1]


def key_shape_keys(meshes, weights: dict, *, start: int = 1, name: str = "keyshape") -> list:
    """Key ``weights {shape key: [weight per frame]}`` on every mesh that has that shape key.

    Slider ranges widen to hold the weights (Blender clamps a shape key to its sliders).
    Returns the names no mesh has.
    """
    found = set()
    for mesh in meshes:
        key = mesh.data.shape_keys
        blocks = {b.name: b for b in key.key_blocks[1:]}
        names = [n for n in weights if n in blocks]
        if not names:
            continue
        action = _new_action(key, f"{name}_{mesh.name}")
        for n in names:
            values = np.nan_to_num(np.asarray(weights[n], dtype=float))
            _widen_sliders(blocks[n], values)
            _curve(action, f'key_blocks["{bpy.utils.escape_identifier(n)}"].value', 0, values, start, group=n)
        found.update(names)
    return [n for n in weights if n not in found]


def _widen_sliders(block, values) -> None:
    if len(values):
        block.slider_min = max(-10.0, min(block.slider_min, float(np.floor(values.min()))))
        block.slider_max = min(10.0, max(block.slider_max, float(np.ceil(values.max()))))


def _new_action(owner, name: str):
    if owner.animation_data is None:
        owner.animation_data_create()
    action = bpy.data.actions.new(name)
    owner.animation_data.action = action
    return action


def _curve(action, path: str, index: int, values, start: int, *, group: str):
    """One LINEAR key per frame on ``action``'s curve ``path[index]``."""
    curve = action.fcurves.find(path, index=index) or action.fcurves.new(path, index=index, action_group=group)
    curve.keyframe_points.clear()
    curve.keyframe_points.add(len(values))
    frames = np.arange(start, start + len(values), dtype=float)
    curve.keyframe_points.foreach_set("co", np.column_stack([frames, values]).ravel())
    for point in curve.keyframe_points:
        point.interpolation = "LINEAR"
    curve.update()
    return curve


def find_node(objects, name: str):
    """``(armature object, bone name)`` for a bone called ``name``, else ``(object, None)``, else None."""
    for obj in objects:
        if obj.type == "ARMATURE" and name in obj.data.bones:
            return obj, name
    for obj in objects:
        if obj.name == name:
            return obj, None
    return None


def pose_at_rest(nodes, object_rests: dict) -> None:
    """Stand ``nodes`` (:func:`find_node` results) and their parents at rest, for :func:`turn`:
    the bones and every bone above them with an identity pose, an object whose rotation is animated
    turned to ``object_rests[its name]`` (a ``(w, x, y, z)`` quaternion; its file's rest), the
    other objects as they are. Their animation sets them again on the next frame change."""
    for owner, bone in nodes:
        if bone is not None:
            pose_bone = owner.pose.bones[bone]
            while pose_bone is not None:
                pose_bone.matrix_basis = Matrix.Identity(4)
                pose_bone = pose_bone.parent
            continue
        action = owner.animation_data.action if owner.animation_data else None
        animated = action is not None and any(c.data_path.startswith("rotation_") for c in action.fcurves)
        if animated and owner.name in object_rests:
            owner.rotation_mode = "QUATERNION"
            owner.rotation_quaternion = object_rests[owner.name]
    bpy.context.view_layer.update()


def turn(turns, *, start: int = 1, name: str = "keyshape") -> None:
    """Key ``[(node, rotations (n_frames, 3, 3)), ...]`` (glTF world axes, each node about its pivot,
    its parents at rest) on each node, a :func:`find_node` result: the pose bone's or the object's
    quaternion rotation. All are computed before any is keyed, so a head keyed first does not move
    the eyes' rest."""
    bpy.context.view_layer.update()
    quats = [_local_quaternions(node, rotations) for node, rotations in turns]
    for (node, _), q in zip(turns, quats):
        owner, bone = node
        (owner.pose.bones[bone] if bone is not None else owner).rotation_mode = "QUATERNION"
        path = f'pose.bones["{bpy.utils.escape_identifier(bone)}"].rotation_quaternion' if bone is not None \
            else "rotation_quaternion"
        action = owner.animation_data.action if owner.animation_data and owner.animation_data.action else \
            _new_action(owner, f"{name}_{owner.name}")
        for i in range(4):
            _curve(action, path, i, q[:, i], start, group=bone or owner.name)


def _local_quaternions(node, rotations) -> np.ndarray:
    """(n_frames, 4) quaternions (w, x, y, z) of the node's own rotation that turn it by ``rotations``."""
    owner, bone = node
    world = np.einsum("ij,fjk,lk->fil", GLTF_TO_BLENDER, np.asarray(rotations, dtype=float), GLTF_TO_BLENDER)
    if bone is not None:
        # armature space: pose = M · basis, M fixed by the parents as they stand; the turn there is
        # Aᵀ D A (A: the armature's world rotation), so basis' = basis · poseᵀ · Aᵀ D A · pose
        pose_bone = owner.pose.bones[bone]
        arm, pose, basis = (_rotation(m) for m in (owner.matrix_world, pose_bone.matrix, pose_bone.matrix_basis))
        local = np.einsum("ij,kj,lk,flm,mn,np->fip", basis, pose, arm, world, arm, pose)
    else:
        # world = W · basis (W: parent world · parent inverse); the turn about the pivot: basis' = Wᵀ D W · basis
        frame = _rotation(owner.matrix_world @ owner.matrix_basis.inverted())
        basis = _rotation(owner.matrix_basis)
        local = np.einsum("ji,fjk,kl,lm->fim", frame, world, frame, basis)
    return _continuous([Matrix(m.tolist()).to_quaternion()[:] for m in local])


def _rotation(matrix) -> np.ndarray:
    """The rotation part of a (4×4 or 3×3) matrix: the polar factor, without scale."""
    m = np.array(matrix)[:3, :3]
    u, _, vt = np.linalg.svd(m)
    return u @ vt


def _continuous(quats) -> np.ndarray:
    quats = np.array(quats, dtype=float)
    for i in range(1, len(quats)):
        if np.dot(quats[i], quats[i - 1]) < 0:
            quats[i] = -quats[i]
    return quats
