"""Mirrored keys, key-set extension and coverage on synthetic faces with planted one-sided expressions.

The face is MediaPipe's canonical face (exactly symmetric), scaled to pixels. Expressions are
built by hand on each side: a smirk pulls one mouth corner out and up, a wink closes one eye's
lids, a smile pulls both corners (symmetric), a brow raise lifts both brows (symmetric). The first
take shows only the left-side moves, the second only the right-side ones.
"""

import itertools
import json

import numpy as np
import pytest

from keyshape.app import coverage, discover_keys, extend_keys, fit_errors, sculpt_targets, solve_take
from keyshape.capture.model_file import canonical_face
from keyshape.cli import main
from keyshape.containers import KeyShapes, Rig, Track, Weights
from keyshape.io import load_keys, load_rig, save_keys, save_weights_csv
from keyshape.io.gltf import write_glb
from keyshape.keyshapes import add_mirrors, find_mirror_pairs, mirror_deltas, mirror_gains, symmetry_plane
from keyshape.mesh import mirror_field, mirror_map
from keyshape.schemes import mirror_pairs
from keyshape.targets import complete_mirrors, mirror_sources, proposer, stylised_head

from gltf_validator import unavailable_reason, validate

# MediaPipe ids: mouth corners (the person's right at image left), eyelids, brows
RIGHT_CORNER, LEFT_CORNER = 61, 291
RIGHT_LIDS, LEFT_LIDS = (159, 158, 160, 145, 144, 153), (386, 385, 387, 374, 373, 380)
BROWS = (70, 63, 105, 66, 107, 300, 293, 334, 296, 336)


def _face() -> np.ndarray:
    """The canonical face in image axes (x right, y down), 12 px per cm, centred at (320, 240)."""
    vertices, _ = canonical_face()
    return np.column_stack([320 + 12 * vertices[:, 0], 240 - 12 * vertices[:, 1], -12 * vertices[:, 2]])


def _bump(face, centre: int, move, radius: float = 14.0) -> np.ndarray:
    """Landmarks near ``centre`` moved by ``move`` (px) with a Gaussian falloff."""
    distance = np.linalg.norm(face - face[centre], axis=1)
    return np.exp(-(distance / radius) ** 2)[:, None] * np.asarray(move, dtype=float)


def _expressions(face) -> dict[str, np.ndarray]:
    lids = lambda ids: sum(_bump(face, i, [0, 8 if i in ids[:3] else -2.5, 0], 5.0) for i in ids)  # noqa: E731
    return {
        "smirk_left": _bump(face, LEFT_CORNER, [10, -8, 0]),     # the person's left = image right
        "smirk_right": _bump(face, RIGHT_CORNER, [-10, -8, 0]),
        "wink_left": lids(LEFT_LIDS),
        "wink_right": lids(RIGHT_LIDS),
        "smile": _bump(face, LEFT_CORNER, [6, -5, 0]) + _bump(face, RIGHT_CORNER, [-6, -5, 0]),
        "brows_up": sum(_bump(face, i, [0, -5, 0], 10.0) for i in BROWS),
    }


NOISE = 0.15  # px


def _take(face, shapes, names, *, n_frames=240, seed=0, noise=NOISE) -> tuple[Track, np.ndarray]:
    """Each frame one of ``names`` at a random weight (a fifth of the frames neutral), some noise;
    and each frame's expression (its name, "" for the neutral)."""
    rng = np.random.default_rng(seed)
    which = rng.integers(0, len(names) + 1, n_frames)  # len(names): neutral
    amount = rng.uniform(0.3, 1.0, n_frames)
    amount[rng.choice(n_frames, len(names), replace=False)] = 1.0
    points = np.repeat(face[None], n_frames, axis=0)
    for f in range(n_frames):
        if which[f] < len(names):
            points[f] += amount[f] * shapes[names[which[f]]]
    for k, name in enumerate(names):  # every expression once at full strength
        points[k + 1] = face + shapes[name]
    points[0] = face
    labels = np.array([*names, ""])[which]
    labels[1:len(names) + 1], labels[0] = names, ""
    return Track(points + noise * rng.standard_normal(points.shape), 30.0), labels


@pytest.fixture(scope="module")
def takes():
    face = _face()
    shapes = _expressions(face)
    first, _ = _take(face, shapes, ["smirk_left", "wink_left", "smile", "brows_up"], seed=1)
    second, labels = _take(face, shapes, ["smirk_right", "wink_right", "smile", "brows_up"], seed=2)
    return face, labels, first, second


def test_the_scheme_pairing_mirrors_the_canonical_face_onto_itself():
    face = _face()
    pairs = mirror_pairs(468)
    normal, offset = symmetry_plane(face, pairs)
    assert abs(normal[0]) > 0.999 and offset == pytest.approx(320, abs=1e-6)
    reflected = face - 2 * (face @ normal - offset)[:, None] * normal
    np.testing.assert_allclose(reflected[pairs], face, atol=1e-4)


