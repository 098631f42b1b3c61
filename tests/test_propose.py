"""Proposals: a planted key -> target mapping recovered on synthetic data, new targets by transfer,
the one-call route for run/demo, the sculpt-kit hook, the robot through the mapping route, and
`keyshape propose` end to end."""

import json
from pathlib import Path

import numpy as np
import pytest
from test_transfer import head_keys, sheet, to_image

from keyshape.cli import main
from keyshape.containers import KeyShapes, Rig, Weights
from keyshape.exceptions import InputError, RigError
from keyshape.io.rig import load_rig
from keyshape.mesh import mesh_components
from keyshape.targets import (
    Correspondence,
    KeyScores,
    Mapping,
    auto_targets,
    propose_mapping,
    propose_targets,
    proposer,
    retarget,
)

ROBOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "robot-expressive" / "RobotExpressive.glb"


def planted(*, n_targets=6, n_keys=4, dims=3, seed=0):
    """A sheet rig with smooth local targets, and key shapes that are known mixes of them."""
    rng = np.random.default_rng(seed)
    vertices, faces = sheet(side=25)
    centres = rng.uniform(-0.08, 0.08, (n_targets, 2))
    bumps = np.exp(-((vertices[None, :, :2] - centres[:, None]) ** 2).sum(axis=2) / (2 * 0.03**2))
    deltas = bumps[:, :, None] * rng.normal(0, 0.006, (n_targets, 1, 3))
    rig = Rig(vertices, faces, deltas, tuple(f"t{i}" for i in range(n_targets)))
    truth = np.zeros((n_targets, n_keys))
    for k in range(n_keys):  # each key mixes one or two targets
        chosen = rng.choice(n_targets, 1 + k % 2, replace=False)
        truth[chosen, k] = rng.uniform(0.4, 1.2, len(chosen))
    landmarks = rng.choice(len(vertices), 45, replace=False)
    motion = np.einsum("tk,tpd->kpd", truth, deltas[:, landmarks])
    neutral = to_image(vertices[landmarks])[:, :dims]
    image_deltas = (to_image(vertices[landmarks][None] + motion) - to_image(vertices[landmarks])[None])[..., :dims]
    keys = KeyShapes(neutral, image_deltas, tuple(f"key{k}" for k in range(n_keys)), np.arange(n_keys),
                     ("whole",) * n_keys, {"whole": np.arange(45)}, stable=np.zeros(0, dtype=int))
    return rig, keys, Correspondence.from_vertex_ids(landmarks), truth


@pytest.mark.parametrize("dims", [3, 2])
def test_planted_mapping_is_recovered(dims):
    rig, keys, corr, truth = planted(dims=dims)
    exact = propose_mapping(keys, rig, correspondence=corr, ridge=0.0, min_gain=0.0)
    assert exact.sources == keys.names and exact.targets == rig.names
    np.testing.assert_allclose(exact.matrix, truth, atol=1e-6)
    default = propose_mapping(keys, rig, correspondence=corr)  # small ridge, pruned
    assert ((default.matrix > 0) == (truth > 0)).all()
    np.testing.assert_allclose(default.matrix, truth, rtol=0.05, atol=0.02)


def test_gains_are_bounded_and_can_be_normalised():
    rig, keys, corr, truth = planted()
    capped = propose_mapping(keys, rig, correspondence=corr, ridge=0.0, min_gain=0.0, max_gain=0.5)
    assert capped.matrix.max() == pytest.approx(0.5)
    np.testing.assert_allclose(capped.matrix[truth <= 0.5], truth[truth <= 0.5], atol=0.2)
    full = propose_mapping(keys, rig, correspondence=corr, ridge=0.0, min_gain=0.0, normalize=True)
    strongest = np.where(truth.max(axis=1, keepdims=True) > 0, truth.max(axis=1, keepdims=True), 1)
    np.testing.assert_allclose(full.matrix, truth / strongest, atol=1e-6)


