"""VRM Animation 1.0 output (issue 37): `.vrma` files for the hand-written avatars, read back node by
node: the expression weights written are the weights given (clipped to [0, 1]), under VRM 1.0 preset
names whatever the avatar's version; the head bone turns as the poses do; the gaze turns the look-at;
the Khronos validator finds no error; `retarget` and `run` write them, and refuse a `.vrma` without a
VRM avatar in one line."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from vrm_avatars import BONES, FACE_TRANSLATION, make_vrm, read_glb

from keyshape.capture import Gaze
from keyshape.containers import Poses, Weights
from keyshape.exceptions import InputError, InputWarning
from keyshape.io import export, load_vrm

PRESETS = {"aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft", "blinkRight", "happy"}  # the test avatars'
REQUIRED_BONES = {"hips", "spine", "head", "leftUpperLeg", "leftLowerLeg", "leftFoot", "rightUpperLeg",
                  "rightLowerLeg", "rightFoot", "leftUpperArm", "leftLowerArm", "leftHand", "rightUpperArm",
                  "rightLowerArm", "rightHand"}  # VRM 1.0's required humanoid bones


def read_vrma(path) -> tuple[dict, dict, list]:
    """(the VRMC_vrm_animation extension, {(node, path): (times, values)}, the nodes) of a .vrma."""
    document, blob = read_glb(path)

    def accessor(index):
        acc = document["accessors"][index]
        view = document["bufferViews"][acc["bufferView"]]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
        assert acc["componentType"] == 5126
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        return np.frombuffer(blob, "<f4", acc["count"] * width, start).reshape(acc["count"], width).squeeze()

    (animation,) = document["animations"]
    tracks = {}
    for channel in animation["channels"]:
        sampler = animation["samplers"][channel["sampler"]]
        assert sampler["interpolation"] == "LINEAR"
        tracks[channel["target"]["node"], channel["target"]["path"]] = (accessor(sampler["input"]),
                                                                         accessor(sampler["output"]))
    assert document["extensionsUsed"] == ["VRMC_vrm_animation"]
    return document["extensions"]["VRMC_vrm_animation"], tracks, document["nodes"]


def expression_track(extension, tracks, group, name) -> np.ndarray:
    node = extension["expressions"][group][name]["node"]
    _, moved = tracks[node, "translation"]
    np.testing.assert_array_equal(moved[:, 1:], 0.0)  # the weight is x alone
    return moved[:, 0]


@pytest.mark.parametrize("version", ["1.0", "0.x"])
def test_expression_weights_read_back(tmp_path, version):
    """Each expression's track is its weight, clipped to [0, 1]; the presets are named in VRM 1.0's
    spelling on both avatars (a 0.x `A` is `aa`, `Joy` is `happy`), custom ones as the avatar names them;
    the look and the perfect-sync morph no expression binds are left out, with a warning naming them."""
    avatar = make_vrm(tmp_path / "avatar.vrm", version, perfect_sync=True)
    vrm = load_vrm(avatar.path)
    values = np.random.default_rng(37).uniform(0.0, 1.4, (25, vrm.rig.n_targets))
    weights = Weights(values, vrm.rig.names, fps=24.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = export(weights, tmp_path / "take.vrma", source=avatar.path)
    (warning,) = [w for w in caught if issubclass(w.category, InputWarning)]
    look = "lookUp" if version == "1.0" else "LookUp"
    assert f"'{look}'" in str(warning.message) and "'mouthSmileLeft'" in str(warning.message)
    extension, tracks, _ = read_vrma(out)
    assert extension["specVersion"] == "1.0"
    smirk = "smirk" if version == "1.0" else "Smirk"
    assert set(extension["expressions"]["preset"]) == PRESETS
    assert set(extension["expressions"]["custom"]) == {smirk, "jawOpen"}
    for expression in vrm.expressions:
        if expression.preset == "lookUp":
            continue
        group, key = ("preset", expression.preset) if expression.preset else ("custom", expression.name)
        got = expression_track(extension, tracks, group, key)
        column = values[:, vrm.rig.names.index(expression.name)]
        np.testing.assert_allclose(got, np.clip(column, 0, 1), atol=1e-7, err_msg=expression.name)
        assert got.max() == 1.0 and (column > 1).any()  # the draw goes past 1: clipped
    times = tracks[extension["expressions"]["preset"]["aa"]["node"], "translation"][0]
    np.testing.assert_allclose(times, np.arange(25) / 24.0, atol=1e-6)
    # a 0.x avatar's "A" track is the one given for "A": the names are mapped, not re-ordered
    aa = vrm.name_of("aa")
    np.testing.assert_allclose(expression_track(extension, tracks, "preset", "aa"),
                               np.clip(values[:, vrm.rig.names.index(aa)], 0, 1), atol=1e-7)


def test_both_versions_write_the_same_animation(tmp_path):
    """The 1.0 and 0.x spellings of one avatar, driven alike, give the same expression tracks."""
    written = []
    for version in ("1.0", "0.x"):
        avatar = make_vrm(tmp_path / f"{version}.vrm", version)
        vrm = load_vrm(avatar.path)
        values = np.random.default_rng(3).random((10, vrm.rig.n_targets))  # the same draw, the same order
        values[:, vrm.rig.names.index(vrm.name_of("lookUp"))] = 0.0  # a look at rest: left out unsaid
        out = export(Weights(values, vrm.rig.names, 30.0), tmp_path / f"{version}.vrma", source=avatar.path)
        extension, tracks, _ = read_vrma(out)
        written.append({key: expression_track(extension, tracks, "preset", key) for key in PRESETS})
    for key in PRESETS:
        np.testing.assert_array_equal(written[0][key], written[1][key], err_msg=key)


def _turns(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Image-space head rotations: a yaw (about image y) and a nod (about image x), in radians."""
    t = np.linspace(0, 1, n)
    return np.radians(30) * np.sin(2 * np.pi * t), np.radians(15) * t


