"""Reading USD (private half of :mod:`keyshape.io.usd`): UsdSkel rigs, animations, checks.

References
----------
Pixar, *UsdSkel* schema documentation: "Blend Shapes", "Skel Animation", "Skel Binding".
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..containers import Rig
from ..exceptions import InputError, RigError
from ._pxr import pxr as _pxr

ANIMATION = "Anim"  # the SkelAnimation of files write_usd builds


class UsdAnimation(NamedTuple):
    """A blend-shape animation read back from a USD file.

    Attributes
    ----------
    names : tuple of n_targets str
    times : (n_frames,) float, seconds (time code / timeCodesPerSecond)
    weights : (n_frames, n_targets) float
    rotations : (n_frames, 4) float quaternions (x, y, z, w) of the first joint, or None
    """

    names: tuple[str, ...]
    times: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray | None


# --------------------------------------------------------------------------- reading


def open_stage(path):
    _, _, Tf, Usd, _, _, _, _ = _pxr()
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such USD file: {str(path)!r}")
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as error:
        raise InputError(f"cannot read {str(path)!r} as USD: {str(error).strip().splitlines()[-1]}") from None
    if stage is None:
        raise InputError(f"cannot read {str(path)!r} as USD")
    return stage


def read_rig(path) -> Rig:
    """Load the UsdSkel blend shapes of a USD file as one :class:`Rig`.

    Every Mesh with bound blend shapes (``skel:blendShapes`` and ``skel:blendShapeTargets``)
    is kept; meshes are concatenated (faces offset, polygons fan-triangulated) and names are
    the union of their blend-shape channel names (a mesh lacking one contributes zero deltas).
    Points and offsets are mesh-local, converted to metres (``metersPerUnit``) and to +Y up
    (``upAxis = "Z"``: ``(x, y, z) -> (x, z, −y)``). In-between shapes are ignored.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Rig

    Raises
    ------
    RigError
        If no mesh has blend shapes.
    MissingDependencyError
        Without ``usd-core``.
    """
    _, _, _, _, UsdGeom, UsdSkel, _, _ = _pxr()
    stage = open_stage(path)
    parts = [_read_mesh(prim) for prim in stage.Traverse()
             if prim.IsA(UsdGeom.Mesh) and prim.HasAPI(UsdSkel.BindingAPI)]
    parts = [p for p in parts if p is not None]
    if not parts:
        raise RigError(f"{str(path)!r} has no meshes with UsdSkel blend shapes to drive")
    rig = _concatenate(parts)
    return _to_gltf_axes(rig, UsdGeom.GetStageMetersPerUnit(stage), UsdGeom.GetStageUpAxis(stage))


def _read_mesh(prim):
    _, _, _, _, UsdGeom, UsdSkel, _, _ = _pxr()
    binding = UsdSkel.BindingAPI(prim)
    names = list(binding.GetBlendShapesAttr().Get() or [])
    targets = list(binding.GetBlendShapeTargetsRel().GetTargets())
    if not names:
        return None
    if len(names) != len(targets):
        raise RigError(f"{prim.GetPath()}: {len(names)} skel:blendShapes but {len(targets)} blendShapeTargets")
    mesh = UsdGeom.Mesh(prim)
    points = np.asarray(mesh.GetPointsAttr().Get(), dtype=float).reshape(-1, 3)
    faces = _triangulate(np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64),
                         np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64))
    stage = prim.GetStage()
    deltas = {str(n): _offsets(UsdSkel.BlendShape(stage.GetPrimAtPath(t)), len(points), t)
              for n, t in zip(names, targets)}
    return points, faces, deltas


def _offsets(shape, n_points: int, where) -> np.ndarray:
    if not shape:
        raise RigError(f"blend-shape target {where} is not a BlendShape prim")
    offsets = np.asarray(shape.GetOffsetsAttr().Get() or [], dtype=float).reshape(-1, 3)
    indices = shape.GetPointIndicesAttr().Get()
    delta = np.zeros((n_points, 3))
    if indices is None:
        if len(offsets) != n_points:
            raise RigError(f"{where}: {len(offsets)} offsets for {n_points} points and no pointIndices")
        return offsets
    delta[np.asarray(indices, dtype=np.int64)] = offsets
    return delta


def _triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons (counts, flat corner indices) into (n_faces, 3)."""
    if counts.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    starts = np.cumsum(counts) - counts
    n_triangles = np.maximum(counts - 2, 0)
    first = np.repeat(starts, n_triangles)
    k = np.arange(n_triangles.sum()) - np.repeat(np.cumsum(n_triangles) - n_triangles, n_triangles) + 1
    return np.stack([indices[first], indices[first + k], indices[first + k + 1]], axis=1)


def _concatenate(parts) -> Rig:
    names = list(dict.fromkeys(n for _, _, d in parts for n in d))
    offsets = np.cumsum([0] + [len(p) for p, _, _ in parts])
    vertices = np.concatenate([p for p, _, _ in parts])
    faces = np.concatenate([f + o for (_, f, _), o in zip(parts, offsets)])
    deltas = np.stack([np.concatenate([d.get(n, np.zeros_like(p)) for p, _, d in parts]) for n in names])
    return Rig(vertices, faces, deltas, tuple(names))