def test_planted_mapping_drives_the_rig_like_the_truth():
    rig, keys, corr, truth = planted(seed=3)
    mapping = propose_mapping(keys, rig, correspondence=corr)
    key_weights = Weights(np.random.default_rng(0).uniform(0, 1, (20, keys.n_keys)), keys.names, 30)
    got = rig.pose(retarget(key_weights, mapping).values)
    want = rig.pose(key_weights.values @ truth.T)
    assert np.abs(got - want).max() < 0.05 * np.abs(want - rig.vertices).max()


def test_gaze_targets_are_not_proposed():
    rig, keys, corr, truth = planted()
    used = int(np.argmax(truth.sum(axis=1)))  # a gaze target that could stand in for a used one
    gaze = Rig(rig.vertices, rig.faces, np.concatenate([rig.deltas[used:used + 1], rig.deltas]),
               ("eyeLookDown_L", *rig.names))
    mapping = propose_mapping(keys, gaze, correspondence=corr, ridge=0.0, min_gain=0.0)
    assert (mapping.matrix[0] == 0).all()
    np.testing.assert_allclose(mapping.matrix[1:], truth, atol=1e-6)
    allowed = propose_mapping(keys, gaze, correspondence=corr, exclude=())
    assert allowed.matrix[0].sum() > 0 or allowed.matrix[1].sum() > 0


def test_a_key_no_target_reproduces_maps_to_nothing():
    rig, keys, corr, _ = planted()
    far = np.linalg.norm(rig.vertices[corr.vertices[:, 0], :2], axis=1) > 10  # nowhere
    deltas = np.array(keys.deltas)
    deltas[0] = 0.0
    assert not far.any()
    quiet = Rig(rig.vertices, rig.faces, rig.deltas * 0, rig.names)
    mapping = propose_mapping(KeyShapes(keys.neutral, deltas, keys.names, keys.frames, keys.key_regions,
                                        keys.regions, stable=np.zeros(0, dtype=int)), quiet, correspondence=corr)
    assert (mapping.matrix == 0).all()


def test_a_rig_without_targets_is_for_the_transfer_route():
    rig, keys, corr, _ = planted()
    bare = Rig(rig.vertices, rig.faces, np.zeros((0, rig.n_vertices, 3)), ())
    with pytest.raises(RigError, match="no blendshapes to combine"):
        propose_mapping(keys, bare, correspondence=corr)


# ---------------------------------------------------------------- new targets, the one call, the kit


@pytest.fixture(scope="module")
def head():
    from keyshape.targets import stylised_head

    return stylised_head()


@pytest.fixture(scope="module")
def mediapipe_keys(head):
    brows = {i: [0, 0.004, 0] for i in (70, 63, 105, 66, 107, 46, 53, 52, 65, 55, 300, 293, 334, 296, 336,
                                         276, 283, 282, 295, 285)}
    jaw = {i: [0, -0.008, -0.002] for i in (14, 87, 178, 88, 95, 317, 402, 318, 324, 17, 84, 314, 152)}
    upper = head_keys(head, {"upper_00": brows}, region="upper")
    lower = head_keys(head, {"lower_00": jaw}, region="lower")
    return KeyShapes(upper.neutral, np.concatenate([upper.deltas, lower.deltas]), ("upper_00", "lower_00"),
                     [0, 1], ("upper", "lower"), upper.regions)


def test_propose_targets_gives_one_target_per_key(head, mediapipe_keys):
    rig = propose_targets(mediapipe_keys, head.rig, correspondence=head.correspondence())
    assert rig.names == mediapipe_keys.names and rig.deltas.shape == (2, head.rig.n_vertices, 3)
    np.testing.assert_array_equal(rig.vertices, head.rig.vertices)
    brow, lip = 105, 14
    assert rig.deltas[0, brow, 1] > 0.003 and abs(rig.deltas[0, lip]).max() < 1e-4
    assert rig.deltas[1, lip, 1] < -0.005 and abs(rig.deltas[1, brow]).max() < 1e-4


