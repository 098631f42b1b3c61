"""USD out (UsdSkel BlendShapes + SkelAnimation) and in; every file checked by USD's own validators."""

import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from keyshape.containers import Poses, Rig, Weights
from keyshape.exceptions import InputError, MissingDependencyError, RigError
from keyshape.io.rig import load_rig

pxr = pytest.importorskip("pxr", reason="usd-core not installed (pip install usd-core)")
from pxr import Usd, UsdGeom, UsdSkel  # noqa: E402

from keyshape.io import usd  # noqa: E402
from keyshape.io.usd import check_usd, deformed_points, read_rig, read_usd_animation, write_usd  # noqa: E402

C = np.diag([1.0, -1.0, -1.0])


@pytest.fixture
def rig():
    rng = np.random.default_rng(2)
    x, y = np.meshgrid(np.linspace(-0.1, 0.1, 5), np.linspace(-0.1, 0.1, 5))
    vertices = np.stack([x.ravel(), y.ravel(), 0.01 * rng.normal(size=25)], axis=1)
    quads = [(r * 5 + c, r * 5 + c + 1, r * 5 + c + 6, r * 5 + c + 5) for r in range(4) for c in range(4)]
    faces = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    deltas = rng.normal(scale=0.01, size=(3, 25, 3))
    deltas[2, 8:] = 0.0  # a target moving few points: written sparsely (pointIndices)
    return Rig(vertices, faces, deltas, ("jawOpen", "Mouth Open", "eyeBlink_L"))


@pytest.fixture
def weights(rig):
    return Weights(np.random.default_rng(3).random((30, rig.n_targets)), rig.names, fps=23.976)


def poses(n, seed=4):
    return Poses(Rotation.random(n, random_state=seed).as_matrix(), np.zeros((n, 3)), np.ones(n))


@pytest.mark.parametrize("suffix", [".usda", ".usdc", ".usd", ".usdz"])
def test_round_trip_and_validators(rig, weights, tmp_path, suffix):
    path = write_usd(tmp_path / f"anim{suffix}", rig, weights, poses=poses(weights.n_frames))
    assert check_usd(path) == []
    back = read_usd_animation(path)
    assert back.names == rig.names
    np.testing.assert_array_equal(back.weights, weights.values.astype(np.float32))
    np.testing.assert_allclose(back.times, weights.times, atol=1e-9)
    assert_same_rig(read_rig(path), rig)


def assert_same_rig(a, b, atol=1e-7):
    assert a.names == b.names
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_allclose(a.vertices, b.vertices, atol=atol)
    np.testing.assert_allclose(a.deltas, b.deltas, atol=atol)


def test_usdskel_deforms_the_points_as_the_rig(rig, weights, tmp_path):
    """UsdSkel's own blend-shape evaluation of the written file == neutral + Σ w·delta."""
    path = write_usd(tmp_path / "anim.usda", rig, weights)
    for frame in (0, 7, 29):
        np.testing.assert_allclose(deformed_points(path, frame), rig.pose(weights.values[frame:frame + 1])[0],
                                   atol=1e-5)


def test_stage_metadata(rig, weights, tmp_path):
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "anim.usda", rig, weights)))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and UsdGeom.GetStageUpAxis(stage) == "Y"
    assert stage.GetTimeCodesPerSecond() == pytest.approx(23.976)
    assert stage.GetFramesPerSecond() == pytest.approx(23.976)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 29)
    assert stage.GetDefaultPrim().GetPath() == "/Character"
    assert stage.GetDefaultPrim().IsA(UsdSkel.Root)
    shapes = [p.GetName() for p in stage.Traverse() if p.IsA(UsdSkel.BlendShape)]
    assert shapes == ["jawOpen", "Mouth_Open", "eyeBlink_L"]  # valid prim names; channels keep the names
    sparse = UsdSkel.BlendShape(stage.GetPrimAtPath("/Character/face/eyeBlink_L"))
    assert list(sparse.GetPointIndicesAttr().Get()) == list(range(8))


def test_head_rotation_on_the_head_joint(rig, weights, tmp_path):
    head = poses(weights.n_frames)
    back = read_usd_animation(write_usd(tmp_path / "anim.usda", rig, weights, poses=head))
    matrices = Rotation.from_quat(back.rotations).as_matrix()
    np.testing.assert_allclose(C @ matrices @ C, head.rotations, atol=1e-6)
    assert read_usd_animation(write_usd(tmp_path / "still.usda", rig, weights)).rotations is None


def test_nan_frames_are_neutral(rig, weights, tmp_path):
    values = weights.values.copy()
    values[4] = np.nan
    back = read_usd_animation(write_usd(tmp_path / "a.usda", rig, Weights(values, rig.names, weights.fps)))
    np.testing.assert_array_equal(back.weights[4], 0.0)