def _to_gltf_axes(rig: Rig, meters_per_unit: float, up_axis) -> Rig:
    """Metres and +Y up: scale by metersPerUnit; Z-up ``(x, y, z) -> (x, z, −y)`` (a rotation)."""
    convert = np.eye(3) * meters_per_unit
    if str(up_axis) == "Z":
        convert = convert @ np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]).T
    return Rig(rig.vertices @ convert, rig.faces, rig.deltas @ convert, rig.names)


def read_usd_animation(path) -> UsdAnimation:
    """Read back the SkelAnimation keyshape wrote (else the first) of a USD file, per time sample.

    Returns
    -------
    UsdAnimation
        ``times`` in seconds; ``rotations`` are the first joint's, when time-sampled (the head's in
        files :func:`write_usd` writes).

    Raises
    ------
    InputError
        If the file has no SkelAnimation with blend-shape weights.
    """
    _, _, _, _, _, UsdSkel, _, _ = _pxr()
    stage = open_stage(path)
    animations = [UsdSkel.Animation(p) for p in stage.Traverse() if p.IsA(UsdSkel.Animation)]
    ours = [a for a in animations if a.GetPrim().GetName() in ("keyshape", ANIMATION)]
    animation = (ours or animations or [None])[0]
    if animation is None or not animation.GetBlendShapeWeightsAttr().HasAuthoredValue():
        raise InputError(f"{str(path)!r} has no SkelAnimation with blend-shape weights")
    names = tuple(str(n) for n in animation.GetBlendShapesAttr().Get())
    attribute = animation.GetBlendShapeWeightsAttr()
    codes = attribute.GetTimeSamples()
    weights = np.array([np.asarray(attribute.Get(t), dtype=float) for t in codes]).reshape(len(codes), len(names))
    return UsdAnimation(names, np.asarray(codes, dtype=float) / stage.GetTimeCodesPerSecond(), weights,
                        _joint_rotations(animation.GetRotationsAttr()))


def _joint_rotations(attribute) -> np.ndarray | None:
    codes = attribute.GetTimeSamples()
    if not codes:
        return None
    quats = [attribute.Get(t)[0] for t in codes]
    return np.array([[*q.GetImaginary(), q.GetReal()] for q in quats], dtype=float)


def deformed_points(path, frame: int) -> np.ndarray:
    """(n_points, 3) float: the first blend-shape mesh at ``frame`` as UsdSkel computes it.

    Blend shapes only (``UsdSkel.BlendShapeQuery``, weights from the bound SkelAnimation);
    skinning and unit conversion are not applied. For checking written files.
    """
    _, _, _, Usd, _, UsdSkel, _, _ = _pxr()
    stage = open_stage(path)
    cache = UsdSkel.Cache()
    for root in (p for p in stage.Traverse() if p.IsA(UsdSkel.Root)):
        cache.Populate(UsdSkel.Root(root), Usd.TraverseInstanceProxies())
        for binding in cache.ComputeSkelBindings(UsdSkel.Root(root), Usd.TraverseInstanceProxies()):
            query = cache.GetSkelQuery(binding.GetSkeleton())
            for target in binding.GetSkinningTargets():
                return _blend_target(target, query, frame)
    raise InputError(f"{str(path)!r} has no skinned blend-shape mesh")


def _blend_target(target, query, frame: int) -> np.ndarray:
    _, _, _, Usd, UsdGeom, UsdSkel, _, _ = _pxr()
    prim = target.GetPrim()
    shapes = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(prim))
    weights = query.GetAnimQuery().ComputeBlendShapeWeights(Usd.TimeCode(frame))
    mapped = target.GetBlendShapeMapper().Remap(weights) if target.GetBlendShapeMapper() else weights
    sub = shapes.ComputeSubShapeWeights(mapped)
    points = UsdGeom.Mesh(prim).GetPointsAttr().Get()
    indices = shapes.ComputeBlendShapePointIndices()
    offsets = shapes.ComputeSubShapePointOffsets()
    ok = shapes.ComputeDeformedPoints(sub[0], sub[1], sub[2], indices, offsets, points)
    if not ok:
        raise InputError(f"UsdSkel could not deform {prim.GetPath()}")
    return np.asarray(points, dtype=float)


# --------------------------------------------------------------------------- checking


def check_usd(path) -> list[str]:
    """Problems USD's own checkers report for a file (what ``usdchecker`` runs).

    ``UsdValidation`` with every registered validator (usd-core ≥ 24.11; ``usdchecker``
    uses it), and ``UsdUtils.ComplianceChecker`` where the installed usd-core still has it.

    Returns
    -------
    list of str
        Errors, warnings and failed checks; empty when the file is clean.
    """
    _, _, _, _, _, _, UsdUtils, _ = _pxr()
    problems = _validation_errors(path)
    checker_class = getattr(UsdUtils, "ComplianceChecker", None)
    if checker_class is not None:  # removed from recent usd-core in favour of UsdValidation
        checker = checker_class(arkit=False, skipARKitRootLayerCheck=False, rootPackageOnly=False,
                                skipVariants=False, verbose=False)
        checker.CheckCompliance(str(path))
        problems += [str(p) for p in (*checker.GetErrors(), *checker.GetWarnings(), *checker.GetFailedChecks())]
    return problems


def _validation_errors(path) -> list[str]:
    _, _, _, Usd, _, _, _, _ = _pxr()
    try:
        from pxr import UsdValidation
    except ImportError:  # older usd-core: the compliance checker alone
        return []
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    errors = context.Validate(Usd.Stage.Open(str(path)))
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors]
