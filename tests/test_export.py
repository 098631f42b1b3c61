"""Exports by suffix or format, and the two real characters driven end to end through mappings.

ICT-FaceKit (an OBJ folder in centimetres, 57 ARKit-style shapes) is driven through a key -> ARKit
mapping; the RobotExpressive glTF (three head primitives sharing 3 targets, skinned body, 14
animations) through a key -> 3-target mapping. Both are exported to every format and checked:
weights read back, vertices recomputed from the written files, Khronos validator and USD validators.
"""

import json
import tarfile
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from scipy.spatial.transform import Rotation

from keyshape.cli import main
from keyshape.containers import Poses, Weights
from keyshape.exceptions import InputError
from keyshape.io import Format, export, format_of
from keyshape.io.gltf import read_glb_animation
from keyshape.io.livelink import LIVELINK_NAMES, read_livelink_csv
from keyshape.io.rig import load_rig
from keyshape.io.weights_csv import load_weights_csv, save_weights_csv
from keyshape.targets import Mapping, retarget

from gltf_validator import validate

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
ICT = SHARED / "ict-facekit" / "ICT-FaceKit_FaceXModel_neutral_and_expressions.tar.xz"
ROBOT = SHARED / "robot-expressive" / "RobotExpressive.glb"
KEYS = ("upper_00", "upper_01", "upper_02", "upper_03", "lower_00", "lower_01", "lower_02", "lower_03")
ICT_MAP = {
    "upper_00": {"browInnerUp_L": 1.0, "browInnerUp_R": 1.0, "browOuterUp_L": 0.6, "browOuterUp_R": 0.6},
    "upper_01": {"browDown_L": 0.8, "browDown_R": 0.8},
    "upper_02": {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0},
    "upper_03": {"eyeWide_L": 0.7, "eyeWide_R": 0.7},
    "lower_00": {"jawOpen": 0.8, "mouthFunnel": 0.3},
    "lower_01": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0, "cheekSquint_L": 0.4, "cheekSquint_R": 0.4},
    "lower_02": {"mouthFrown_L": 1.0, "mouthFrown_R": 1.0},
    "lower_03": {"mouthPucker": 1.0},
}
ROBOT_MAP = {"upper_00": {"Surprised": 1.0}, "upper_01": {"Angry": 0.7}, "lower_00": {"Surprised": 0.5},
             "lower_01": {"Sad": 1.0, "Angry": 0.2}, "lower_02": {"Angry": 1.0}}


def _clean(path):
    report = validate(path)
    assert (report["numErrors"], report["numWarnings"]) == (0, 0), report["messages"]


@pytest.fixture(scope="module")
def key_weights():
    """A take's key weights: smooth, non-negative, some frames with no face (NaN)."""
    t = np.arange(72)[:, None] / 24.0
    phase = np.arange(len(KEYS))[None, :]
    values = np.clip(np.sin(2 * np.pi * (0.4 + 0.1 * phase) * t + phase), 0, None) * 0.9
    values[[5, 6]] = np.nan
    return Weights(values, KEYS, fps=24.0)


@pytest.fixture(scope="module")
def head():
    angles = np.radians(np.stack([np.linspace(-20, 20, 72), 8 * np.sin(np.arange(72) / 9), np.zeros(72)], axis=1))
    return Poses(Rotation.from_euler("YXZ", angles).as_matrix(), np.zeros((72, 3)), np.ones(72))


# ---------------------------------------------------------------- dispatch


@pytest.mark.parametrize("name, fmt, expected", [
    ("a.glb", None, Format.GLB), ("a.usda", None, Format.USD), ("a.usdc", None, Format.USD),
    ("a.usdz", None, Format.USD), ("a.csv", None, Format.CSV), ("a.csv", "livelink", Format.LIVELINK),
    ("a.usd", "usd", Format.USD), ("a.glb", Format.GLB, Format.GLB),
])
def test_format_of(name, fmt, expected):
    assert format_of(name, fmt) is expected


@pytest.mark.parametrize("name, fmt, message", [
    ("a.abc", None, "cannot tell the format of 'a.abc'"),
    ("a.glb", "livelink", r"format livelink is written to a file ending in \.csv"),
    ("a.csv", "usd", r"format usd is written to a file ending in \.usd or \.usda"),
    ("a.csv", "fbx", r"format fbx is written to a file ending in \.fbx"),
    ("a.csv", "abc", "unknown format 'abc'"),
])
def test_format_errors(name, fmt, message):
    with pytest.raises(InputError, match=message):
        format_of(name, fmt)