@pytest.mark.parametrize("version, skeleton", [("1.0", False), ("0.x", True), ("0.x", False)])
def test_head_bone_turns_as_the_poses(tmp_path, version, skeleton):
    """The head bone's rotation is the pose's, in glTF axes (x right, y up, z toward the viewer: the
    image's y and z flipped, so a turn about image y by θ is a turn about glTF y by −θ, about image
    x by φ one about glTF x by φ); a frame without a pose holds the one before. Rest: the VRM
    T-pose (no bone rotated), every required bone, the head at the avatar's head height (its face
    node's on the plain 1.0 avatar, its head bone's in the 0.x list of bones), or the 1.5 m
    figure's 1.45 m when the avatar names no head (the plain 0.x one)."""
    avatar = make_vrm(tmp_path / "avatar.vrm", version, skeleton=skeleton)
    vrm = load_vrm(avatar.path)
    n = 12
    yaw, nod = _turns(n)
    def about(axis, angles):
        return Rotation.from_rotvec(np.outer(angles, np.eye(3)[axis])).as_matrix()

    image = about(1, yaw) @ about(0, nod)
    image[5] = np.nan  # no face in frame 5
    poses = Poses(image, np.zeros((n, 3)), np.ones(n))
    out = export(Weights(np.zeros((n, vrm.rig.n_targets)), vrm.rig.names, 30.0), tmp_path / "t.vrma",
                 source=avatar.path, poses=poses)
    extension, tracks, nodes = read_vrma(out)
    bones = {name: entry["node"] for name, entry in extension["humanoid"]["humanBones"].items()}
    assert REQUIRED_BONES <= set(bones) and not {"leftEye", "rightEye"} & set(bones)
    assert all("rotation" not in nodes[i] and "scale" not in nodes[i] for i in bones.values())
    _, quats = tracks[bones["head"], "rotation"]
    assert [key for key in tracks if key[1] == "rotation"] == [(bones["head"], "rotation")]
    expected = about(1, -yaw) @ about(0, nod)
    expected[5] = expected[4]
    np.testing.assert_allclose(Rotation.from_quat(quats).as_matrix(), expected, atol=1e-6)
    assert all(np.dot(quats[i], quats[i + 1]) > 0 for i in range(n - 1))  # one hemisphere: short slerps

    def height(bone):  # world y: the translations down the chain from the hips
        parent = {child: i for i, node in enumerate(nodes) for child in node.get("children", [])}
        y, node = 0.0, bones[bone]
        while node is not None:
            y, node = y + nodes[node]["translation"][1], parent.get(node)
        return y

    named = {"1.0": FACE_TRANSLATION[1], "0.x": {b: p for b, _, p in BONES}["head"][1] if skeleton else 1.45}
    assert height("head") == pytest.approx(named[version], abs=1e-6)
    assert 0 < height("hips") < height("spine") < height("head")


