import json

import numpy as np
import pygltflib
import pytest
from scipy.spatial.transform import Rotation

from keyshape.containers import KeyShapes, Poses, Rig, Weights
from keyshape.exceptions import InputError, RigError
from keyshape.io import gltf as gltf_io
from keyshape.io.gltf import read_glb_animation, write_glb
from keyshape.rig import load_rig, rig_from_keyshapes
from keyshape.schemes import face_triangles

from gltf_validator import validate

C = np.diag([1.0, -1.0, -1.0])  # image axes <-> glTF axes


@pytest.fixture
def rig():
    """A small grid face with three targets (metres, glTF axes)."""
    rng = np.random.default_rng(2)
    x, y = np.meshgrid(np.linspace(-0.1, 0.1, 5), np.linspace(-0.1, 0.1, 5))
    vertices = np.stack([x.ravel(), y.ravel(), 0.01 * rng.normal(size=25)], axis=1)
    quads = [(r * 5 + c, r * 5 + c + 1, r * 5 + c + 6, r * 5 + c + 5) for r in range(4) for c in range(4)]
    faces = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    deltas = rng.normal(scale=0.01, size=(3, 25, 3))
    return Rig(vertices, faces, deltas, ("Angry", "Surprised", "Sad"))


@pytest.fixture
def weights(rig):
    rng = np.random.default_rng(3)
    return Weights(rng.random((40, rig.n_targets)), rig.names, fps=29.97)


def random_poses(n_frames, seed=4):
    rotations = Rotation.random(n_frames, random_state=seed).as_matrix()
    return Poses(rotations, np.zeros((n_frames, 3)), np.ones(n_frames))


def test_weights_round_trip(rig, weights, tmp_path):
    path = write_glb(tmp_path / "anim.glb", rig, weights)
    names, times, values, rotations = read_glb_animation(path)
    assert names == rig.names and rotations is None
    np.testing.assert_array_equal(times, weights.times.astype(np.float32))
    np.testing.assert_array_equal(values, weights.values.astype(np.float32))


def test_deformed_vertices_from_the_file_match_the_rig(rig, weights, tmp_path):
    path = write_glb(tmp_path / "anim.glb", rig, weights)
    stored = load_rig(path)  # base + targets read back from the file
    animation = read_glb_animation(path)
    np.testing.assert_allclose(stored.pose(animation.weights), rig.pose(weights.values), atol=1e-5)


def test_document_structure(rig, weights, tmp_path):
    document = pygltflib.GLTF2().load(str(write_glb(tmp_path / "anim.glb", rig, weights)))
    (mesh,) = document.meshes
    (primitive,) = mesh.primitives
    assert mesh.extras == {"targetNames": list(rig.names)}
    assert mesh.weights == [0.0] * rig.n_targets
    assert len(primitive.targets) == rig.n_targets
    assert document.nodes[0].name == "face" and document.nodes[0].mesh == 0
    (animation,) = document.animations
    (channel,) = animation.channels
    assert channel.target.path == "weights" and channel.target.node == 0
    sampler = animation.samplers[channel.sampler]
    assert sampler.interpolation == "LINEAR"
    assert document.accessors[sampler.output].count == weights.n_frames * rig.n_targets
    time = document.accessors[sampler.input]
    assert time.min == [0.0] and time.max == pytest.approx([(weights.n_frames - 1) / weights.fps])
    position = document.accessors[primitive.attributes.POSITION]
    assert position.min == pytest.approx(rig.vertices.min(axis=0).tolist())


def test_nan_weights_are_written_as_neutral(rig, weights, tmp_path):
    values = weights.values.copy()
    values[[0, 7]] = np.nan
    path = write_glb(tmp_path / "anim.glb", rig, Weights(values, rig.names, weights.fps))
    written = read_glb_animation(path).weights
    np.testing.assert_array_equal(written[[0, 7]], 0.0)
    assert validate(path)["numErrors"] == 0


def test_rotation_channel_round_trip(rig, weights, tmp_path):
    poses = random_poses(weights.n_frames)
    path = write_glb(tmp_path / "head.glb", rig, weights, poses=poses)
    quats = read_glb_animation(path).rotations
    assert quats.shape == (weights.n_frames, 4)
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-6)
    assert (np.sum(quats[1:] * quats[:-1], axis=1) >= 0).all()  # one hemisphere: short LINEAR paths
    back = C @ Rotation.from_quat(quats).as_matrix() @ C  # glTF -> image convention
    np.testing.assert_allclose(back, poses.rotations, atol=1e-6)


def test_image_rotation_becomes_gltf_rotation(rig, weights, tmp_path):
    """Turning the head to the image's right (about image y, down) is about glTF -y."""
    n = weights.n_frames
    turn = Rotation.from_euler("y", 30, degrees=True).as_matrix()  # in image axes
    poses = Poses(np.tile(turn, (n, 1, 1)), np.zeros((n, 3)), np.ones(n))
    quats = read_glb_animation(write_glb(tmp_path / "turn.glb", rig, weights, poses=poses)).rotations
    expected = Rotation.from_euler("y", -30, degrees=True).as_quat()
    np.testing.assert_allclose(quats, np.tile(expected, (n, 1)), atol=1e-6)


