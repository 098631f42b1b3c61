from pathlib import Path

import numpy as np
import pygltflib
import pytest

from keyshape.containers import KeyShapes, Rig, Weights
from keyshape.exceptions import InputError, RigError
from keyshape.io.gltf import write_glb
from keyshape.io.rig import load_rig, read_obj, save_obj_folder

from helpers import rig_from_keyshapes

ROBOT = Path("/work/shared/data/robot-expressive/RobotExpressive.glb")


@pytest.fixture
def rig():
    rng = np.random.default_rng(1)
    vertices = rng.normal(size=(6, 3))
    faces = np.array([[0, 1, 2], [0, 2, 3], [3, 4, 5]])
    return Rig(vertices, faces, rng.normal(scale=0.1, size=(3, 6, 3)), ("blink", "jawOpen", "smile"))


def assert_same_rig(a: Rig, b: Rig, *, atol=0.0):
    assert a.names == b.names
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_allclose(a.vertices, b.vertices, atol=atol)
    np.testing.assert_allclose(a.deltas, b.deltas, atol=atol)


def test_obj_folder_round_trip(rig, tmp_path):
    folder = save_obj_folder(rig, tmp_path / "hero")
    assert sorted(p.name for p in folder.iterdir()) == ["blink.obj", "jawOpen.obj", "neutral.obj", "smile.obj"]
    assert_same_rig(load_rig(folder), rig, atol=1e-8)


def test_obj_targets_are_sorted_by_name(rig, tmp_path):
    shuffled = Rig(rig.vertices, rig.faces, rig.deltas[::-1], rig.names[::-1])
    assert load_rig(save_obj_folder(shuffled, tmp_path)).names == rig.names


QUAD_OBJ = """# a unit square as one quad and a pentagon, with texture/normal indices
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 0 0
v 2 1 0
vt 0 0
vn 0 0 1
f 1/1/1 2/1/1 3/1/1 4/1/1
f 2//1 5//1 6//1 3//1 -3//1
"""


def test_quads_and_ngons_are_fan_triangulated(tmp_path):
    path = tmp_path / "quad.obj"
    path.write_text(QUAD_OBJ)
    vertices, faces = read_obj(path)
    assert vertices.shape == (6, 3)
    np.testing.assert_array_equal(faces, [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2], [1, 2, 3]])


def test_quad_rig_folder(tmp_path):
    (tmp_path / "neutral.obj").write_text(QUAD_OBJ)
    (tmp_path / "wide.obj").write_text(QUAD_OBJ.replace("v 2 0 0", "v 3 0 0"))
    rig = load_rig(tmp_path)
    assert rig.names == ("wide",) and rig.faces.shape == (5, 3)
    expected = np.zeros((6, 3))
    expected[4, 0] = 1.0
    np.testing.assert_array_equal(rig.deltas[0], expected)