def test_a_found_pairing_agrees_with_the_scheme_and_refuses_a_random_cloud():
    face = _face()
    pairs = find_mirror_pairs(face[:468])
    assert np.array_equal(pairs, mirror_pairs(468))
    assert find_mirror_pairs(np.random.default_rng(0).normal(size=(40, 3)) * 50) is None


def test_mirror_of_a_left_smirk_is_the_right_smirk():
    face = _face()
    shapes = _expressions(face)
    normal, _ = symmetry_plane(face, mirror_pairs(468))
    mirrored = mirror_deltas(shapes["smirk_left"][:468], mirror_pairs(468), normal)
    np.testing.assert_allclose(mirrored, shapes["smirk_right"][:468], atol=1e-6)


def test_mirrored_keys_reach_the_unseen_side_and_symmetric_keys_get_none(takes):
    _, _, first, second = takes
    plain = discover_keys(first, n_keys=4, neutral=0, mirror=False)
    mirrored = discover_keys(first, n_keys=4, neutral=0)
    assert plain.n_keys == 8 and not plain.mirrored.any()
    assert mirrored.names[: 4] == plain.names[: 4]
    sources = {mirrored.mirror_of[k]: k for k in np.flatnonzero(mirrored.mirrored)}
    assert len(sources) == 2  # the smirk and the wink, not the smile nor the brows
    for source, k in sources.items():
        j = mirrored.names.index(source)
        assert mirrored.frames[k] == mirrored.frames[j] and mirrored.names[k] == source + "_mirror"
    gains = mirror_gains(plain)  # nothing on the other side reaches a one-sided move
    assert all(gains[source] > 0.5 for source in sources)
    before, _ = fit_errors(second, plain)
    after, _ = fit_errors(second, mirrored)
    floor = 100 * NOISE * np.sqrt(3) / np.linalg.norm(first.points[0, 33] - first.points[0, 263])  # the noise's RMS
    for region in ("upper", "lower"):
        assert before[region] > 3 * floor and after[region] < 1.7 * floor, (region, before, after, floor)


def test_the_switch_and_the_threshold(takes):
    _, _, first, _ = takes
    plain = discover_keys(first, n_keys=4, neutral=0, mirror=False)
    assert add_mirrors(plain, min_reach=1.0).n_keys == plain.n_keys
    every = add_mirrors(plain, min_reach=0.0, max_error=0.0)
    assert every.mirrored.sum() == plain.n_keys  # every non-zero key gets its mirror at 0
    with pytest.raises(Exception, match="min_reach"):
        add_mirrors(plain, min_reach=1.5)


def test_mirrored_keys_round_trip_through_keys_json(takes, tmp_path):
    _, _, first, _ = takes
    keys = discover_keys(first, n_keys=4, neutral=0)
    path = save_keys(keys, tmp_path / "keys.json")
    entries = [e for r in json.loads(path.read_text())["regions"].values() for e in r["keys"]]
    assert [e.get("mirror_of", "") for e in entries] == list(keys.mirror_of)
    back = load_keys(path)
    assert back.names == keys.names and back.mirror_of == keys.mirror_of
    np.testing.assert_allclose(back.deltas, keys.deltas, atol=1e-3)


def test_a_mirror_must_name_a_frame_key():
    args = (np.zeros((3, 2)), np.ones((2, 3, 2)), ("a", "b"), [1, 1], ("r", "r"), {"r": [0, 1, 2]})
    with pytest.raises(Exception, match="mirror"):
        KeyShapes(*args, mirror_of=("", "c"))
    with pytest.raises(Exception, match="mirror"):
        KeyShapes(*args, mirror_of=("b", "a"))  # a mirror of a mirror


def test_extend_adds_the_fewest_keys_and_keeps_every_old_one(takes):
    _, _, first, second = takes
    keys = discover_keys(first, n_keys=4, neutral=0, mirror=False)
    extended = extend_keys(keys, second, take="second.npz", max_error=0.5, mirror=False)
    old = {n: k for k, n in enumerate(keys.names)}
    for name, k in old.items():
        j = extended.names.index(name)
        np.testing.assert_array_equal(extended.deltas[j], keys.deltas[k])
        assert extended.frames[j] == keys.frames[k] and extended.takes[j] == keys.takes[k]
    new = [n for n in extended.names if n not in old]
    assert len(new) == 2  # the right smirk and the right wink: nothing else is out of reach
    assert {extended.takes[extended.names.index(n)] for n in new} == {"second.npz"}
    assert {extended.key_regions[extended.names.index(n)] for n in new} == {"upper", "lower"}
    errors, _ = fit_errors(second, extended)
    assert max(errors.values()) < 0.5
    assert new == ["upper_04", "lower_04"] or sorted(new) == ["lower_04", "upper_04"]