def test_2d_poses_rotate_about_z(rig, weights, tmp_path):
    n = weights.n_frames
    angles = np.linspace(-0.5, 0.5, n)
    c, s = np.cos(angles), np.sin(angles)
    rotations = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], axis=1)
    poses = Poses(rotations, np.zeros((n, 2)), np.ones(n))
    quats = read_glb_animation(write_glb(tmp_path / "roll.glb", rig, weights, poses=poses)).rotations
    # image y is down, so a counter-clockwise image angle is clockwise about glTF +Z
    np.testing.assert_allclose(Rotation.from_quat(quats).as_rotvec(), np.outer(-angles, [0, 0, 1]), atol=1e-6)


def test_nan_poses_hold_the_previous_rotation(rig, weights, tmp_path):
    poses = random_poses(weights.n_frames)
    rotations = poses.rotations.copy()
    rotations[[0, 1, 10, 11, 12]] = np.nan
    holed = Poses(rotations, poses.translations, poses.scales)
    quats = read_glb_animation(write_glb(tmp_path / "holes.glb", rig, weights, poses=holed)).rotations
    matrices = C @ Rotation.from_quat(quats).as_matrix() @ C
    np.testing.assert_allclose(matrices[[0, 1]], rotations[[2, 2]], atol=1e-6)  # leading: first valid
    np.testing.assert_allclose(matrices[10:13], rotations[[9, 9, 9]], atol=1e-6)
    np.testing.assert_allclose(matrices[13:], rotations[13:], atol=1e-6)


def test_all_nan_poses_are_identity(rig, weights, tmp_path):
    n = weights.n_frames
    poses = Poses(np.full((n, 3, 3), np.nan), np.zeros((n, 3)), np.ones(n))
    quats = read_glb_animation(write_glb(tmp_path / "none.glb", rig, weights, poses=poses)).rotations
    np.testing.assert_allclose(quats, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))


@pytest.mark.validator
@pytest.mark.parametrize("with_poses", [False, True])
def test_khronos_validator_is_clean(rig, weights, tmp_path, with_poses):
    poses = random_poses(weights.n_frames) if with_poses else None
    report = validate(write_glb(tmp_path / "anim.glb", rig, weights, poses=poses))
    assert (report["numErrors"], report["numWarnings"]) == (0, 0), report["messages"]


@pytest.mark.validator
def test_khronos_validator_on_the_default_face_character(tmp_path):
    """MediaPipe's tesselation over 478 landmarks (irises unused by any triangle)."""
    rng = np.random.default_rng(5)
    neutral = rng.normal(size=(478, 3)) * [80.0, 100.0, 30.0] + [320.0, 240.0, 0.0]
    keys = KeyShapes(neutral, rng.normal(size=(4, 478, 3)), ("upper_00", "upper_01", "lower_00", "lower_01"),
                     [3, 5, 7, 9], ("upper", "upper", "lower", "lower"),
                     {"upper": np.arange(239), "lower": np.arange(239, 478)})
    face = rig_from_keyshapes(keys, face_triangles())
    weights = Weights(rng.random((30, 4)), face.names, fps=30)
    path = write_glb(tmp_path / "face.glb", face, weights, poses=random_poses(30))
    report = validate(path)
    assert (report["numErrors"], report["numWarnings"]) == (0, 0), report["messages"]


def test_single_frame_and_empty_animation(rig, tmp_path):
    one = write_glb(tmp_path / "one.glb", rig, Weights(np.full((1, 3), 0.5), rig.names, fps=24))
    assert read_glb_animation(one).weights.tolist() == [[0.5, 0.5, 0.5]]
    empty = write_glb(tmp_path / "empty.glb", rig, Weights(np.zeros((0, 3)), rig.names, fps=24))
    with pytest.raises(InputError, match="no animation with a 'weights' channel"):
        read_glb_animation(empty)
    assert validate(empty)["numErrors"] == 0


def test_mismatched_names_raise_and_write_nothing(rig, weights, tmp_path):
    renamed = Weights(weights.values, ("Angry", "Happy", "Sad"), weights.fps)
    with pytest.raises(RigError, match=r"missing \['Surprised'\], extra \['Happy'\]"):
        write_glb(tmp_path / "anim.glb", rig, renamed)
    reordered = Weights(weights.values, ("Sad", "Surprised", "Angry"), weights.fps)
    with pytest.raises(RigError, match="in rig order"):
        write_glb(tmp_path / "anim.glb", rig, reordered)
    assert list(tmp_path.iterdir()) == []


def test_pose_frame_count_and_suffix_are_checked(rig, weights, tmp_path):
    with pytest.raises(InputError, match=r"one frame per weights frame \(40\); got 3"):
        write_glb(tmp_path / "anim.glb", rig, weights, poses=random_poses(3))
    with pytest.raises(InputError, match=r"must end in \.glb"):
        write_glb(tmp_path / "anim.gltf", rig, weights)
    assert list(tmp_path.iterdir()) == []


def test_failure_while_writing_leaves_the_old_file(rig, weights, tmp_path, monkeypatch):
    path = write_glb(tmp_path / "anim.glb", rig, weights)
    before = path.read_bytes()

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(gltf_io.Path, "write_bytes", broken)
    with pytest.raises(OSError, match="disk full"):
        write_glb(path, rig, Weights(weights.values * 0.5, rig.names, weights.fps))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["anim.glb"]  # no temporary left behind


def test_json_chunk_is_plain_gltf(rig, weights, tmp_path):
    data = write_glb(tmp_path / "anim.glb", rig, weights).read_bytes()
    assert data[:4] == b"glTF"
    length = int.from_bytes(data[12:16], "little")
    document = json.loads(data[20 : 20 + length])
    assert document["asset"]["version"] == "2.0"