def test_bad_suffix_and_names_write_nothing(rig, weights, tmp_path):
    with pytest.raises(InputError, match="must end in one of"):
        write_usd(tmp_path / "anim.glb", rig, weights)
    with pytest.raises(RigError, match="in rig order"):
        write_usd(tmp_path / "anim.usda", rig, Weights(weights.values, rig.names[::-1], weights.fps))
    assert list(tmp_path.iterdir()) == []


def test_load_rig_reads_usd_in_metres_and_y_up(rig, tmp_path):
    """A Z-up centimetre stage, as many DCC tools write, comes in as metres, +Y up."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "cm.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdSkel.Root.Define(stage, "/Hero")
    mesh = UsdGeom.Mesh.Define(stage, "/Hero/head")
    mesh.CreatePointsAttr([(0, 0, 0), (10, 0, 0), (0, 0, 20), (10, 0, 20)])
    mesh.CreateFaceVertexCountsAttr([4])  # one quad
    mesh.CreateFaceVertexIndicesAttr([0, 1, 3, 2])
    shape = UsdSkel.BlendShape.Define(stage, "/Hero/head/up")
    shape.CreateOffsetsAttr([(0, 0, 5)])
    shape.CreatePointIndicesAttr([3])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateBlendShapesAttr(["browUp"])
    binding.CreateBlendShapeTargetsRel().SetTargets([shape.GetPath()])
    stage.Save()
    loaded = load_rig(tmp_path / "cm.usda")
    assert loaded.names == ("browUp",)
    np.testing.assert_allclose(loaded.vertices[3], [0.1, 0.2, 0.0])  # z up -> y up, cm -> m
    np.testing.assert_allclose(loaded.deltas[0, 3], [0.0, 0.05, 0.0])
    np.testing.assert_array_equal(loaded.faces, [[0, 1, 3], [0, 3, 2]])


def test_a_usd_without_blend_shapes(tmp_path):
    stage = Usd.Stage.CreateNew(str(tmp_path / "plain.usda"))
    UsdGeom.Mesh.Define(stage, "/m").CreatePointsAttr([(0, 0, 0)])
    stage.Save()
    with pytest.raises(RigError, match="no meshes with UsdSkel blend shapes"):
        load_rig(tmp_path / "plain.usda")
    with pytest.raises(InputError, match="no SkelAnimation"):
        read_usd_animation(tmp_path / "plain.usda")


def test_missing_usd_core_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pxr", None)
    with pytest.raises(MissingDependencyError, match=r'pip install "keyshape\[usd\]"'):
        usd._pxr()
    with pytest.raises(MissingDependencyError, match="usd-core is required"):
        usd.write_usd("a.usda", Rig(np.eye(3), [[0, 1, 2]], np.ones((1, 3, 3)), ("x",)),
                      Weights(np.zeros((1, 1)), ("x",), 30))


# ---------------------------------------------------------------- an artist's stage kept whole

from keyshape.io.usd import animate_usd  # noqa: E402


def test_animate_our_own_stage(rig, weights, tmp_path):
    source = write_usd(tmp_path / "hero.usda", rig, Weights(np.zeros((1, 3)), rig.names, 30))
    head = poses(weights.n_frames)
    out = animate_usd(source, weights, tmp_path / "anim.usdc", poses=head)
    assert check_usd(out) == []
    back = read_usd_animation(out)
    np.testing.assert_array_equal(back.weights, weights.values.astype(np.float32))
    np.testing.assert_allclose(C @ Rotation.from_quat(back.rotations).as_matrix() @ C, head.rotations, atol=1e-6)
    for frame in (0, 11):
        np.testing.assert_allclose(deformed_points(out, frame), rig.pose(weights.values[frame:frame + 1])[0], atol=1e-5)
    assert read_usd_animation(source).weights.shape == (1, 3)  # the source is untouched


def _z_up_character(path):
    """A centimetre, Z-up stage: SkelRoot > Skeleton (Root > Neck > Head, rest rotations) + a bound mesh."""
    from pxr import Gf, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    root = UsdSkel.Root.Define(stage, "/Hero")
    stage.SetDefaultPrim(root.GetPrim())
    skeleton = UsdSkel.Skeleton.Define(stage, "/Hero/Rig")
    skeleton.CreateJointsAttr(["Root", "Root/Neck", "Root/Neck/Head"])
    local = [Gf.Matrix4d(1.0),
             Gf.Matrix4d(Gf.Rotation(Gf.Vec3d(1, 0, 0), 90), Gf.Vec3d(0, 0, 150)),
             Gf.Matrix4d(Gf.Rotation(Gf.Vec3d(0, 0, 1), 30), Gf.Vec3d(0, 10, 0))]
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray(local))
    world = UsdSkel.ConcatJointTransforms(UsdSkel.Topology(["Root", "Root/Neck", "Root/Neck/Head"]),
                                          Vt.Matrix4dArray(local))
    skeleton.CreateBindTransformsAttr(world)
    mesh = UsdGeom.Mesh.Define(stage, "/Hero/face")
    mesh.CreatePointsAttr([(0, 0, 160), (10, 0, 160), (0, 0, 170)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
    shape = UsdSkel.BlendShape.Define(stage, "/Hero/face/smile")
    shape.CreateOffsetsAttr([(0, 0, 2)])
    shape.CreatePointIndicesAttr([2])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateBlendShapesAttr(["smile"])
    binding.CreateBlendShapeTargetsRel().SetTargets([shape.GetPath()])
    binding.CreateJointIndicesPrimvar(True, 1).Set([2])
    binding.CreateJointWeightsPrimvar(True, 1).Set([1.0])
    stage.Save()
    return path


def test_animate_a_z_up_stage_turns_its_head_joint(tmp_path):
    source = _z_up_character(tmp_path / "hero.usda")
    n = 6
    head = poses(n, seed=9)
    out = animate_usd(source, Weights(np.linspace(0, 1, n)[:, None], ("smile",), 24), tmp_path / "anim.usda",
                      poses=head)
    assert check_usd(out) == []
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    assert stage.GetTimeCodesPerSecond() == 24
    cache = UsdSkel.Cache()
    skeleton = UsdSkel.Skeleton(stage.GetPrimAtPath("/Hero/Rig"))
    query = cache.GetSkelQuery(skeleton)
    rest = np.asarray(query.ComputeJointSkelTransforms(Usd.TimeCode.Default(), atRest=True)[2])[:3, :3].T
    a = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # glTF (+Y up) -> stage (+Z up)
    for frame in range(n):
        turned = np.asarray(query.ComputeJointSkelTransforms(Usd.TimeCode(frame))[2])[:3, :3].T
        expected = a @ (C @ head.rotations[frame] @ C) @ a.T @ rest
        np.testing.assert_allclose(turned, expected, atol=1e-5)
    np.testing.assert_allclose(read_usd_animation(out).weights[:, 0], np.linspace(0, 1, n), atol=1e-7)


def test_animate_usd_needs_a_skeleton_and_known_names(rig, tmp_path):
    source = _z_up_character(tmp_path / "hero.usda")
    stage = Usd.Stage.Open(str(source))
    UsdSkel.Skeleton(stage.GetPrimAtPath("/Hero/Rig")).GetJointsAttr().Set(["Root", "Root/Neck", "Root/Neck/Skull"])
    stage.Save()
    with pytest.warns(UserWarning, match="no joint named like 'head'"):
        out = animate_usd(source, Weights(np.zeros((2, 1)), ("smile",), 24), tmp_path / "still.usda", poses=poses(2))
    assert read_usd_animation(out).rotations is None
    with pytest.raises(RigError, match=r"does not have: \['frown'\]"):
        animate_usd(source, Weights(np.zeros((2, 1)), ("frown",), 24), tmp_path / "x.usda")
    stage = Usd.Stage.Open(str(source))
    UsdSkel.BindingAPI(stage.GetPrimAtPath("/Hero/face")).GetSkeletonRel().ClearTargets(True)
    stage.Save()
    with pytest.raises(RigError, match="has blend shapes but no skeleton"):
        animate_usd(source, Weights(np.zeros((2, 1)), ("smile",), 24), tmp_path / "x.usda")
    assert not (tmp_path / "x.usda").exists()


def test_retarget_command_keeps_a_usd_rig_whole(tmp_path):
    from keyshape.cli import main
    from keyshape.io.weights_csv import save_weights_csv

    source = _z_up_character(tmp_path / "hero.usda")
    stage = Usd.Stage.Open(str(source))
    UsdGeom.Xform.Define(stage, "/Hero/Props")  # something of the artist's that must survive
    stage.Save()
    csv = save_weights_csv(Weights(np.linspace(0, 1, 8)[:, None], ("grin",), 24), tmp_path / "w.csv")
    (tmp_path / "map.json").write_text('{"grin": {"smile": 0.5}}')
    out = tmp_path / "anim.usdc"
    assert main(["retarget", str(csv), "--rig", str(source), "--map", str(tmp_path / "map.json"), "-o", str(out),
                 "-o", str(tmp_path / "anim.glb"), "-q"]) == 0
    written = Usd.Stage.Open(str(out))
    assert written.GetPrimAtPath("/Hero/Props") and written.GetPrimAtPath("/Hero/Rig/keyshape")
    np.testing.assert_allclose(read_usd_animation(out).weights[:, 0], 0.5 * np.linspace(0, 1, 8), atol=1e-6)
    assert check_usd(out) == []
    from gltf_validator import validate

    report = validate(tmp_path / "anim.glb")  # a USD rig to glTF: a new file from its blend shapes
    assert (report["numErrors"], report["numWarnings"]) == (0, 0), report["messages"]
