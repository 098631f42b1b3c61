import json

import numpy as np
import pygltflib
import pytest
from scipy.spatial.transform import Rotation

from keyshape.containers import KeyShapes, Poses, Rig, Weights
from keyshape.exceptions import InputError, RigError
from keyshape.io import gltf as gltf_io
from keyshape.io.gltf import eye_nodes, read_glb_animation, write_glb
from keyshape.io.rig import load_rig
from keyshape.schemes import face_triangles

from gltf_validator import validate
from helpers import rig_from_keyshapes

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


# ---------------------------------------------------------------- sparse targets and several primitives


def test_targets_moving_few_vertices_are_sparse(rig, weights, tmp_path):
    deltas = rig.deltas.copy()
    deltas[1, 3:] = 0.0  # moves 3 of 25 vertices
    few = Rig(rig.vertices, rig.faces, deltas, rig.names)
    path = write_glb(tmp_path / "sparse.glb", few, weights)
    document = pygltflib.GLTF2().load(str(path))
    targets = document.meshes[0].primitives[0].targets
    sparse = document.accessors[targets[1]["POSITION"]]
    assert sparse.bufferView is None and sparse.sparse.count == 3
    assert document.accessors[targets[0]["POSITION"]].sparse is None
    np.testing.assert_allclose(load_rig(path).deltas, few.deltas, atol=1e-7)
    report = validate(path)
    assert (report["numErrors"], report["numWarnings"]) == (0, 0), report["messages"]


def _split_into_primitives(path, out):
    """Rewrite a write_glb file: its triangles in two primitives sharing one vertex buffer,
    plus a copy of the mesh as a second mesh (same names), as exporters split by material."""
    document = pygltflib.GLTF2().load(str(path))
    (primitive,) = document.meshes[0].primitives
    indices = document.accessors[primitive.indices]
    half = indices.count // 6 * 3
    view = document.bufferViews[indices.bufferView]
    item = 2 if indices.componentType == pygltflib.UNSIGNED_SHORT else 4
    first = pygltflib.Accessor(bufferView=indices.bufferView, byteOffset=0, componentType=indices.componentType,
                               count=half, type="SCALAR")
    second = pygltflib.Accessor(bufferView=indices.bufferView, byteOffset=half * item,
                                componentType=indices.componentType, count=indices.count - half, type="SCALAR")
    assert view.byteLength == indices.count * item
    document.accessors += [first, second]
    primitive.indices = len(document.accessors) - 2
    other = pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=primitive.attributes.POSITION),
                                indices=len(document.accessors) - 1, material=0,
                                targets=[dict(t) for t in primitive.targets])
    document.meshes[0].primitives.append(other)
    document.save_binary(str(out))
    return out


def test_primitives_sharing_a_vertex_buffer_share_rig_vertices(rig, weights, tmp_path):
    path = _split_into_primitives(write_glb(tmp_path / "a.glb", rig, weights), tmp_path / "split.glb")
    loaded = load_rig(path)
    assert loaded.n_vertices == rig.n_vertices  # not duplicated
    np.testing.assert_array_equal(np.sort(loaded.faces, axis=0), np.sort(rig.faces, axis=0))
    _, parts = gltf_io.read_meshes(path)
    assert [(p.mesh, p.primitive, p.start, p.count) for p in parts] == [(0, 0, 0, 25), (0, 1, 0, 25)]


def test_target_names_on_the_first_primitive(rig, weights, tmp_path):
    document = pygltflib.GLTF2().load(str(write_glb(tmp_path / "a.glb", rig, weights)))
    document.meshes[0].primitives[0].extras = document.meshes[0].extras
    document.meshes[0].extras = {}
    document.save_binary(str(tmp_path / "b.glb"))
    assert load_rig(tmp_path / "b.glb").names == rig.names
    assert read_glb_animation(tmp_path / "b.glb").names == rig.names


# ---------------------------------------------------------------- an artist's file kept whole

from pathlib import Path  # noqa: E402

from keyshape.io import _gltf_edit as edit  # noqa: E402
from keyshape.io._gltf_read import read_accessor  # noqa: E402
from keyshape.io.gltf import animate_gltf, read_meshes, write_gltf_targets  # noqa: E402

ROBOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "robot-expressive" / "RobotExpressive.glb"
needs_robot = pytest.mark.skipif(not ROBOT.is_file(), reason=f"{ROBOT} not present (shared data)")


def _clean(path):
    report = validate(path)
    assert (report["numErrors"], report["numWarnings"]) == (0, 0), report["messages"]


def skinned_character(path, rig):
    """A skinned morph-target mesh (joints Neck > Head), its node under the armature, not at the root."""
    document = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0"), scene=0,
                               scenes=[pygltflib.Scene(nodes=[0])])
    blob = edit.Blob(document)
    n = rig.n_vertices
    joints = np.tile(np.array([1, 0, 0, 0], np.uint8), (n, 1))
    skin_weights = np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1))
    attributes = pygltflib.Attributes(
        POSITION=blob.add(rig.vertices.astype(np.float32), "VEC3", target=pygltflib.ARRAY_BUFFER, bounds=True),
        JOINTS_0=blob.add(joints, "VEC4", target=pygltflib.ARRAY_BUFFER),
        WEIGHTS_0=blob.add(skin_weights, "VEC4", target=pygltflib.ARRAY_BUFFER))
    indices = blob.add(rig.faces.reshape(-1).astype(np.uint16), "SCALAR", target=pygltflib.ELEMENT_ARRAY_BUFFER)
    targets = [{"POSITION": blob.add_target(d)} for d in rig.deltas]
    document.meshes.append(pygltflib.Mesh(name="face", weights=[0.0] * rig.n_targets,
                                          extras={"targetNames": list(rig.names)},
                                          primitives=[pygltflib.Primitive(attributes=attributes, indices=indices,
                                                                          targets=targets)]))
    inverse_bind = np.stack([np.eye(4), np.eye(4)]).astype(np.float32)
    inverse_bind[1, 3, 1] = -0.1  # column-major: translation (0, -0.1, 0) in the 4th column
    document.skins.append(pygltflib.Skin(joints=[1, 2], inverseBindMatrices=blob.add(inverse_bind, "MAT4")))
    document.nodes = [pygltflib.Node(name="Armature", children=[1, 3]),
                      pygltflib.Node(name="Neck", children=[2]),
                      pygltflib.Node(name="Head", translation=[0.0, 0.1, 0.0]),
                      pygltflib.Node(name="face", mesh=0, skin=0)]
    blob.finish()
    document.save_binary(str(path))
    return path


def _head_world_rotations(path, animation_quats, head):
    document = pygltflib.GLTF2().load(str(path))
    parent = edit.parents(document).get(head)
    p = edit.world_rotation(document, parent)
    return p @ Rotation.from_quat(animation_quats).as_matrix()


def test_skinned_character_turns_its_head_joint(rig, weights, tmp_path):
    source = skinned_character(tmp_path / "skinned.glb", rig)
    assert validate(source)["numWarnings"] == 1  # NODE_SKINNED_MESH_NON_ROOT in the source
    poses = random_poses(weights.n_frames)
    out = animate_gltf(source, weights, tmp_path / "anim.glb", poses=poses)
    _clean(out)
    document = pygltflib.GLTF2().load(str(out))
    (animation,) = document.animations
    rotation = [c for c in animation.channels if c.target.path == "rotation"]
    assert [document.nodes[c.target.node].name for c in rotation] == ["Head"]
    assert 3 in document.scenes[0].nodes and 3 not in document.nodes[0].children  # mesh at the root
    assert document.skins[0].joints == [1, 2]
    back = read_glb_animation(out)
    np.testing.assert_array_equal(back.weights, weights.values.astype(np.float32))
    world = _head_world_rotations(out, back.rotations, 2)
    np.testing.assert_allclose(world, C @ poses.rotations @ C, atol=1e-6)


