"""Writing VRM Animation 1.0 (``.vrma``) for a VRM avatar: expressions, head and gaze over time.

A ``.vrma`` is a glTF 2.0 binary with the root extension ``VRMC_vrm_animation``
(``specVersion "1.0"``). It carries no mesh: a humanoid skeleton in the VRM T-pose (every bone's
rest rotation the identity, the figure facing +Z with its left at +X), one node per expression
and one for the gaze, and one glTF animation moving them. What keyshape writes:

* **expressions** — one node per expression of the avatar the take was made for, its
  ``translation`` x the expression's weight over time (y = z = 0), clipped to [0, 1] as the
  format asks. Preset expressions are written under their VRM 1.0 preset name
  (``expressions.preset``), whatever the avatar's version: a VRM 0.x avatar's ``A I U E O``,
  ``Blink``, ``Blink_L``/``Blink_R``, ``Joy``, ``Angry``, ``Sorrow``, ``Fun``, ``Neutral`` become
  ``aa ih ou ee oh``, ``blink``, ``blinkLeft``/``blinkRight``, ``happy``, ``angry``, ``sad``,
  ``relaxed``, ``neutral`` (VRMA is VRM 1.0 only; players map them back onto a 0.x avatar's
  groups). Custom expressions keep the avatar's name for them (``expressions.custom``).
  ``lookUp/Down/Left/Right`` may not be animated in a VRMA (the gaze drives them) and are left
  out, as are perfect-sync morph targets that no expression binds (a VRMA animates expressions
  only): an :class:`~keyshape.exceptions.InputWarning` names those the take moves.
* **head** — the ``head`` bone's rotation per frame from the take's head poses
  (:func:`keyshape.schemes.head_rotations`, frames without a pose holding the previous one), as
  the normalized bone rotation (the rest is the identity). The other bones stay at rest.
* **gaze** — with eye rotations, the ``lookAt`` node's local rotation per frame (a child of the
  head, at ``offsetFromHeadBone``): the turn from straight ahead (+Z) to the mean gaze direction
  of the two eyes relative to the head, whose extrinsic Z-X-Y Euler angles are VRM's look-at yaw
  (about Y) and pitch (about X), as the 1.0 text has it and three-vrm-animation reads it. (The
  1.0 draft took the node's *position* as a gaze target; readers still on the draft, such as
  the VRM add-on for Blender 4.10, ignore this gaze.) The humanoid's ``leftEye``/``rightEye``
  may not be in a VRMA; the avatar's look-at turns its eyes.

The skeleton's proportions are a 1.5 m-tall figure scaled so its head is as high as the avatar's
``head`` bone (when the avatar names one); bone positions only place the rest pose, since
rotations are read relative to it.

References
----------
VRM Consortium, *VRMC_vrm_animation 1.0* (``humanoid.humanBones``, ``expressions``, ``lookAt``);
*VRMC_vrm 1.0* humanoid and expression presets.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from ..containers import Poses, Weights
from ..exceptions import InputError, InputWarning
from ..schemes import rotations_to_gltf
from ._gltf_anim import check_eyes, check_poses, pose_quaternions
from ._gltf_edit import Blob
from ._gltf_nodes import continuous_hemisphere, world_matrix
from ._vrm_read import PRESETS_1, VrmAvatar, read_vrm
from .atomic import atomic_path
from .validate import check_weight_values

__all__ = ["write_vrma", "vrma_expression_names", "SKELETON"]

# (bone, parent, rest position in metres) of a 1.5 m figure in the VRM T-pose, facing +Z, left at +X:
# VRM 1.0's required bones, and the chest and neck between spine and head.
SKELETON = (
    ("hips", None, (0.0, 0.85, 0.0)),
    ("spine", "hips", (0.0, 0.95, 0.0)),
    ("chest", "spine", (0.0, 1.1, 0.0)),
    ("neck", "chest", (0.0, 1.35, 0.0)),
    ("head", "neck", (0.0, 1.45, 0.0)),
    ("leftUpperLeg", "hips", (0.08, 0.8, 0.0)),
    ("leftLowerLeg", "leftUpperLeg", (0.08, 0.45, 0.0)),
    ("leftFoot", "leftLowerLeg", (0.08, 0.07, 0.0)),
    ("rightUpperLeg", "hips", (-0.08, 0.8, 0.0)),
    ("rightLowerLeg", "rightUpperLeg", (-0.08, 0.45, 0.0)),
    ("rightFoot", "rightLowerLeg", (-0.08, 0.07, 0.0)),
    ("leftUpperArm", "chest", (0.17, 1.3, 0.0)),
    ("leftLowerArm", "leftUpperArm", (0.42, 1.3, 0.0)),
    ("leftHand", "leftLowerArm", (0.65, 1.3, 0.0)),
    ("rightUpperArm", "chest", (-0.17, 1.3, 0.0)),
    ("rightLowerArm", "rightUpperArm", (-0.42, 1.3, 0.0)),
    ("rightHand", "rightLowerArm", (-0.65, 1.3, 0.0)),
)
_LOOKS = frozenset({"lookUp", "lookDown", "lookLeft", "lookRight"})
_EYE_HEIGHT = 0.06  # the look-at node above the head bone (VRM's usual offsetFromHeadBone), metres


def vrma_expression_names(avatar: VrmAvatar, names) -> tuple[dict[str, str], dict[str, str], list[str]]:
    """How a take's target names are written: ``(preset, custom, left_out)``.

    ``preset`` maps the VRM 1.0 preset name to the take's target (``{"aa": "A"}`` on a VRM 0.x
    avatar), ``custom`` the custom expression's name to the target (the same name), ``left_out``
    lists the targets a VRMA cannot carry (looks, perfect-sync morphs without an expression, names
    the avatar lacks).
    """
    by_name = {e.name: e for e in avatar.expressions}
    preset, custom, left_out = {}, {}, []
    for name in names:
        expression = by_name.get(name)
        if expression is None or expression.preset in _LOOKS:
            left_out.append(name)
        elif expression.preset is not None:
            preset[expression.preset] = name
        elif name in PRESETS_1:  # a custom expression may not take a preset's name
            left_out.append(name)
        else:
            custom[name] = name
    return preset, custom, left_out


def write_vrma(path, animation: Weights, avatar_path, *, poses: Poses | None = None,
               eyes: np.ndarray | None = None) -> Path:
    """Write ``animation`` as a VRM Animation 1.0 file for the avatar at ``avatar_path``, atomically.

    Parameters
    ----------
    path : str or Path
        Output file, ending in ``.vrma``.
    animation : Weights
        ``values (n_frames, n_targets)`` named by the avatar's targets (its expression names, in
        its VRM version's spelling; perfect-sync morph names are left out), at least one frame.
    avatar_path : str or Path
        The ``.vrm`` the animation was made for (read with :func:`keyshape.io.rig.load_vrm`).
    poses : Poses, optional, keyword-only
        Head poses (image convention), one per frame: the head bone's rotation.
    eyes : (n_frames, 2, 3, 3) float, optional, keyword-only
        Eye rotations relative to the head (left eye first, image convention): the look-at.

    Returns
    -------
    Path

    Raises
    ------
    InputError
        A suffix other than ``.vrma``, no frames, weights that are not finite numbers, poses or
        eyes of another frame count, or no name of the animation among the avatar's expressions.
    RigError
        ``avatar_path`` is not a readable VRM avatar.
    """
    path = Path(path)
    if path.suffix.lower() != ".vrma":
        raise InputError(f"{path}: a VRM Animation file must end in .vrma")
    check_weight_values(path, animation.names, animation.values, animation.frame_index)
    check_poses(poses, animation)
    check_eyes(eyes, animation)
    if animation.n_frames == 0:
        raise InputError(f"{path}: the take has no frames to animate")
    avatar = read_vrm(avatar_path)
    preset, custom, left_out = vrma_expression_names(avatar, animation.names)
    if not preset and not custom:
        raise InputError(f"{path}: none of the animation's targets {list(animation.names)[:8]} is an expression "
                         f"of {avatar_path}; a .vrma animates the expressions of the avatar it was made for")
    values = np.nan_to_num(np.asarray(animation.values, dtype=float))
    moving = [n for n in left_out if np.abs(values[:, animation.names.index(n)]).max(initial=0) > 0]
    if moving:  # a target at rest throughout (an avatar's look no key drives) goes unsaid
        warnings.warn(f"{path}: left out, not expressions a VRM Animation can carry: {moving}", InputWarning,
                      stacklevel=2)
    document = _document(animation, preset, custom, poses, eyes, _head_height(avatar_path))
    data = b"".join(document.save_to_bytes())
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def _head_height(avatar_path) -> float | None:
    """The avatar's ``head`` bone height above its origin (metres), or None when it names none."""
    from ._gltf_read import load_document

    document, _ = load_document(avatar_path, editable=False)
    extensions = document.extensions if isinstance(document.extensions, dict) else {}
    node = None
    try:
        if isinstance(extensions.get("VRMC_vrm"), dict):
            node = extensions["VRMC_vrm"]["humanoid"]["humanBones"]["head"]["node"]
        elif isinstance(extensions.get("VRM"), dict):
            bones = extensions["VRM"]["humanoid"]["humanBones"]
            node = next(b["node"] for b in bones if isinstance(b, dict) and b.get("bone") == "head")
    except (KeyError, TypeError, StopIteration):
        return None
    if not isinstance(node, int) or not 0 <= node < len(document.nodes):
        return None
    height = float(world_matrix(document, node)[1, 3])
    return height if np.isfinite(height) and height > 0.05 else None