def test_auto_targets_default_character(mediapipe_keys):
    auto = auto_targets(mediapipe_keys)
    assert auto.route == "transfer" and auto.rig.names == mediapipe_keys.names
    assert auto.mapping.matrix.tolist() == [[1.0, 0.0], [0.0, 1.0]]
    assert auto.rig.n_vertices > 10000  # a decent resolution
    from keyshape.targets import default_character

    np.testing.assert_allclose(default_character(mediapipe_keys).deltas, auto.rig.deltas)


def test_auto_targets_picks_the_route_from_the_rig(head, mediapipe_keys):
    corr = head.correspondence()
    own = propose_targets(mediapipe_keys, head.rig, correspondence=corr)
    semantic = Rig(own.vertices, own.faces, own.deltas, ("browsUp", "jawDrop"))
    auto = auto_targets(mediapipe_keys, semantic, correspondence=corr)
    assert auto.route == "mapping" and auto.rig is semantic
    gains = auto.mapping.to_dict()
    assert max(gains["upper_00"], key=gains["upper_00"].get) == "browsUp"
    assert max(gains["lower_00"], key=gains["lower_00"].get) == "jawDrop"
    full = auto_targets(mediapipe_keys, semantic, correspondence=corr, normalize=True)
    assert full.mapping.matrix.max(axis=1).tolist() == [1.0, 1.0]
    forced = auto_targets(mediapipe_keys, semantic, correspondence=corr, route="transfer")
    assert forced.route == "transfer" and forced.rig.names == mediapipe_keys.names
    with pytest.raises(InputError, match="route must be"):
        auto_targets(mediapipe_keys, semantic, route="sculpt")


def test_the_default_character_needs_mediapipe_keys():
    rig, keys, _, _ = planted()
    with pytest.raises(InputError, match="knows MediaPipe's landmarks"):
        auto_targets(keys)
    with pytest.raises(InputError, match="only MediaPipe landmarks"):
        auto_targets(keys, rig)  # no correspondence and not MediaPipe: cannot be found automatically


def test_proposer_starts_the_sculpt_kit(head, mediapipe_keys):
    from keyshape.app import sculpt_targets

    kit = sculpt_targets(mediapipe_keys, head.rig, propose=proposer(correspondence=head.correspondence()))
    assert kit.names == mediapipe_keys.names and np.abs(kit.deltas).max() > 0.003


# ---------------------------------------------------------------- the robot, through the mapping route


def robot_correspondence(rig: Rig) -> dict:
    """What a user would write for the robot: MediaPipe brow and eye landmarks as points on its brow
    plates and eyes (the head faces -Y, +Z up, in the file's mesh coordinates)."""
    label = mesh_components(rig.vertices, rig.faces)
    counts = np.bincount(label)
    brows = [c for c in range(len(counts)) if counts[c] == 24]
    eyes = [c for c in range(len(counts)) if counts[c] == 258]
    points = {}
    sides = {"right": (70, 63, 105, 66, 107, 33, 133, 159, 145), "left": (300, 293, 334, 296, 336, 263, 362, 386, 374)}
    for side, (brow, eye) in (("right", (brows, eyes)), ("left", (brows, eyes))):
        pick = min if side == "right" else max  # the robot's right is -X
        brow_part = rig.vertices[label == pick(brow, key=lambda c: rig.vertices[label == c, 0].mean())]
        eye_part = rig.vertices[label == pick(eye, key=lambda c: rig.vertices[label == c, 0].mean())]
        ids = sides[side]
        inner, outer = np.argsort(np.abs(brow_part[:, 0]))[[0, -1]]
        top = brow_part[:, 2].max()
        front = brow_part[:, 1].min()
        for f, landmark in zip(np.linspace(1, 0, 5), ids[:5]):  # outer -> inner
            x = brow_part[inner, 0] + f * (brow_part[outer, 0] - brow_part[inner, 0])
            points[landmark] = [float(x), float(front), float(top)]
        low, high = eye_part.min(axis=0), eye_part.max(axis=0)
        middle = (low + high) / 2
        x_outer, x_inner = (low[0], high[0]) if side == "right" else (high[0], low[0])
        points[ids[5]] = [float(x_outer), float(middle[1]), float(middle[2])]
        points[ids[6]] = [float(x_inner), float(middle[1]), float(middle[2])]
        points[ids[7]] = [float(middle[0]), float(low[1]), float(high[2])]
        points[ids[8]] = [float(middle[0]), float(low[1]), float(low[2])]
    return {"n_landmarks": 478, "landmarks": {str(k): v for k, v in points.items()}}