def test_coverage_finds_the_frames_out_of_reach(takes):
    _, labels, first, second = takes
    keys = discover_keys(first, n_keys=4, neutral=0, mirror=False)
    cov = coverage(keys, second, max_error=0.7)
    for region, move in (("lower", "smirk_right"), ("upper", "wink_right")):
        far = set(cov.out_of_reach(region).tolist())
        assert far == set(np.flatnonzero(labels == move).tolist()), region  # exactly the unseen move's frames
    summary = cov.summary()
    assert summary["lower"]["keys_to_add"] == 1 and summary["upper"]["keys_to_add"] == 1
    curve = summary["lower"]["error_vs_added_keys"]
    assert curve[0] > 0.7 > curve[-1] and all(a >= b for a, b in itertools.pairwise(curve))
    covered = coverage(extend_keys(keys, second, max_error=0.7, mirror=False), second, max_error=0.7)
    assert covered.summary()["lower"]["frames_out_of_reach"] == 0


def test_a_mirrored_target_is_made_from_its_source_on_a_symmetric_mesh():
    head = stylised_head().rig
    _, normal = mirror_map(head.vertices)
    assert abs(normal[0]) == 1.0
    left = head.vertices[:, 0] > 0.01
    source = np.zeros_like(head.vertices)
    source[left, 1] = 0.004  # the left half lifts
    rig = Rig(head.vertices, head.faces, np.stack([source, np.zeros_like(source)]), ("lower_00", "lower_00_mirror"))
    made, names = complete_mirrors(rig, {"lower_00_mirror": "lower_00"})
    assert names == ["lower_00_mirror"]
    mirrored = made.deltas[1]
    right = head.vertices[:, 0] < -0.02  # clear of the midline, whose partners may sit on either side
    assert np.mean(np.abs(mirrored[right, 1] - 0.004) < 1e-9) > 0.99
    assert np.mean(np.abs(mirrored[head.vertices[:, 0] > 0.02]).max(axis=1) < 1e-9) > 0.99
    sculpted = Rig(head.vertices, head.faces, np.stack([source, 0.5 * source]), rig.names)
    assert complete_mirrors(sculpted, {"lower_00_mirror": "lower_00"})[1] == []  # the artist's own stays
    missing = Rig(head.vertices, head.faces, source[None], ("lower_00",))
    assert complete_mirrors(missing, mirror_sources(["lower_00", "lower_00_mirror"]))[0].names == rig.names


def test_retarget_makes_the_mirrored_targets_a_sculpted_file_lacks(takes, tmp_path):
    """The artist sculpts the frame keys only; `retarget` drives the mirrored keys with mirrored targets."""
    _, _, first, second = takes
    keys = discover_keys(first, n_keys=4, neutral=0)
    assert keys.mirrored.any()
    head = stylised_head()
    kit = sculpt_targets(keys, head.rig, propose=proposer(correspondence=head.correspondence(468)))
    assert np.abs(kit.deltas[keys.mirrored]).max() == 0 and np.abs(kit.deltas[~keys.mirrored]).max() > 0
    sculpted = write_glb(tmp_path / "sculpted.glb", kit, Weights(np.zeros((0, kit.n_targets)), kit.names, 30.0))
    weights = save_weights_csv(solve_take(second, keys).weights, tmp_path / "w.csv")
    before = sculpted.read_bytes()
    out = tmp_path / "anim.glb"
    assert main(["retarget", str(weights), "--rig", str(sculpted), "-o", str(out), "-q"]) == 0
    assert sculpted.read_bytes() == before
    animated = load_rig(out)
    pairs, normal = mirror_map(kit.vertices)
    for k in np.flatnonzero(keys.mirrored):
        source = kit.names.index(keys.mirror_of[k])
        expected = mirror_field(kit.deltas[source], pairs, normal)
        np.testing.assert_allclose(animated.deltas[animated.names.index(keys.names[k])], expected, atol=1e-6)
    if unavailable_reason() is None:
        report = validate(out)
        assert (report["numErrors"], report["numWarnings"]) == (0, 0), report["messages"]


def test_batch_warns_about_a_take_outside_the_shared_keys_reach(takes, tmp_path):
    from keyshape.app._batch import _warn_out_of_reach
    from keyshape.app._run import RunOptions
    from keyshape.exceptions import InputWarning

    _, _, first, second = takes
    keys = discover_keys(first, n_keys=4, neutral=0, mirror=False)
    keys_path = save_keys(keys, tmp_path / "keys.json")
    options = RunOptions(max_error=0.5)
    with pytest.warns(InputWarning, match=r"^b\.mp4: outside the shared key set's reach .*--extend") as caught:
        _warn_out_of_reach(keys, keys_path, {tmp_path / "a.mp4": first, tmp_path / "b.mp4": second}, options)
    assert len(caught) == 1  # the take the keys came from is within reach