@needs_robot
def test_robot_keeps_everything_and_gains_the_performance(tmp_path):
    original = pygltflib.GLTF2().load(str(ROBOT))
    rig = load_rig(ROBOT)
    rng = np.random.default_rng(7)
    weights = Weights(rng.random((60, 3)), rig.names, fps=24)
    poses = random_poses(60, seed=8)
    out = animate_gltf(ROBOT, weights, tmp_path / "robot.glb", poses=poses)
    _clean(out)
    document = pygltflib.GLTF2().load(str(out))
    assert [a.name for a in document.animations] == ["keyshape"] + [a.name for a in original.animations]
    assert len(document.skins) == len(original.skins) and len(document.materials) == len(original.materials)
    assert len(document.meshes) == len(original.meshes) == 19
    performance = document.animations[0]  # first: what viewers play by default
    weight_nodes = [document.nodes[c.target.node].name for c in performance.channels if c.target.path == "weights"]
    assert weight_nodes == ["Head_2", "Head_3", "Head_4"]  # the three head primitives
    back = read_glb_animation(out)
    assert back.names == ("Angry", "Surprised", "Sad")
    np.testing.assert_array_equal(back.weights, weights.values.astype(np.float32))
    np.testing.assert_allclose(back.times, np.arange(60) / 24, atol=1e-6)
    # deformed vertices recomputed from the written file
    np.testing.assert_allclose(load_rig(out).pose(back.weights), rig.pose(weights.values), atol=1e-5)
    (rotation,) = [c for c in performance.channels if c.target.path == "rotation"]
    head = rotation.target.node
    assert document.nodes[head].name == "Head"
    rest = edit.world_rotation(original, head)
    world = _head_world_rotations(out, back.rotations, head)
    np.testing.assert_allclose(world, (C @ poses.rotations @ C) @ rest, atol=1e-5)


@needs_robot
def test_animating_twice_replaces_the_earlier_take(tmp_path):
    rig = load_rig(ROBOT)
    first = animate_gltf(ROBOT, Weights(np.ones((5, 3)), rig.names, 30), tmp_path / "a.glb")
    second = animate_gltf(first, Weights(np.zeros((9, 3)), rig.names, 30), tmp_path / "b.glb")
    document = pygltflib.GLTF2().load(str(second))
    assert [a.name for a in document.animations].count("keyshape") == 1
    assert read_glb_animation(second).weights.shape == (9, 3)
    assert second.stat().st_size < first.stat().st_size + 2000  # the old take's data is pruned
    _clean(second)


@needs_robot
def test_subset_of_targets_and_unknown_names(tmp_path):
    out = animate_gltf(ROBOT, Weights(np.full((4, 1), 0.5), ("Sad",), 30), tmp_path / "sad.glb")
    back = read_glb_animation(out)
    np.testing.assert_array_equal(back.weights, [[0.0, 0.0, 0.5]] * 4)  # others at their rest weight
    with pytest.raises(RigError, match=r"does not have: \['Happy'\]"):
        animate_gltf(ROBOT, Weights(np.zeros((4, 1)), ("Happy",), 30), tmp_path / "x.glb")
    assert not (tmp_path / "x.glb").exists()


def test_head_node_by_name_or_a_clear_error(rig, weights, tmp_path):
    source = write_glb(tmp_path / "two.glb", rig, Weights(np.zeros((0, 3)), rig.names, 30))
    document = pygltflib.GLTF2().load(str(source))
    document.nodes[0].name = "faceA"
    document.nodes.append(pygltflib.Node(name="faceB", mesh=0, translation=[0.3, 0.0, 0.0]))
    document.nodes.append(pygltflib.Node(name="Group", children=[0, 1]))
    document.scenes[0].nodes = [2]
    document.save_binary(str(tmp_path / "two.glb"))
    poses = random_poses(weights.n_frames)
    with pytest.warns(UserWarning, match="no head node found .*the head rotation is not written"):
        still = animate_gltf(source, weights, tmp_path / "still.glb", poses=poses)
    assert read_glb_animation(still).rotations is None
    out = animate_gltf(source, weights, tmp_path / "anim.glb", poses=poses, head="Group")
    _clean(out)
    with pytest.raises(RigError, match="no node named 'Neck'"):
        animate_gltf(source, weights, tmp_path / "anim.glb", poses=poses, head="Neck")


