"""Animation pieces of the glTF writers, also used by the USD and Live Link writers.

* checks of what is to be animated: weight names against a rig, pose and eye-rotation
  frame counts;
* head and eye rotations from image-space poses to glTF axes (:func:`head_rotations`,
  ``R_gltf = C R C`` with ``C = diag(1, -1, -1)``), NaN frames holding the previous valid
  rotation, as sign-continuous quaternions for LINEAR interpolation;
* the accessors, samplers and channels of a morph-weight (``weights``) and ``rotation``
  animation in a :class:`~keyshape.io._gltf_Blob`.

Private to :mod:`keyshape.io.gltf`, which re-exports :func:`head_rotations`.
"""

from __future__ import annotations

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from ..containers import Poses, Weights
from ..exceptions import InputError, RigError
from ._gltf_edit import Blob
from ._gltf_nodes import as_trs, continuous_hemisphere, head_local_rotations
from ._gltf_read import target_names

_IMAGE_TO_GLTF = np.diag([1.0, -1.0, -1.0])  # C: image (x right, y down, z away) <-> glTF


# --------------------------------------------------------------------------- checks


def _check_names(names, weights: Weights) -> None:
    if tuple(weights.names) != tuple(names):
        missing = [n for n in names if n not in weights.names]
        extra = [n for n in weights.names if n not in names]
        raise RigError(
            f"weights must be named by the rig's targets, in rig order {list(names)}; "
            f"got {list(weights.names)} (missing {missing}, extra {extra}); retarget them first"
        )


def _check_poses(poses: Poses | None, weights: Weights) -> None:
    if poses is not None and poses.n_frames != weights.n_frames:
        raise InputError(
            f"poses must have one frame per weights frame ({weights.n_frames}); got {poses.n_frames}"
        )


def _check_eyes(eyes, weights: Weights) -> None:
    if eyes is not None and np.shape(eyes) != (weights.n_frames, 2, 3, 3):
        raise InputError(f"eyes must have shape ({weights.n_frames}, 2, 3, 3) (left, right rotations per frame); "
                         f"got {np.shape(eyes)}")


# --------------------------------------------------------------------------- rotations


def head_rotations(poses: Poses) -> np.ndarray:
    """(n_frames, 3, 3) float: head rotations in glTF axes from image-space poses.

    2D rotations turn about the image z axis; NaN frames hold the previous valid rotation
    (leading ones the first valid; none at all: identity).
    """
    rotations = _fill_invalid(_as_3d(np.asarray(poses.rotations, dtype=float)))
    return _IMAGE_TO_GLTF @ rotations @ _IMAGE_TO_GLTF  # R_gltf = C R C (C is its own inverse)


def _pose_quaternions(poses: Poses) -> np.ndarray:
    """Unit quaternions ``(n_frames, 4)`` (x, y, z, w) in glTF axes from image-space rotations."""
    rot = head_rotations(poses)
    quats = Rotation.from_matrix(rot).as_quat() if len(rot) else np.zeros((0, 4))
    return continuous_hemisphere(quats)


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


# --------------------------------------------------------------------------- channels


def _times(blob: Blob, weights: Weights) -> int:
    return blob.add(weights.times.astype(np.float32), "SCALAR", bounds=True)


def _weights_output(blob: Blob, values: np.ndarray) -> int:
    # glTF morph-weight output: n_frames · n_targets scalars, frame-major.
    return blob.add(np.nan_to_num(values, nan=0.0).astype(np.float32).reshape(-1), "SCALAR")


def _animation(times: int, weight_outputs, name: str) -> pygltflib.Animation:
    """An animation with one LINEAR ``weights`` channel per ``(node, output accessor)``."""
    samplers, channels = [], []
    for node, output in weight_outputs:
        samplers.append(pygltflib.AnimationSampler(input=times, output=output, interpolation="LINEAR"))
        channels.append(pygltflib.AnimationChannel(
            sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path="weights")))
    return pygltflib.Animation(name=name, samplers=samplers, channels=channels)


def _add_rotation(animation: pygltflib.Animation, blob: Blob, times: int, node: int,
                  quats: np.ndarray) -> None:
    output = blob.add(quats.astype(np.float32), "VEC4")
    animation.samplers.append(pygltflib.AnimationSampler(input=times, output=output, interpolation="LINEAR"))
    animation.channels.append(pygltflib.AnimationChannel(
        sampler=len(animation.samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path="rotation")))


def _add_node_rotation(document, blob, animation, node: int, world: np.ndarray) -> None:
    """A rotation channel turning ``node`` by ``world (n_frames, 3, 3)`` (glTF axes) about its pivot."""
    as_trs(document.nodes[node])
    times = animation.samplers[0].input
    _add_rotation(animation, blob, times, node, head_local_rotations(document, node, world))


def _mesh_weights(mesh: pygltflib.Mesh, weights: Weights) -> np.ndarray:
    """(n_frames, n_mesh_targets): the mesh's targets in its own order; unnamed ones at rest."""
    names = target_names(mesh)
    rest = list(mesh.weights or []) + [0.0] * (len(names) - len(mesh.weights or []))
    columns = [weights.values[:, weights.names.index(n)] if n in weights.names
               else np.full(weights.n_frames, rest[k]) for k, n in enumerate(names)]
    return np.stack(columns, axis=1)