needs_robot = pytest.mark.skipif(not ROBOT.is_file(), reason=f"{ROBOT} not present (shared data)")


@pytest.fixture(scope="module")
def robot_keys(head):
    inner, outer = (107, 55, 336, 285), (70, 46, 300, 276)
    middle = (63, 105, 66, 53, 52, 65, 293, 334, 296, 283, 282, 295)
    up = {i: [0, 0.005, 0] for i in inner + outer + middle}
    frown = {**{i: [0, -0.003, 0] for i in inner}, **{i: [0, 0.002, 0] for i in outer}}
    sad = {**{i: [0, 0.002, 0] for i in inner}, **{i: [0, -0.002, 0] for i in outer}}
    jaw = {i: [0, -0.008, 0] for i in (14, 87, 178, 88, 95, 317, 402, 318, 324, 17, 152)}
    upper = head_keys(head, {"upper_00": up, "upper_01": frown, "upper_02": sad}, region="upper")
    lower = head_keys(head, {"lower_00": jaw}, region="lower")
    return KeyShapes(upper.neutral, np.concatenate([upper.deltas, lower.deltas]), (*upper.names, "lower_00"),
                     [0, 1, 2, 3], ("upper",) * 3 + ("lower",), upper.regions)


@needs_robot
def test_robot_gets_a_sensible_mapping(robot_keys, tmp_path):
    rig = load_rig(ROBOT)
    path = tmp_path / "robot.json"
    path.write_text(json.dumps(robot_correspondence(rig)))
    mapping = propose_mapping(robot_keys, rig, correspondence=path)
    gains = mapping.to_dict()
    strongest = {key: max(row, key=row.get) if row else None for key, row in gains.items()}
    assert strongest == {"upper_00": "Surprised", "upper_01": "Angry", "upper_02": "Sad", "lower_00": None}
    # geometric gains: a 5 mm human brow raise is a fifth of the robot's (cartoon) Surprised brows
    assert 0.1 < gains["upper_00"]["Surprised"] < 0.4
    full = propose_mapping(robot_keys, rig, correspondence=path, normalize=True)
    assert full.matrix.max(axis=1).tolist() == [1.0, 1.0, 1.0]  # each target reaches full strength
    assert full.to_dict()["upper_00"]["Surprised"] == 1.0


@needs_robot
def test_robot_through_the_command_line(robot_keys, tmp_path):
    from keyshape.io.keys_json import save_keys
    from keyshape.io.weights_csv import save_weights_csv

    rig = load_rig(ROBOT)
    keys_json = save_keys(robot_keys, tmp_path / "keys.json")
    corr = tmp_path / "robot.json"
    corr.write_text(json.dumps(robot_correspondence(rig)))
    mapping_json = tmp_path / "robot_map.json"
    assert main(["propose", str(keys_json), "--rig", str(ROBOT), "--correspondence", str(corr), "--normalize",
                 "-o", str(mapping_json), "--save-correspondence", str(tmp_path / "used.json"), "-q"]) == 0
    mapping = Mapping.from_file(mapping_json, targets=rig.names)
    assert mapping.matrix[rig.names.index("Surprised"), 0] == 1.0
    assert json.loads((tmp_path / "used.json").read_text())["n_landmarks"] == 478
    weights = save_weights_csv(Weights(np.eye(4)[[0, 0, 1, 2, 3]], robot_keys.names, 30), tmp_path / "w.csv")
    out = tmp_path / "robot_anim.glb"
    assert main(["retarget", str(weights), "--rig", str(ROBOT), "--map", str(mapping_json), "-o", str(out),
                 "-q"]) == 0
    assert out.stat().st_size > 0


