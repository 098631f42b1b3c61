"""Animation pieces of the glTF writers, also used by the USD and Live Link writers.

* checks of what is to be animated: weight names against a rig, pose and eye-rotation
  frame counts;
* head rotations (:func:`keyshape.schemes.head_rotations`, NaN frames holding the previous valid
  rotation) as sign-continuous quaternions for LINEAR interpolation;
* the accessors, samplers and channels of a morph-weight (``weights``) and ``rotation``
  animation in a :class:`~keyshape.io._gltf_Blob`.

Private to :mod:`keyshape.io`: used by the glTF, USD and Live Link writers.
"""

from __future__ import annotations

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from ..containers import Poses, Weights
from ..exceptions import InputError, RigError
from ..schemes import head_rotations
from ._gltf_edit import Blob
from ._gltf_nodes import as_trs, continuous_hemisphere, head_local_rotations
from ._gltf_read import target_names

# --------------------------------------------------------------------------- checks


def check_names(names, weights: Weights) -> None:
    if tuple(weights.names) != tuple(names):
        missing = [n for n in names if n not in weights.names]
        extra = [n for n in weights.names if n not in names]
        raise RigError(
            f"weights must be named by the rig's targets, in rig order {list(names)}; "
            f"got {list(weights.names)} (missing {missing}, extra {extra}); retarget them first"
        )


def check_poses(poses: Poses | None, weights: Weights) -> None:
    if poses is not None and poses.n_frames != weights.n_frames:
        raise InputError(
            f"poses must have one frame per weights frame ({weights.n_frames}); got {poses.n_frames}"
        )


def check_eyes(eyes, weights: Weights) -> None:
    if eyes is not None and np.shape(eyes) != (weights.n_frames, 2, 3, 3):
        raise InputError(f"eyes must have shape ({weights.n_frames}, 2, 3, 3) (left, right rotations per frame); "
                         f"got {np.shape(eyes)}")


# --------------------------------------------------------------------------- rotations


def pose_quaternions(poses: Poses) -> np.ndarray:
    """Unit quaternions ``(n_frames, 4)`` (x, y, z, w) in glTF axes from image-space rotations."""
    rot = head_rotations(poses, hold=True)
    quats = Rotation.from_matrix(rot).as_quat() if len(rot) else np.zeros((0, 4))
    return continuous_hemisphere(quats)


# --------------------------------------------------------------------------- channels


def time_accessor(blob: Blob, weights: Weights) -> int:
    return blob.add(weights.times.astype(np.float32), "SCALAR", bounds=True)


def weights_output(blob: Blob, values: np.ndarray) -> int:
    # glTF morph-weight output: n_frames · n_targets scalars, frame-major.
    return blob.add(np.nan_to_num(values, nan=0.0).astype(np.float32).reshape(-1), "SCALAR")


def new_animation(times: int, weight_outputs, name: str) -> pygltflib.Animation:
    """An animation with one LINEAR ``weights`` channel per ``(node, output accessor)``."""
    samplers, channels = [], []
    for node, output in weight_outputs:
        samplers.append(pygltflib.AnimationSampler(input=times, output=output, interpolation="LINEAR"))
        channels.append(pygltflib.AnimationChannel(
            sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path="weights")))
    return pygltflib.Animation(name=name, samplers=samplers, channels=channels)


def add_rotation(animation: pygltflib.Animation, blob: Blob, times: int, node: int,
                  quats: np.ndarray) -> None:
    output = blob.add(quats.astype(np.float32), "VEC4")
    animation.samplers.append(pygltflib.AnimationSampler(input=times, output=output, interpolation="LINEAR"))
    animation.channels.append(pygltflib.AnimationChannel(
        sampler=len(animation.samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path="rotation")))


def add_node_rotation(document, blob, animation, node: int, world: np.ndarray) -> None:
    """A rotation channel turning ``node`` by ``world (n_frames, 3, 3)`` (glTF axes) about its pivot."""
    as_trs(document.nodes[node])
    times = animation.samplers[0].input
    add_rotation(animation, blob, times, node, head_local_rotations(document, node, world))


def mesh_weights(mesh: pygltflib.Mesh, weights: Weights) -> np.ndarray:
    """(n_frames, n_mesh_targets): the mesh's targets in its own order; unnamed ones at rest."""
    names = target_names(mesh)
    rest = list(mesh.weights or []) + [0.0] * (len(names) - len(mesh.weights or []))
    columns = [weights.values[:, weights.names.index(n)] if n in weights.names
               else np.full(weights.n_frames, rest[k]) for k, n in enumerate(names)]
    return np.stack(columns, axis=1)
