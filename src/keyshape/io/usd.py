"""USD: UsdSkel blend-shape rigs in, blend-shape (and head-joint) animation out.

Needs ``pip install usd-core`` (imported only in :mod:`keyshape.io._pxr`). Readers and the
checker live in :mod:`keyshape.io._usd_read`. A new file holds::

    /Character            SkelRoot (defaultPrim)
      Skel                Skeleton, one joint "head" at the origin; skel:animationSource -> Anim
      Anim                SkelAnimation: blendShapes, blendShapeWeights (time-sampled per frame),
                          the head joint's rotations (time-sampled when poses are given)
      face                Mesh bound to Skel (every point rigidly on "head"), skel:blendShapes
        <target>          BlendShape per target: offsets + pointIndices (moving points only)

Stage metadata: ``metersPerUnit = 1`` (the rig is in metres), ``upAxis = "Y"`` (glTF's axes,
so no conversion), ``timeCodesPerSecond = framesPerSecond = fps``, time code ``f`` = frame ``f``
(a variable frame rate take: frame ``f`` at ``weights.times[f] * fps``), ``startTimeCode = 0``,
``endTimeCode = n_frames − 1``. Target names become blend-shape *channel*
names as they are (tokens); the BlendShape prims get valid identifiers made from them.

References
----------
Pixar, *UsdSkel* schema documentation: "Blend Shapes", "Skel Animation", "Skel Binding".
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..containers import Poses, Rig, Weights
from ..exceptions import InputError, RigError
from ._pxr import pxr as _pxr
from ._usd_read import ANIMATION, UsdAnimation, check_usd, deformed_points, open_stage, read_rig, read_usd_animation
from .atomic import atomic_path
from .validate import check_weight_values

__all__ = ["write_usd", "animate_usd", "read_rig", "read_usd_animation", "deformed_points", "check_usd",
           "UsdAnimation", "USD_SUFFIXES"]

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
ROOT, SKELETON, MESH, JOINT = "/Character", "Skel", "face", "head"


# --------------------------------------------------------------------------- writing


def write_usd(path, rig: Rig, weights: Weights, *, poses: Poses | None = None) -> Path:
    """Write a rig and its weight animation as a UsdSkel file, atomically.

    Parameters
    ----------
    path : str or Path
        ``.usda`` (text), ``.usdc``/``.usd`` (binary crate) or ``.usdz`` (package).
    rig : Rig
        In metres, +Y up (glTF's convention; written unconverted with ``metersPerUnit = 1``).
    weights : Weights
        ``values (n_frames, n_targets)`` named exactly ``rig.names`` in order; NaN is written as 0.
    poses : Poses, optional
        Head poses in image convention (as :func:`keyshape.io.gltf.write_glb`), written as the
        time-sampled rotation of the joint ``head``, which carries every point.

    Returns
    -------
    Path

    Raises
    ------
    MissingDependencyError
        Without ``usd-core``.
    RigError, InputError
        As :func:`keyshape.io.gltf.write_glb` (names, frame counts), or a bad suffix.
    """
    from ._gltf_anim import check_names, check_poses, pose_quaternions

    path = Path(path)
    if path.suffix.lower() not in USD_SUFFIXES:
        raise InputError(f"USD output must end in one of {USD_SUFFIXES}; got {str(path)!r}")
    check_names(rig.names, weights)
    check_weight_values(path, weights.names, weights.values, weights.frame_index)
    check_poses(poses, weights)
    quats = None if poses is None else pose_quaternions(poses)
    stage = _build_stage(rig, weights, quats)
    with atomic_path(path) as tmp:
        _export(stage, tmp)
    return path


def _export(stage, tmp: Path) -> None:
    _, _, _, _, _, _, UsdUtils, _ = _pxr()
    if tmp.suffix.lower() != ".usdz":
        if not stage.GetRootLayer().Export(str(tmp)):
            raise InputError(f"USD could not write {str(tmp)!r}")
        return
    layer = tmp.with_name(tmp.stem + ".usdc")
    try:
        stage.GetRootLayer().Export(str(layer))
        if not UsdUtils.CreateNewUsdzPackage(str(layer), str(tmp)):
            raise InputError(f"USD could not package {str(tmp)!r}")
    finally:
        layer.unlink(missing_ok=True)


def _build_stage(rig: Rig, weights: Weights, quats: np.ndarray | None):
    _, _, _, Usd, _, UsdSkel, _, _ = _pxr()
    stage = Usd.Stage.CreateInMemory()
    _set_metadata(stage, weights)
    root = UsdSkel.Root.Define(stage, ROOT)
    stage.SetDefaultPrim(root.GetPrim())
    skeleton = _skeleton(stage)
    mesh = _mesh(stage, rig)
    _blend_shapes(stage, mesh, skeleton, rig)
    _animation(stage, skeleton, rig, weights, quats)
    return stage


def _set_metadata(stage, weights: Weights) -> None:
    _, _, _, _, UsdGeom, _, _, _ = _pxr()
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    _set_timing(stage, weights)


def _set_timing(stage, weights: Weights) -> None:
    stage.SetTimeCodesPerSecond(weights.fps)
    stage.SetFramesPerSecond(weights.fps)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(float(max(_time_codes(weights)[-1], 0)) if weights.n_frames else 0)


def _time_codes(weights: Weights) -> np.ndarray:
    """(n_frames,) float: each frame's time code, its time from the first frame x fps (whole
    numbers for a constant rate; a variable frame rate take keeps its own timing)."""
    codes = weights.times * weights.fps
    whole = np.round(codes)
    return np.where(np.abs(codes - whole) < 1e-6, whole, codes)


def _skeleton(stage):
    Gf, _, _, _, _, UsdSkel, _, Vt = _pxr()
    skeleton = UsdSkel.Skeleton.Define(stage, f"{ROOT}/{SKELETON}")
    skeleton.CreateJointsAttr([JOINT])
    identity = Vt.Matrix4dArray([Gf.Matrix4d(1.0)])
    skeleton.CreateBindTransformsAttr(identity)
    skeleton.CreateRestTransformsAttr(identity)
    return skeleton


def _mesh(stage, rig: Rig):
    _, _, _, _, UsdGeom, _, _, Vt = _pxr()
    mesh = UsdGeom.Mesh.Define(stage, f"{ROOT}/{MESH}")
    points = rig.vertices.astype(np.float32)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(rig.faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(rig.faces.reshape(-1).astype(np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateDoubleSidedAttr(True)
    extent = np.stack([points.min(axis=0), points.max(axis=0)]) if len(points) else np.zeros((2, 3), np.float32)
    mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(extent.astype(np.float32)))
    return mesh


def _blend_shapes(stage, mesh, skeleton, rig: Rig) -> None:
    Gf, _, Tf, _, _, UsdSkel, _, Vt = _pxr()
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
    binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    paths = []
    for identifier, delta in zip(_identifiers(rig.names, Tf), rig.deltas):
        shape = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(identifier))
        moved = np.flatnonzero(np.any(delta != 0, axis=1)).astype(np.int32)
        shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(delta[moved], dtype=np.float32)))
        shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moved))
        paths.append(shape.GetPath())
    binding.CreateBlendShapesAttr(list(rig.names))
    binding.CreateBlendShapeTargetsRel().SetTargets(paths)


def _identifiers(names, Tf) -> list[str]:
    """Valid, unique prim names made from target names."""
    out, seen = [], set()
    for name in names:
        base = Tf.MakeValidIdentifier(name)
        candidate, k = base, 1
        while candidate in seen:
            candidate, k = f"{base}_{k}", k + 1
        seen.add(candidate)
        out.append(candidate)
    return out


def _animation(stage, skeleton, rig: Rig, weights: Weights, quats: np.ndarray | None) -> None:
    Gf, _, _, Usd, _, UsdSkel, _, Vt = _pxr()
    animation = UsdSkel.Animation.Define(stage, f"{ROOT}/{ANIMATION}")
    animation.CreateJointsAttr([JOINT])
    animation.CreateBlendShapesAttr(list(rig.names))
    animation.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(0.0)]))
    animation.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1.0)]))
    values = np.nan_to_num(weights.values, nan=0.0).astype(np.float32)
    channel = animation.CreateBlendShapeWeightsAttr()
    codes = _time_codes(weights)
    for code, row in zip(codes, values):
        channel.Set(Vt.FloatArray.FromNumpy(row), Usd.TimeCode(float(code)))
    rotations = animation.CreateRotationsAttr()
    if quats is None:
        rotations.Set(Vt.QuatfArray([Gf.Quatf(1.0)]))
    for code, (x, y, z, w) in zip(codes, [] if quats is None else quats):
        rotations.Set(Vt.QuatfArray([Gf.Quatf(float(w), float(x), float(y), float(z))]), Usd.TimeCode(float(code)))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets([animation.GetPath()])


# --------------------------------------------------------------------------- an artist's stage


def animate_usd(source, weights: Weights, path, *, poses: Poses | None = None) -> Path:
    """Add the performance to an artist's own UsdSkel stage, keeping everything else.

    The stage is flattened into one layer (references and sublayers resolved); every Skeleton that
    a blend-shape mesh is bound to gets a new SkelAnimation ``keyshape`` (its ``skel:animationSource``):
    the joints hold their rest transforms, except the joint named like ``head`` (closest to the root),
    which turns by the head pose about its pivot (``Pᵀ D P R`` in skeleton space, as the glTF
    writer); the blend-shape weights are time-sampled per frame. ``timeCodesPerSecond`` and
    ``framesPerSecond`` become the take's fps; ``metersPerUnit`` and ``upAxis`` stay the stage's.

    Parameters
    ----------
    source : str or Path
        A USD file whose blend-shape meshes are bound to a Skeleton (UsdSkel plays blend shapes
        only through a skeleton's animation).
    weights : Weights
        Named by the stage's blend-shape channel names (any order, any subset; others stay 0).
    path : str or Path
        Output ``.usda``/``.usdc``/``.usd``/``.usdz`` (atomic).
    poses : Poses, optional, keyword-only
        Head poses in image convention (as :func:`keyshape.io.gltf.write_glb`).

    Returns
    -------
    Path

    Raises
    ------
    RigError
        No blend-shape mesh, one without a skeleton, or names the stage lacks. (Poses with no
        joint named like ``head`` are not written, with a warning.)
    """
    from ..schemes import head_rotations
    from ._gltf_anim import check_poses

    _, _, _, Usd, _, _, _, _ = _pxr()
    path = Path(path)
    if path.suffix.lower() not in USD_SUFFIXES:
        raise InputError(f"USD output must end in one of {USD_SUFFIXES}; got {str(path)!r}")
    check_weight_values(path, weights.names, weights.values, weights.frame_index)
    check_poses(poses, weights)
    stage = Usd.Stage.Open(open_stage(source).Flatten())
    skeletons = _bound_skeletons(stage, source)
    _check_channels(skeletons, weights, source)
    _set_timing(stage, weights)
    world = None if poses is None else _to_stage_axes(stage, head_rotations(poses, hold=True))
    for skeleton, channels in skeletons.values():
        _add_animation(stage, skeleton, channels, weights, world, source)
    with atomic_path(path) as tmp:
        _export(stage, tmp)
    return path


def _bound_skeletons(stage, source) -> dict:
    """``{skeleton path: (Skeleton, channel names)}`` for every blend-shape mesh."""
    _, _, _, _, UsdGeom, UsdSkel, _, _ = _pxr()
    found = {}
    for prim in stage.Traverse():
        if not (prim.IsA(UsdGeom.Mesh) and prim.HasAPI(UsdSkel.BindingAPI)):
            continue
        binding = UsdSkel.BindingAPI(prim)
        names = [str(n) for n in binding.GetBlendShapesAttr().Get() or []]
        if not names:
            continue
        skeleton = binding.GetInheritedSkeleton()
        if not skeleton:
            raise RigError(f"{source}: {prim.GetPath()} has blend shapes but no skeleton (skel:skeleton); "
                           "UsdSkel plays blend shapes through a skeleton's animation")
        entry = found.setdefault(str(skeleton.GetPath()), (skeleton, []))
        entry[1].extend(n for n in names if n not in entry[1])
    if not found:
        raise RigError(f"{source} has no meshes with UsdSkel blend shapes to drive")
    return found


def _check_channels(skeletons: dict, weights: Weights, source) -> None:
    known = {n for _, names in skeletons.values() for n in names}
    unknown = [n for n in weights.names if n not in known]
    if unknown:
        raise RigError(f"weights name blend shapes {source} does not have: {unknown}; it has {sorted(known)}")


def _to_stage_axes(stage, rotations: np.ndarray) -> np.ndarray:
    """glTF-axis (+Y up) rotations in the stage's axes (``upAxis = "Z"``: (x, y, z) -> (x, −z, y))."""
    _, _, _, _, UsdGeom, _, _, _ = _pxr()
    if str(UsdGeom.GetStageUpAxis(stage)) != "Z":
        return rotations
    a = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    return a @ rotations @ a.T


def _add_animation(stage, skeleton, channels, weights: Weights, world, source) -> None:
    Gf, _, _, Usd, _, UsdSkel, _, Vt = _pxr()
    joints = list(skeleton.GetJointsAttr().Get() or [])
    rest = skeleton.GetRestTransformsAttr().Get() or Vt.Matrix4dArray([Gf.Matrix4d(1.0)] * len(joints))
    translations, rotations, scales = UsdSkel.DecomposeTransforms(rest)
    animation = UsdSkel.Animation.Define(stage, skeleton.GetPath().AppendChild("keyshape"))
    animation.CreateJointsAttr(joints)
    animation.CreateTranslationsAttr(translations)
    animation.CreateScalesAttr(scales)
    animation.CreateBlendShapesAttr(channels)
    columns = [weights.values[:, weights.names.index(n)] if n in weights.names else np.zeros(weights.n_frames)
               for n in channels]
    values = np.nan_to_num(np.stack(columns, axis=1), nan=0.0).astype(np.float32)
    attribute = animation.CreateBlendShapeWeightsAttr()
    codes = _time_codes(weights)
    for code, row in zip(codes, values):
        attribute.Set(Vt.FloatArray.FromNumpy(row), Usd.TimeCode(float(code)))
    _joint_rotations_over_time(animation, skeleton, joints, rest, rotations, world, source, codes)
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets([animation.GetPath()])


def _joint_rotations_over_time(animation, skeleton, joints, rest, rotations, world, source, codes) -> None:
    Gf, _, _, Usd, _, _, _, Vt = _pxr()
    attribute = animation.CreateRotationsAttr()
    if world is None:
        attribute.Set(rotations)
        return
    head = _head_joint(joints)
    if head is None:
        warnings.warn(f"{source}: no joint named like 'head' in {skeleton.GetPath()}: the head rotation is not "
                      "written", UserWarning, stacklevel=5)
        attribute.Set(rotations)
        return
    local = _head_local(skeleton, joints, rest, head, world)
    quats = list(rotations)
    for code, (x, y, z, w) in zip(codes, local):
        quats[head] = Gf.Quatf(float(w), float(x), float(y), float(z))
        attribute.Set(Vt.QuatfArray(quats), Usd.TimeCode(float(code)))


def _head_joint(joints) -> int | None:
    from ._gltf_nodes import is_head

    heads = [k for k, joint in enumerate(joints) if is_head(str(joint).rsplit("/", 1)[-1])]
    return min(heads, key=lambda k: (str(joints[k]).count("/"), k)) if heads else None


def _head_local(skeleton, joints, rest, head: int, world: np.ndarray) -> np.ndarray:
    """(n_frames, 4) quaternions (x, y, z, w): ``Pᵀ D P R`` in skeleton space (column vectors)."""
    from scipy.spatial.transform import Rotation

    from ._gltf_nodes import continuous_hemisphere, rotation_part

    _, _, _, Usd, UsdGeom, UsdSkel, _, _ = _pxr()
    topology = UsdSkel.Topology(joints)
    skel_space = UsdSkel.ConcatJointTransforms(topology, rest)
    to_world = np.asarray(UsdGeom.Xformable(skeleton.GetPrim()).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    s = rotation_part(to_world[:3, :3].T)  # USD matrices act on row vectors: transpose
    parent = topology.GetParent(head)
    p = np.eye(3) if parent < 0 else rotation_part(np.asarray(skel_space[parent])[:3, :3].T)
    r = rotation_part(np.asarray(rest[head])[:3, :3].T)
    d = np.einsum("ji,fjk,kl->fil", s, world, s)  # D in skeleton space: Sᵀ D S
    local = np.einsum("ji,fjk,kl,lm->fim", p, d, p, r)  # Pᵀ D P R
    return continuous_hemisphere(Rotation.from_matrix(local).as_quat())