# ---------------------------------------------------------------- `keyshape propose`


def test_propose_command_default_character(mediapipe_keys, tmp_path, capsys):
    from keyshape.io.keys_json import save_keys

    keys_json = save_keys(mediapipe_keys, tmp_path / "keys.json")
    out = tmp_path / "head.glb"
    assert main(["propose", str(keys_json), "-o", str(out)]) == 0
    assert "2 proposed targets" in capsys.readouterr().out
    rig = load_rig(out)
    assert rig.names == ("upper_00", "lower_00") and rig.n_vertices > 10000
    folder = tmp_path / "head_obj"
    assert main(["propose", str(keys_json), "-o", str(folder), "-q"]) == 0
    assert sorted(p.name for p in folder.glob("*.obj")) == ["lower_00.obj", "neutral.obj", "upper_00.obj"]


def test_propose_command_mapping_onto_an_obj_rig(head, mediapipe_keys, tmp_path, capsys):
    from keyshape.io.keys_json import save_keys
    from keyshape.io.rig import save_obj_folder

    own = propose_targets(mediapipe_keys, head.rig, correspondence=head.correspondence())
    folder = save_obj_folder(Rig(own.vertices, own.faces, own.deltas, ("browsUp", "jawDrop")), tmp_path / "rig")
    head.correspondence().save(tmp_path / "corr.json")
    keys_json = save_keys(mediapipe_keys, tmp_path / "keys.json")
    out = tmp_path / "map.json"
    assert main(["propose", str(keys_json), "--rig", str(folder), "--correspondence", str(tmp_path / "corr.json"),
                 "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "upper_00: browsUp" in printed and "lower_00: jawDrop" in printed
    assert Mapping.from_file(out).to_dict()["upper_00"]["browsUp"] > 0.8


@pytest.mark.parametrize("extra, message", [
    (["-o", "map.json"], "a mapping needs --rig"),
    (["-o", "out.fbx"], "expected MAP.json"),
    (["-o", "out.glb", "--falloff", "0"], "--falloff: must be > 0"),
])
def test_propose_command_errors(mediapipe_keys, tmp_path, capsys, extra, message):
    from keyshape.io.keys_json import save_keys

    keys_json = save_keys(mediapipe_keys, tmp_path / "keys.json")
    args = ["propose", str(keys_json)] + [str(tmp_path / a) if a.endswith((".json", ".fbx", ".glb")) else a
                                          for a in extra]
    try:
        code = main(args)
    except SystemExit as exc:  # argparse's own usage errors
        code = exc.code
    assert code == 2  # usage errors (issue 17)
    assert message in capsys.readouterr().err


# ---------------------------------------------------------------- the built-in stylised head


def test_canonical_face_is_read_from_the_vendored_model():
    from keyshape.targets import canonical_face

    vertices, faces = canonical_face()
    assert vertices.shape == (468, 3) and faces.shape == (898, 3)
    assert 14 < np.ptp(vertices[:, 0]) < 17 and 16 < np.ptp(vertices[:, 1]) < 19  # centimetres
    assert faces.min() == 0 and faces.max() == 467


def test_stylised_head_is_deterministic_and_well_formed(head):
    from keyshape.targets import stylised_head

    again = stylised_head.__wrapped__()  # a fresh build, not the cached one
    np.testing.assert_array_equal(again.rig.vertices, head.rig.vertices)
    np.testing.assert_array_equal(again.rig.faces, head.rig.faces)
    rig = head.rig
    assert 10000 < rig.n_vertices < 13000 and rig.n_targets == 0
    assert 0.2 < np.ptp(rig.vertices[:, 1]) < 0.3  # metres, +Y up
    label = mesh_components(rig.vertices, rig.faces)
    assert len(np.unique(label)) == 21  # the head, two eyeballs, the mouth cavity, 16 teeth, the tongue
    assert (label[head.landmark_vertices] == 0).all()
    assert (label[head.parts["skin"]] == 0).all() and head.colours.shape == (rig.n_vertices, 3)
    assert all((label[part] != 0).all() for part in head.rigid)
    a, b, c = (rig.vertices[rig.faces[label[rig.faces[:, 0]] == 0][:, i]] for i in range(3))
    outward = (np.cross(b - a, c - a) * ((a + b + c) / 3 - [0, 0.012, -0.03])).sum(axis=1) > 0
    assert outward.mean() > 0.97  # glTF front faces out


def test_stylised_head_looks_unlike_a_person(head):
    """Bigger eyes than the canonical face it is built from: a caricature, not the actor."""
    from keyshape.targets import canonical_face

    face = canonical_face()[0] * 0.01
    rig = head.rig.vertices

    def eye_height_over_face_width(points):
        return np.ptp(points[[159, 145], 1]) / np.ptp(points[[234, 454], 0])

    assert eye_height_over_face_width(rig) > 1.4 * eye_height_over_face_width(face)


def test_found_correspondence_proposes_nearly_the_built_targets(head, mediapipe_keys):
    """The whole automatic route (render, track the render, snap, transfer) against the head's
    built-in correspondence: the proposed targets agree to within a third of their motion (60 %
    on the mouth key: the head's lips meet at rest, so the render cannot tell which lip an inner-lip
    landmark sits on)."""
    plain = Rig(head.rig.vertices, head.rig.faces, np.zeros((0, head.rig.n_vertices, 3)), ())
    found = propose_targets(mediapipe_keys, plain)  # no correspondence: found on a render
    built = propose_targets(mediapipe_keys, plain, correspondence=head.correspondence())
    difference = np.linalg.norm(found.deltas - built.deltas, axis=2).sum(axis=1)
    motion = np.linalg.norm(built.deltas, axis=2).sum(axis=1)
    assert (difference < np.array([0.35, 0.6]) * motion).all(), difference / motion


def test_score_route_uses_the_trackers_scores_at_the_keys():
    """With ARKit scores at the key frames, a key's gains are its scores minus the neutral's where they rise
    (gains >= 0, as every mapping's: a key with less smile than the neutral leaves the smile at the offset)."""
    rig, keys, corr, _ = planted(n_targets=4, n_keys=2)
    rig = Rig(rig.vertices, rig.faces, rig.deltas, ("mouthSmile_L", "mouthSmile_R", "jawOpen", "eyeLookUp_L"))
    names = ("_neutral", "mouthSmileLeft", "mouthSmileRight", "jawOpen", "eyeLookUpLeft", "browInnerUp")
    scores = KeyScores(np.array([0.1, 0.6, 0.5, 0.0, 0.3, 0.2]),
                       np.array([[0.0, 0.9, 0.8, 0.1, 0.0, 0.0], [0.0, 0.2, 0.1, 0.7, 0.9, 0.9]]), names)
    mapping = propose_mapping(keys, rig, correspondence=corr, scores=scores)
    np.testing.assert_allclose(mapping.offset, [0.6, 0.5, 0.0, 0.0])  # gaze excluded by default
    np.testing.assert_allclose(mapping.matrix, [[0.3, 0.0], [0.3, 0.0], [0.1, 0.7], [0.0, 0.0]])
    frames = Weights(np.array([[0.0, 0.0], [0.0, 1.0]]), keys.names, 30.0)
    np.testing.assert_allclose(retarget(frames, mapping).values, [[0.6, 0.5, 0.0, 0.0], [0.6, 0.5, 0.7, 0.0]])
    geometric = propose_mapping(keys, rig, correspondence=corr)  # no scores: the landmark fit, no offset
    assert not geometric.offset.any() and (geometric.matrix >= 0).all()
    auto = auto_targets(keys, rig, correspondence=corr, route="mapping", scores=scores)
    np.testing.assert_allclose(auto.mapping.offset, [0.6, 0.5, 0.0, 0.0])  # gaze has its own channel:
    np.testing.assert_allclose(auto.mapping.matrix, mapping.matrix)
    assert auto.mapping.gaze == (("eyeLookUp_L", "eyeLookUpLeft", 0.0),)  # its score, frame by frame