def test_gaze_turns_the_look_at(tmp_path):
    """Eyes turned toward the subject's left and up: the look-at turns toward the avatar's left
    (+yaw about +Y) and up (negative pitch about X: VRM's pitch is positive downward), by the
    eyes' angles; a frame without a face looks ahead."""
    avatar = make_vrm(tmp_path / "avatar.vrm", "0.x")
    vrm = load_vrm(avatar.path)
    n = 6
    yaw = np.repeat(np.linspace(0, 25, n)[:, None], 2, axis=1)
    pitch = np.repeat(np.linspace(0, 10, n)[:, None], 2, axis=1)
    yaw[2] = pitch[2] = np.nan
    eyes = Gaze(yaw, pitch).rotations()
    out = export(Weights(np.zeros((n, vrm.rig.n_targets)), vrm.rig.names, 30.0), tmp_path / "t.vrma",
                 source=avatar.path, eyes=eyes)
    extension, tracks, nodes = read_vrma(out)
    look = extension["lookAt"]["node"]
    assert look in nodes[extension["humanoid"]["humanBones"]["head"]["node"]]["children"]
    assert extension["lookAt"]["offsetFromHeadBone"] == nodes[look]["translation"]
    assert nodes[look]["translation"][1] > 0 and "rotation" not in nodes[look]  # rest: looking ahead, +Z
    _, quats = tracks[look, "rotation"]
    angles = np.degrees(Rotation.from_quat(quats).as_euler("YXZ"))  # three.js's Euler order for VRM look-at
    expected_yaw, expected_pitch = np.linspace(0, 25, n), -np.linspace(0, 10, n)
    expected_yaw[2] = expected_pitch[2] = 0.0
    np.testing.assert_allclose(angles[:, 0], expected_yaw, atol=1e-4)
    np.testing.assert_allclose(angles[:, 1], expected_pitch, atol=1e-4)
    np.testing.assert_allclose(angles[:, 2], 0.0, atol=1e-4)


@pytest.mark.validator
@pytest.mark.parametrize("version", ["1.0", "0.x"])
def test_the_khronos_validator_finds_no_error(tmp_path, version):
    from gltf_validator import validate

    avatar = make_vrm(tmp_path / "avatar.vrm", version, perfect_sync=True)
    vrm = load_vrm(avatar.path)
    n = 8
    yaw, nod = _turns(n)
    poses = Poses(Rotation.from_euler("YX", np.stack([yaw, nod], 1)).as_matrix(), np.zeros((n, 3)), np.ones(n))
    eyes = Gaze(np.full((n, 2), 10.0), np.zeros((n, 2))).rotations()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        out = export(Weights(np.random.default_rng(0).random((n, vrm.rig.n_targets)), vrm.rig.names, 30.0),
                     tmp_path / "take.vrma", source=avatar.path, poses=poses, eyes=eyes)
    glb = out.with_suffix(".glb")
    glb.write_bytes(out.read_bytes())
    report = validate(glb)
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"]


@pytest.mark.parametrize("case", ["no avatar", "not a vrm", "suffix", "no expression", "no frames", "poses",
                                  "negative"])
def test_refusals_write_nothing(tmp_path, case):
    """A .vrma that cannot be right is refused in one line, and nothing is written."""
    avatar = make_vrm(tmp_path / "avatar.vrm", "1.0")
    vrm = load_vrm(avatar.path)
    weights = Weights(np.zeros((4, vrm.rig.n_targets)), vrm.rig.names, 30.0)
    out, source, poses = tmp_path / "out" / "t.vrma", avatar.path, None
    if case == "no avatar":
        source = None
    elif case == "not a vrm":
        source = tmp_path / "avatar.glb"
        source.write_bytes(avatar.path.read_bytes())
    elif case == "suffix":
        out = tmp_path / "out" / "t.glb"
        with pytest.raises(InputError, match=r"t\.glb.*\.vrma"):
            from keyshape.io._vrma_write import write_vrma

            write_vrma(out, weights, avatar.path)
        assert not out.parent.exists()
        return
    elif case == "no expression":
        weights = Weights(np.zeros((4, 2)), ("jawOpen_x", "other"), 30.0)
    elif case == "no frames":
        weights = Weights(np.zeros((0, vrm.rig.n_targets)), vrm.rig.names, 30.0)
    elif case == "negative":  # the writers' rule: 0..MAX_WEIGHT or NaN
        values = np.zeros((4, vrm.rig.n_targets))
        values[2, 1] = -0.5
        weights = Weights(values, vrm.rig.names, 30.0)
    else:
        poses = Poses(np.tile(np.eye(3), (3, 1, 1)), np.zeros((3, 3)), np.ones(3))
    with pytest.raises(InputError) as error:
        export(weights, out, source=source, poses=poses)
    assert "\n" not in str(error.value)
    assert not out.parent.exists() or not any(out.parent.iterdir())