def test_gltf_with_external_buffer_and_image_becomes_one_glb(rig, weights, tmp_path):
    from PIL import Image

    glb = write_glb(tmp_path / "a.glb", rig, Weights(np.zeros((0, 3)), rig.names, 30))
    document = pygltflib.GLTF2().load(str(glb))
    Image.new("RGB", (4, 4), (200, 30, 30)).save(tmp_path / "skin.png")
    document.images.append(pygltflib.Image(uri="skin.png"))
    document.samplers.append(pygltflib.Sampler())
    document.textures.append(pygltflib.Texture(source=0, sampler=0))
    document.convert_buffers(pygltflib.BufferFormat.BINFILE)
    document.save_json(str(tmp_path / "hero.gltf"))
    assert (tmp_path / "hero.gltf").is_file() and list(tmp_path.glob("*.bin"))
    out = animate_gltf(tmp_path / "hero.gltf", weights, tmp_path / "hero_anim.glb")
    _clean(out)
    packed = pygltflib.GLTF2().load(str(out))
    assert packed.images[0].uri is None and packed.images[0].mimeType == "image/png"
    assert len(packed.buffers) == 1 and packed.buffers[0].uri is None
    np.testing.assert_array_equal(read_glb_animation(out).weights, weights.values.astype(np.float32))


# ---------------------------------------------------------------- new targets on an original file


@needs_robot
def test_new_targets_on_the_robot(tmp_path):
    neutral, parts = read_meshes(ROBOT)
    assert sorted({p.mesh for p in parts}) == [3, 4, 5] and neutral.names == ("Angry", "Surprised", "Sad")
    rng = np.random.default_rng(9)
    deltas = rng.normal(scale=0.001, size=(2, neutral.n_vertices, 3))
    targets = Rig(neutral.vertices, neutral.faces, deltas, ("upper_00", "lower_00"))
    out = write_gltf_targets(ROBOT, tmp_path / "kit.glb", targets)
    _clean(out)
    back = load_rig(out)
    assert back.names == ("upper_00", "lower_00")
    np.testing.assert_allclose(back.deltas, deltas, atol=1e-7)
    document = pygltflib.GLTF2().load(str(out))
    assert all(c.target.path != "weights" for a in document.animations for c in a.channels)
    assert len(document.animations) == 14  # the skeletal animations stay
    with pytest.raises(RigError, match="have 1742 vertices but the rig has 3"):
        write_gltf_targets(ROBOT, tmp_path / "bad.glb", Rig(np.eye(3), [[0, 1, 2]], np.ones((1, 3, 3)), ("x",)))


def test_eye_nodes_turn_with_the_gaze(rig, weights, tmp_path):
    source = write_glb(tmp_path / "face.glb", rig, Weights(np.zeros((0, 3)), rig.names, 30))
    document = pygltflib.GLTF2().load(str(source))
    rest = Rotation.from_euler("x", -90, degrees=True).as_quat().tolist()  # a bone axis convention
    document.nodes += [pygltflib.Node(name="Head", children=[0, 2, 3], rotation=[0.0, 0.0, 0.3826834, 0.9238795]),
                       pygltflib.Node(name="Eye.L", translation=[0.03, 0.05, 0.05], rotation=rest),
                       pygltflib.Node(name="Eye.R", translation=[-0.03, 0.05, 0.05], rotation=rest),
                       pygltflib.Node(name="eyelid_L")]
    document.nodes[1].children.append(4)
    document.scenes[0].nodes = [1]
    document.save_binary(str(source))
    n = weights.n_frames
    look = np.stack([Rotation.from_euler("y", np.linspace(-15, 15, n)[:, None], degrees=True).as_matrix(),
                     Rotation.from_euler("x", np.linspace(10, -10, n)[:, None], degrees=True).as_matrix()], axis=1)
    out = animate_gltf(source, weights, tmp_path / "eyes.glb", poses=random_poses(n), eyes=look)
    _clean(out)
    written = pygltflib.GLTF2().load(str(out))
    channels = [c for c in written.animations[0].channels if c.target.path == "rotation"]
    assert [written.nodes[c.target.node].name for c in channels] == ["Head", "Eye.L", "Eye.R"]
    for side, channel in enumerate(channels[1:]):
        sampler = written.animations[0].samplers[channel.sampler]
        quats = read_accessor(written, [written.binary_blob()], sampler.output)
        parent = edit.world_rotation(document, 1)  # the eye's parent, the head, at rest
        world = parent @ Rotation.from_quat(quats).as_matrix()
        expected = (C @ look[:, side] @ C) @ parent @ Rotation.from_quat(rest).as_matrix()
        np.testing.assert_allclose(world, expected, atol=1e-5)
    with pytest.raises(InputError, match=r"eyes must have shape \(40, 2, 3, 3\)"):
        animate_gltf(source, weights, tmp_path / "x.glb", eyes=look[:, :1])
    plain = write_glb(tmp_path / "plain.glb", rig, Weights(np.zeros((0, 3)), rig.names, 30))
    no_eyes = pygltflib.GLTF2().load(str(animate_gltf(plain, weights, tmp_path / "plain_anim.glb", eyes=look)))
    assert [c.target.path for c in no_eyes.animations[0].channels] == ["weights"]  # no eye nodes: none turned
    with pytest.raises(RigError, match=r"no eye nodes named \['L', 'R'\]"):
        animate_gltf(plain, weights, tmp_path / "x.glb", eyes=look, eye_nodes=("L", "R"))
    assert eye_nodes(source) == ("Eye.L", "Eye.R") and eye_nodes(plain) is None  # what auto-targets asks
    assert not (tmp_path / "x.glb").exists()