def test_topology_mismatch_names_the_file_and_counts(rig, tmp_path):
    save_obj_folder(rig, tmp_path)
    (tmp_path / "smile.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(RigError, match=r"smile\.obj has 3 vertices but neutral\.obj has 6"):
        load_rig(tmp_path)


def test_other_faces_are_a_topology_mismatch(rig, tmp_path):
    save_obj_folder(rig, tmp_path)
    text = (tmp_path / "blink.obj").read_text().replace("f 4 5 6", "f 4 6 5")
    (tmp_path / "blink.obj").write_text(text)
    with pytest.raises(RigError, match=r"blink\.obj has the same 6 vertices as neutral\.obj but other faces"):
        load_rig(tmp_path)


def test_missing_neutral(rig, tmp_path):
    save_obj_folder(rig, tmp_path)
    (tmp_path / "neutral.obj").unlink()
    with pytest.raises(RigError, match=r"has no neutral\.obj"):
        load_rig(tmp_path)


def test_bad_obj_line_is_quoted(tmp_path):
    (tmp_path / "neutral.obj").write_text("v 0 0 0\nv 1 zero 0\n")
    with pytest.raises(InputError, match=r"line 2: cannot read 'v 1 zero 0'"):
        load_rig(tmp_path)


def test_unknown_paths(tmp_path):
    with pytest.raises(RigError, match="no rig at"):
        load_rig(tmp_path / "nothing")
    (tmp_path / "hero.fbx").write_bytes(b"")
    with pytest.raises(RigError, match=r"expected an OBJ folder, an \.obj, a \.glb/\.gltf, a \.vrm or a USD"):
        load_rig(tmp_path / "hero.fbx")


def test_unwritable_target_names(rig, tmp_path):
    bad = Rig(rig.vertices, rig.faces, rig.deltas[:2], ("ok", "a/b"))
    with pytest.raises(RigError, match=r"\['a/b'\]"):
        save_obj_folder(bad, tmp_path)


# ---------------------------------------------------------------- glTF rigs


def test_glb_round_trip(rig, tmp_path):
    path = write_glb(tmp_path / "hero.glb", rig, Weights(np.zeros((2, 3)), rig.names, fps=30))
    assert_same_rig(load_rig(path), rig, atol=1e-6)


def test_gltf_with_embedded_buffer(rig, tmp_path):
    glb = write_glb(tmp_path / "hero.glb", rig, Weights(np.zeros((2, 3)), rig.names, fps=30))
    document = pygltflib.GLTF2().load(str(glb))
    document.convert_buffers(pygltflib.BufferFormat.DATAURI)
    document.save_json(str(tmp_path / "hero.gltf"))
    assert_same_rig(load_rig(tmp_path / "hero.gltf"), rig, atol=1e-6)


def _rewrite(path, out, edit):
    document = pygltflib.GLTF2().load(str(path))
    edit(document)
    document.save_binary(str(out))
    return out


def test_gltf_without_target_names(rig, tmp_path):
    glb = write_glb(tmp_path / "hero.glb", rig, Weights(np.zeros((2, 3)), rig.names, fps=30))
    out = _rewrite(glb, tmp_path / "unnamed.glb", lambda d: setattr(d.meshes[0], "extras", {}))
    with pytest.raises(RigError, match=r"\[3\] morph targets but 0 names in mesh\.extras\.targetNames"):
        load_rig(out)


def test_gltf_without_morph_targets(rig, tmp_path):
    glb = write_glb(tmp_path / "hero.glb", rig, Weights(np.zeros((2, 3)), rig.names, fps=30))

    def strip(document):
        document.meshes[0].primitives[0].targets = []
        document.meshes[0].weights = []
        document.animations = []

    with pytest.raises(RigError, match="has no morph targets"):
        load_rig(_rewrite(glb, tmp_path / "static.glb", strip))


@pytest.mark.skipif(not ROBOT.is_file(), reason=f"{ROBOT} not present (shared data)")
def test_robot_expressive_head():
    rig = load_rig(ROBOT)
    assert rig.names == ("Angry", "Surprised", "Sad")
    # three head primitives, concatenated
    document = pygltflib.GLTF2().load(str(ROBOT))
    heads = [p for m in document.meshes for p in m.primitives if p.targets]
    assert len(heads) == 3
    assert rig.n_vertices == sum(document.accessors[p.attributes.POSITION].count for p in heads)
    assert len(rig.faces) == sum(document.accessors[p.indices].count for p in heads) // 3
    assert (np.abs(rig.deltas).max(axis=(1, 2)) > 0).all()


# ---------------------------------------------------------------- the default character


def test_rig_from_keyshapes_converts_axes_and_scale():
    neutral = np.array([[100.0, 200.0, 5.0], [140.0, 200.0, -5.0], [120.0, 300.0, 0.0]])
    deltas = np.zeros((2, 3, 3))
    deltas[0, 2] = [0.0, 10.0, 0.0]  # jaw drops (image y down)
    deltas[1, 0] = [0.0, 0.0, 4.0]  # point moves away from camera
    keys = KeyShapes(neutral, deltas, ("lower_00", "upper_00"), [4, 9], ("lower", "upper"),
                     {"lower": [2], "upper": [0, 1]})
    rig = rig_from_keyshapes(keys, np.array([[0, 2, 1]]), size=0.25)
    assert rig.names == ("lower_00", "upper_00")
    np.testing.assert_allclose(np.ptp(rig.vertices[:, 1]), 0.25)
    np.testing.assert_allclose((rig.vertices.min(0) + rig.vertices.max(0)) / 2, 0.0, atol=1e-12)
    scale = 0.25 / 100.0
    assert rig.vertices[2, 1] < rig.vertices[0, 1]  # the chin is below the eyes: +Y up
    np.testing.assert_allclose(rig.vertices[0, 2], -5.0 * scale)  # z toward the viewer
    np.testing.assert_allclose(rig.deltas[0, 2], [0.0, -10.0 * scale, 0.0])
    np.testing.assert_allclose(rig.deltas[1, 0], [0.0, 0.0, -4.0 * scale])
    # the pose of the rig is the pose of the key shapes, transformed
    w = np.array([[0.5, 1.0]])
    expected = (keys.pose(w)[0] - [120.0, 250.0, 0.0]) * [1, -1, -1] * scale
    np.testing.assert_allclose(rig.pose(w)[0], expected, atol=1e-12)


def test_rig_from_2d_keyshapes_and_bad_faces():
    keys = KeyShapes(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0]]), np.zeros((1, 3, 2)), ("k",), [0],
                     ("whole",), {"whole": [0, 1, 2]})
    rig = rig_from_keyshapes(keys, [[0, 1, 2]])
    assert rig.vertices.shape == (3, 3) and (rig.vertices[:, 2] == 0).all()
    with pytest.raises(InputError, match=r"faces must index landmarks 0\.\.2; got 0\.\.3"):
        rig_from_keyshapes(keys, [[0, 1, 3]])