def _weights_csv(tmp_path, names, n=9):
    from keyshape.io import save_weights_csv

    values = np.random.default_rng(5).random((n, len(names)))
    save_weights_csv(Weights(values, names, 30.0), tmp_path / "w.csv")
    return tmp_path / "w.csv", values


def test_retarget_writes_a_vrma(tmp_path):
    """`keyshape retarget W.csv --rig avatar.vrm -o take.vrma -o take.glb`: both written, the .vrma's
    tracks the CSV's columns under their 1.0 names."""
    from keyshape.cli import main

    avatar = make_vrm(tmp_path / "avatar.vrm", "0.x")
    vrm = load_vrm(avatar.path)
    csv, values = _weights_csv(tmp_path, vrm.rig.names)
    code = main(["retarget", str(csv), "--rig", str(avatar.path), "-o", str(tmp_path / "take.vrma"),
                 "-o", str(tmp_path / "take.glb"), "-q"])
    assert code == 0 and (tmp_path / "take.glb").is_file()
    extension, tracks, _ = read_vrma(tmp_path / "take.vrma")
    for preset, name in (("aa", "A"), ("oh", "O"), ("blinkLeft", "Blink_L"), ("happy", "Joy")):
        np.testing.assert_allclose(expression_track(extension, tracks, "preset", preset),
                                   values[:, vrm.rig.names.index(name)], atol=1e-6)


@pytest.mark.parametrize("rig", ["none", "glb"])
def test_retarget_refuses_a_vrma_without_a_vrm_avatar(tmp_path, capsys, rig):
    from keyshape.cli import main

    avatar = make_vrm(tmp_path / "avatar.vrm", "1.0")
    csv, _ = _weights_csv(tmp_path, load_vrm(avatar.path).rig.names)
    words = ["retarget", str(csv), "-o", str(tmp_path / "take.vrma")]
    if rig == "glb":
        glb = tmp_path / "avatar.glb"
        glb.write_bytes(avatar.path.read_bytes())
        words += ["--rig", str(glb)]
    else:
        (tmp_path / "map.json").write_text(json.dumps({"aa": {"aa": 1.0}}))
        words += ["--map", str(tmp_path / "map.json")]
    assert main(words) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]  # after the usage
    assert len(errors) == 1 and "take.vrma" in errors[0] and "--rig avatar.vrm" in errors[0], errors
    assert not (tmp_path / "take.vrma").exists()


@pytest.mark.slow
def test_run_writes_animation_vrma(demo_clip, tmp_path):
    """`keyshape run CLIP --keys K --rig avatar.vrm --map MAP`: animation.vrma beside the other outputs,
    recorded in take.json; its tracks are the solved weights through the map, its head turns."""
    from keyshape.cli import main
    from keyshape.containers import KeyShapes
    from keyshape.datasets import make_performance
    from keyshape.io import load_weights_csv, save_keys

    avatar = make_vrm(tmp_path / "avatar.vrm", "1.0")
    perf = make_performance(n_frames=40, n_landmarks=478)
    save_keys(KeyShapes(perf.neutral, perf.key_deltas, ["a", "b", "c", "d"], perf.extreme_frames,
                        perf.key_regions, perf.regions), tmp_path / "keys.json")
    (tmp_path / "map.json").write_text(json.dumps({"a": {"aa": 1.0}, "b": {"oh": 0.5}, "c": {"blink": 1.0},
                                                   "d": {"smirk": 0.7}}))
    out = tmp_path / "take"
    assert main(["run", str(demo_clip), "--keys", str(tmp_path / "keys.json"), "--rig", str(avatar.path),
                 "--map", str(tmp_path / "map.json"), "--no-preview", "-o", str(out), "-q"]) == 0
    assert "animation.vrma" in json.loads((out / "take.json").read_text())["written"]
    weights = load_weights_csv(out / "weights.csv")
    extension, tracks, _ = read_vrma(out / "animation.vrma")
    column = weights.values[:, list(weights.names).index("a")]
    np.testing.assert_allclose(expression_track(extension, tracks, "preset", "aa"), np.clip(column, 0, 1),
                               atol=1e-5)
    column = weights.values[:, list(weights.names).index("d")]
    np.testing.assert_allclose(expression_track(extension, tracks, "custom", "smirk"),
                               np.clip(0.7 * column, 0, 1), atol=1e-5)
    head = extension["humanoid"]["humanBones"]["head"]["node"]
    _, quats = tracks[head, "rotation"]
    assert len(quats) == weights.n_frames and np.ptp(quats, axis=0).max() > 1e-3  # the head moves
    assert (head, "rotation") in tracks and extension["lookAt"]["node"] is not None