def _document(animation: Weights, preset: dict, custom: dict, poses, eyes, head_height) -> pygltflib.GLTF2:
    document = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0", generator="keyshape"), scene=0)
    rest = {bone: np.asarray(position) for bone, _, position in SKELETON}
    scale = head_height / rest["head"][1] if head_height else 1.0
    bones = {}
    for bone, parent, _ in SKELETON:
        local = (rest[bone] - (rest[parent] if parent else 0.0)) * scale
        document.nodes.append(pygltflib.Node(name=bone, translation=[float(v) for v in local]))
        bones[bone] = len(document.nodes) - 1
        if parent is not None:
            document.nodes[bones[parent]].children.append(bones[bone])
    look = None
    if eyes is not None:  # the gaze origin between the eyes, turned with the head
        document.nodes.append(pygltflib.Node(name="lookAt", translation=[0.0, _EYE_HEIGHT * scale, 0.0]))
        look = len(document.nodes) - 1
        document.nodes[bones["head"]].children.append(look)
    expression_nodes = {}
    for group, names in (("preset", preset), ("custom", custom)):
        for key in names:
            document.nodes.append(pygltflib.Node(name=f"expression_{key}", translation=[0.0, 0.0, 0.0]))
            expression_nodes[group, key] = len(document.nodes) - 1
    document.scenes = [pygltflib.Scene(nodes=[bones["hips"], *expression_nodes.values()])]

    blob = Blob(document)
    times = blob.add(animation.times.astype(np.float32), "SCALAR", bounds=True)
    channels = []
    for (group, key), node in expression_nodes.items():
        column = animation.values[:, animation.names.index((preset if group == "preset" else custom)[key])]
        moved = np.zeros((animation.n_frames, 3), np.float32)
        moved[:, 0] = np.clip(np.nan_to_num(column, nan=0.0), 0.0, 1.0)
        channels.append((node, "translation", blob.add(moved, "VEC3")))
    if poses is not None:
        channels.append((bones["head"], "rotation", blob.add(pose_quaternions(poses).astype(np.float32), "VEC4")))
    if look is not None:
        channels.append((look, "rotation", blob.add(gaze_quaternions(eyes).astype(np.float32), "VEC4")))
    samplers, targets = [], []
    for node, field, output in channels:
        samplers.append(pygltflib.AnimationSampler(input=times, output=output, interpolation="LINEAR"))
        targets.append(pygltflib.AnimationChannel(
            sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path=field)))
    document.animations = [pygltflib.Animation(name="performance", samplers=samplers, channels=targets)]
    blob.finish()

    extension = {"specVersion": "1.0", "humanoid": {"humanBones": {b: {"node": i} for b, i in bones.items()}}}
    expressions = {}
    for group in ("preset", "custom"):
        entries = {k: {"node": n} for (g, k), n in expression_nodes.items() if g == group}
        if entries:
            expressions[group] = entries
    extension["expressions"] = expressions
    if look is not None:
        extension["lookAt"] = {"node": look, "offsetFromHeadBone": document.nodes[look].translation}
    document.extensionsUsed = ["VRMC_vrm_animation"]
    document.extensions = {"VRMC_vrm_animation": extension}
    return document