def test_matrix_nodes_become_trs_when_animated():
    rotation = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    matrix = np.eye(4)
    matrix[:3, :3] = rotation * [1.0, 2.0, 0.5]
    matrix[:3, 3] = [0.1, 0.2, 0.3]
    node = pygltflib.Node(name="Head", matrix=matrix.T.reshape(-1).tolist())  # column-major
    edit.as_trs(node)
    assert node.matrix is None and node.scale == pytest.approx([1.0, 2.0, 0.5])
    np.testing.assert_allclose(edit.local_matrix(node), matrix, atol=1e-12)


def test_colours_come_from_the_materials(tmp_path):
    """Base colour factor times the base-colour texture at each vertex's UV: the character as it looks."""
    import base64
    import io

    from PIL import Image

    from keyshape.io.gltf import read_colours

    rig = Rig(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]), np.array([[0, 1, 2], [1, 3, 2]]),
              np.zeros((1, 4, 3)), ("smile",))
    plain = write_glb(tmp_path / "plain.glb", rig, Weights(np.zeros((0, 1)), rig.names, 30))
    np.testing.assert_allclose(read_colours(plain), [[0.8, 0.8, 0.8, 1.0]] * 4)  # no material: light grey, opaque
    document = pygltflib.GLTF2().load(str(plain))
    picture = io.BytesIO()
    Image.fromarray(np.array([[[255, 0, 0], [0, 0, 255]]], dtype=np.uint8)).save(picture, format="PNG")
    uv = np.array([[0.25, 0.5], [0.75, 0.5], [0.25, 0.5], [0.75, 0.5]], dtype=np.float32).tobytes()
    document.buffers.append(pygltflib.Buffer(uri="data:application/octet-stream;base64,"
                                             + base64.b64encode(uv).decode(), byteLength=len(uv)))
    document.bufferViews.append(pygltflib.BufferView(buffer=len(document.buffers) - 1, byteOffset=0,
                                                     byteLength=len(uv)))
    document.accessors.append(pygltflib.Accessor(bufferView=len(document.bufferViews) - 1, componentType=5126,
                                                 count=4, type="VEC2"))
    png = base64.b64encode(picture.getvalue()).decode()
    document.images.append(pygltflib.Image(uri="data:image/png;base64," + png))
    document.textures.append(pygltflib.Texture(source=len(document.images) - 1))
    texture = pygltflib.TextureInfo(index=len(document.textures) - 1)
    document.materials.append(pygltflib.Material(pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
        baseColorFactor=[0.5, 1.0, 1.0, 1.0], baseColorTexture=texture)))
    primitive = document.meshes[0].primitives[0]
    primitive.material = len(document.materials) - 1
    primitive.attributes.TEXCOORD_0 = len(document.accessors) - 1
    document.save_binary(str(tmp_path / "painted.glb"))
    np.testing.assert_allclose(read_colours(tmp_path / "painted.glb"),
                               [[0.5, 0, 0, 1], [0, 0, 1, 1], [0.5, 0, 0, 1], [0, 0, 1, 1]])