# ---------------------------------------------------------------- OBJ details, units, dispatch

from keyshape.io.rig import _read_obj_checked, _read_obj_fast, parse_unit  # noqa: E402


def test_fast_and_checked_obj_readers_agree(tmp_path):
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(40, 3))
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    lines += ["vt 0.5 0.5", "vn 0 0 1", "g mesh", "usemtl skin", "s off"]
    polygons = [rng.choice(40, size=rng.integers(3, 7), replace=False) for _ in range(30)]
    lines += ["f " + " ".join(f"{i + 1}/1/1" for i in p) for p in polygons]
    lines += ["f  1  2   3 "]  # extra spaces
    text = "\r\n".join(lines) + "\r\n"  # Windows line ends
    fast = _read_obj_fast(text)
    checked = _read_obj_checked(text.splitlines(), "x.obj")
    assert fast is not None
    np.testing.assert_array_equal(fast[0], checked[0])
    np.testing.assert_array_equal(fast[1], checked[1])
    assert len(fast[1]) == sum(len(p) - 2 for p in polygons) + 1


def test_vertex_colours_are_ignored(tmp_path):
    (tmp_path / "c.obj").write_text("v 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 0 1 0 0 0 1\nf 1 2 3\n")
    vertices, faces = read_obj(tmp_path / "c.obj")
    assert vertices.shape == (3, 3) and faces.tolist() == [[0, 1, 2]]


def test_single_obj_is_a_neutral_without_targets(rig, tmp_path):
    folder = save_obj_folder(rig, tmp_path / "hero")
    neutral = load_rig(folder / "neutral.obj")
    assert neutral.n_targets == 0 and neutral.n_vertices == rig.n_vertices


def test_neutral_found_by_name(rig, tmp_path):
    folder = save_obj_folder(rig, tmp_path / "hero")
    (folder / "neutral.obj").rename(folder / "generic_neutral_mesh.obj")
    assert load_rig(folder).names == rig.names
    (folder / "neutral_old.obj").write_text((folder / "generic_neutral_mesh.obj").read_text())
    candidates = r"candidates: \['generic_neutral_mesh\.obj', 'neutral_old\.obj'\]"
    with pytest.raises(RigError, match=r"no neutral\.obj .*" + candidates):
        load_rig(folder)


def test_units(rig, tmp_path):
    folder = save_obj_folder(rig, tmp_path / "hero")
    in_cm, as_is = load_rig(folder, unit=parse_unit("cm")), load_rig(folder)
    np.testing.assert_allclose(in_cm.vertices, as_is.vertices * 0.01, rtol=1e-12)
    np.testing.assert_allclose(in_cm.deltas, as_is.deltas * 0.01, rtol=1e-12)
    assert parse_unit("0.0254") == parse_unit("in") == 0.0254
    with pytest.raises(InputError, match="unit must be one of m, cm, mm, in, ft"):
        parse_unit("furlong")
    with pytest.raises(InputError, match="positive number"):
        load_rig(folder, unit=-1)
    glb = write_glb(tmp_path / "hero.glb", rig, Weights(np.zeros((1, 3)), rig.names, fps=30))
    with pytest.raises(InputError, match="unit applies to OBJ files only"):
        load_rig(glb, unit=0.01)


def test_compressed_gltf_is_refused_clearly(rig, tmp_path):
    glb = write_glb(tmp_path / "hero.glb", rig, Weights(np.zeros((2, 3)), rig.names, fps=30))
    out = _rewrite(glb, tmp_path / "draco.glb", lambda d: setattr(d, "extensionsUsed", ["KHR_draco_mesh_compression"]))
    with pytest.raises(RigError, match="compressed geometry cannot be read as a rig"):
        load_rig(out)