def test_export_needs_a_rig_for_meshes(tmp_path):
    anim = Weights(np.zeros((3, 1)), ("jawOpen",), 30)
    with pytest.raises(InputError, match="writing usd needs the rig"):
        export(anim, tmp_path / "a.usda")
    assert load_weights_csv(export(anim, tmp_path / "a.csv")).names == ("jawOpen",)
    assert read_livelink_csv(export(anim, tmp_path / "b.csv", format="livelink")).weights.n_frames == 3


# ---------------------------------------------------------------- ICT-FaceKit through a key -> ARKit mapping


@pytest.fixture(scope="session")
def ict_folder(request, tmp_path_factory):
    if not ICT.is_file():
        pytest.skip(f"{ICT} not present (shared data)")
    cache = getattr(request.config, "cache", None)
    base = cache.mkdir("ict-facekit") if cache is not None else tmp_path_factory.mktemp("ict")
    done = base / f".extracted-{ICT.stat().st_size}"
    if not done.exists():
        with tarfile.open(ICT) as archive:
            archive.extractall(base, filter="data")
        done.touch()
    return base / "FaceXModel"


@pytest.fixture(scope="session")
def ict(ict_folder):
    return load_rig(ict_folder, unit=0.01)  # the OBJs are in centimetres


def test_ict_rig_loads_in_metres(ict):
    assert ict.n_vertices == 26719 and ict.n_targets == 57
    assert "jawOpen" in ict.names and "eyeBlink_L" in ict.names
    height = np.ptp(ict.vertices[:, 1])
    assert 0.2 < height < 0.5  # a head, in metres, +Y up
    assert np.abs(ict.deltas).max() < 0.05


def test_ict_driven_through_an_arkit_mapping(ict, ict_folder, key_weights, head, tmp_path):
    mapping = Mapping.from_dict(ICT_MAP, targets=ict)
    anim = retarget(key_weights, mapping)
    assert anim.names == ict.names
    expected = ict.pose(anim.values)

    glb = export(anim, tmp_path / "ict.glb", rig=ict, poses=head)
    _clean(glb)
    back = read_glb_animation(glb)
    np.testing.assert_array_equal(back.weights, np.nan_to_num(anim.values).astype(np.float32))
    stored = load_rig(glb)
    np.testing.assert_allclose(stored.pose(back.weights), expected, atol=1e-5)
    document = pygltflib.GLTF2().load(str(glb))
    sparse = [document.accessors[t["POSITION"]].sparse is not None for t in document.meshes[0].primitives[0].targets]
    assert sum(sparse) > 40  # most ICT shapes move a small part of the head: stored sparsely

    from keyshape.io.usd import check_usd, deformed_points, read_usd_animation

    usd = export(anim, tmp_path / "ict.usdc", rig=ict, poses=head)
    assert check_usd(usd) == []
    np.testing.assert_array_equal(read_usd_animation(usd).weights, np.nan_to_num(anim.values).astype(np.float32))
    for frame in (0, 30, 71):
        np.testing.assert_allclose(deformed_points(usd, frame), expected[frame], atol=1e-5)

    live = read_livelink_csv(export(anim, tmp_path / "ict_livelink.csv", format="livelink", poses=head), fps=24)
    column = dict(zip(LIVELINK_NAMES, live.weights.values.T))
    jaw = np.nan_to_num(anim.values[:, ict.names.index("jawOpen")])
    np.testing.assert_allclose(column["JawOpen"], np.clip(jaw, 0, 1), atol=1e-6)
    browinner = np.nan_to_num(key_weights.values[:, 0])  # both halves at gain 1: the mean is the key weight
    np.testing.assert_allclose(column["BrowInnerUp"], np.clip(browinner, 0, 1), atol=1e-6)
    np.testing.assert_allclose(np.degrees(live.rotations[:, 0]), -np.linspace(-20, 20, 72), atol=1e-3)