def gaze_quaternions(eyes: np.ndarray) -> np.ndarray:
    """(n_frames, 4) unit quaternions (x, y, z, w), glTF axes: the look-at turn of each frame.

    ``eyes (n_frames, 2, 3, 3)``: eye rotations relative to the head in image convention (what
    :meth:`keyshape.capture.gaze.Gaze.rotations` gives). Each eye's rest direction (+Z in glTF
    axes, out of the face) is turned, the two directions averaged, and the result written as
    ``R_y(yaw) · R_x(pitch)`` with ``yaw = atan2(x, z)``, ``pitch = atan2(−y, √(x² + z²))``: the
    turn of +Z onto the gaze with no roll, whose Y-X-Z Euler angles are the look-at's yaw (toward
    the avatar's left, +X, positive) and pitch (downward positive).

    Examples
    --------
    >>> turn = np.array([[[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]] * 2)[None]  # both eyes 90° toward image +x
    >>> np.round(gaze_quaternions(turn), 4)  # the subject's left, the avatar's left: +90° about +Y
    array([[0.    , 0.7071, 0.    , 0.7071]])
    """
    rotations = rotations_to_gltf(np.asarray(eyes, dtype=float).reshape(-1, 3, 3)).reshape(-1, 2, 3, 3)
    finite = np.isfinite(rotations).all(axis=(2, 3))
    directions = np.where(finite[..., None], rotations[..., :, 2], [0.0, 0.0, 1.0]).mean(axis=1)
    x, y, z = directions.T
    yaw, pitch = np.arctan2(x, z), np.arctan2(-y, np.hypot(x, z))
    quats = Rotation.from_euler("YX", np.stack([yaw, pitch], axis=1)).as_quat() if len(directions) \
        else np.zeros((0, 4))
    return continuous_hemisphere(quats)