def test_ict_through_the_command_line(ict_folder, key_weights, tmp_path):
    weights_csv = save_weights_csv(key_weights, tmp_path / "weights.csv")
    (tmp_path / "arkit.json").write_text(json.dumps(ICT_MAP))
    outs = [tmp_path / "face.glb", tmp_path / "face.usda", tmp_path / "face_weights.csv"]
    args = ["retarget", str(weights_csv), "--rig", str(ict_folder), "--rig-unit", "cm", "--map",
            str(tmp_path / "arkit.json"), "-q"]
    assert main(args + [a for out in outs for a in ("-o", str(out))]) == 0
    _clean(outs[0])
    from keyshape.io.usd import check_usd

    assert check_usd(outs[1]) == []
    written = load_weights_csv(outs[2])
    assert written.names[0] == "PupilDilate_L" and written.n_channels == 57
    live = tmp_path / "take_livelink.csv"
    assert main(["retarget", str(weights_csv), "--map", str(tmp_path / "arkit.json"), "--format", "livelink",
                 "-o", str(live), "-q"]) == 0  # Live Link needs no rig
    assert read_livelink_csv(live).weights.n_frames == key_weights.n_frames


# ---------------------------------------------------------------- the robot through a 3-target mapping


needs_robot = pytest.mark.skipif(not ROBOT.is_file(), reason=f"{ROBOT} not present (shared data)")


def _synthetic_track(path, poses: Poses, fps: float):
    """478 landmarks turned by ``poses`` (image axes), in pixels: what `track` would write."""
    rng = np.random.default_rng(11)
    face = rng.normal(size=(478, 3)) * [60.0, 80.0, 40.0]
    points = np.einsum("fij,pj->fpi", poses.rotations, face) + [320.0, 240.0, 0.0]
    np.savez(path, points=points, fps=fps)
    return path


@needs_robot
def test_robot_driven_through_a_three_target_mapping(key_weights, head, tmp_path):
    weights_csv = save_weights_csv(key_weights, tmp_path / "weights.csv")
    (tmp_path / "robot_map.json").write_text(json.dumps(ROBOT_MAP))
    track = _synthetic_track(tmp_path / "track.npz", head, key_weights.fps)
    outs = [tmp_path / "robot.glb", tmp_path / "robot.usda", tmp_path / "robot.csv"]
    assert main(["retarget", str(weights_csv), "--rig", str(ROBOT), "--map", str(tmp_path / "robot_map.json"),
                 "--track", str(track), "-q", *[a for out in outs for a in ("-o", str(out))]]) == 0
    rig = load_rig(ROBOT)
    anim = retarget(load_weights_csv(weights_csv), Mapping.from_dict(ROBOT_MAP, targets=rig))

    _clean(outs[0])
    document = pygltflib.GLTF2().load(str(outs[0]))
    assert len(document.animations) == 15 and len(document.skins) == 4  # the robot, kept whole
    (rotation,) = [c for c in document.animations[0].channels if c.target.path == "rotation"]  # keyshape's, first
    assert document.nodes[rotation.target.node].name == "Head"
    back = read_glb_animation(outs[0])
    assert back.names == ("Angry", "Surprised", "Sad")
    np.testing.assert_allclose(back.weights, anim.values, atol=1e-6)
    np.testing.assert_allclose(load_rig(outs[0]).pose(back.weights), rig.pose(anim.values), atol=1e-5)

    from keyshape.io.usd import check_usd, deformed_points

    assert check_usd(outs[1]) == []
    np.testing.assert_allclose(deformed_points(outs[1], 40), rig.pose(anim.values[40:41])[0], atol=1e-5)
    np.testing.assert_allclose(load_weights_csv(outs[2]).values, anim.values, atol=1e-6)


@needs_robot
def test_robot_without_a_mapping_lists_the_missing_targets(key_weights, tmp_path):
    weights_csv = save_weights_csv(key_weights, tmp_path / "weights.csv")
    assert main(["retarget", str(weights_csv), "--rig", str(ROBOT), "-o", str(tmp_path / "x.glb"), "-q"]) == 1
    assert not (tmp_path / "x.glb").exists()


def test_rig_is_required_for_meshes(key_weights, tmp_path, capsys):
    weights_csv = save_weights_csv(key_weights, tmp_path / "weights.csv")
    assert main(["retarget", str(weights_csv), "-o", str(tmp_path / "x.glb")]) == 2  # a usage error
    assert "--rig is required" in capsys.readouterr().err
