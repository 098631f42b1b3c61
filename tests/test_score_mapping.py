"""The score mapping fitted on the whole take (targets._propose._take_mapping) on a synthetic take
with a known key -> ARKit relation, against reading each key's frame alone."""

import numpy as np

from keyshape.containers import KeyShapes, Rig
from keyshape.targets import KeyScores
from keyshape.targets._propose import _take_mapping


def _setup(seed=0, n_frames=400, noise=0.08, low=0.0):
    rng = np.random.default_rng(seed)
    n_keys, n_targets = 4, 6
    keys = KeyShapes(np.zeros((3, 2)), np.ones((n_keys, 3, 2)), ("upper_00", "upper_01", "lower_00", "lower_01"),
                     [10, 20, 30, 40], ("upper", "upper", "lower", "lower"), {"upper": [0], "lower": [1, 2]})
    names = tuple(f"t{i}" for i in range(n_targets))
    rig = Rig(np.zeros((3, 3)), [[0, 1, 2]], np.zeros((n_targets, 3, 3)), names)
    own = np.array([[1, 1, 0, 0]] * 3 + [[0, 0, 1, 1]] * 3, dtype=bool)  # targets 0-2 upper, 3-5 lower
    gains = np.maximum(rng.uniform(-0.1, 0.35, (n_targets, n_keys)), low) * own  # readings stay in [0, 1]
    offset = rng.uniform(0.2, 0.4, n_targets)
    weights = rng.uniform(0, 1, (n_frames, n_keys)) * (rng.uniform(size=(n_frames, n_keys)) < 0.4)
    truth = offset + weights @ gains.T
    scores = np.clip(truth + noise * rng.standard_normal(truth.shape), 0, 1)
    return keys, rig, own, gains, offset, weights, truth, scores


def test_the_whole_take_recovers_the_keys_relation():
    keys, rig, own, gains, offset, weights, truth, scores = _setup()
    rest = np.full(rig.n_targets, 0.1)  # the tracker reads the character at 0.1 at rest
    bundle = KeyScores(np.zeros(6), np.zeros((4, 6)), rig.names, take=np.clip(scores + rest, 0, 1), weights=weights)
    mapping = _take_mapping(keys, rig, np.eye(6), own, bundle, rest)
    assert np.abs(mapping.matrix - gains).max() < 0.05 and np.abs(mapping.offset - offset).max() < 0.03
    assert np.all(mapping.matrix[~own] == 0)  # a key drives only its own region's targets
    fitted = mapping.offset + weights @ mapping.matrix.T
    # reading each key's frame alone: the gains are that frame's scores minus the neutral frame's
    frame = np.argmax(weights, axis=0)
    alone = scores[frame] - scores[np.argmin(weights.sum(axis=1))]
    by_frames = scores[np.argmin(weights.sum(axis=1))] + weights @ (alone.T * own).T
    assert np.abs(fitted - truth).mean() < 0.5 * np.abs(by_frames - truth).mean()


def test_too_few_frames_fall_back():
    keys, rig, own, _, _, weights, _, scores = _setup(n_frames=6)
    bundle = KeyScores(np.zeros(6), np.zeros((4, 6)), rig.names, take=scores, weights=weights)
    assert _take_mapping(keys, rig, np.eye(6), own, bundle, np.zeros(6)) is None


def test_frames_without_a_face_are_left_out():
    keys, rig, own, gains, _, weights, _, scores = _setup(seed=1)
    scores[::5] = np.nan
    bundle = KeyScores(np.zeros(6), np.zeros((4, 6)), rig.names, take=scores, weights=weights)
    mapping = _take_mapping(keys, rig, np.eye(6), own, bundle, np.zeros(6))
    assert np.isfinite(mapping.matrix).all() and np.abs(mapping.matrix - gains).max() < 0.06


def test_gaze_follows_its_scores_frame_by_frame(tmp_path):
    """Gaze on its own channel: each gaze target follows its score less the character's rest
    reading; the keys (expressions) cannot carry a look that is independent of them."""
    from keyshape.containers import Weights
    from keyshape.targets import Mapping, drive_gaze, gaze_channels, retarget

    keys, rig, own, gains, offset, weights, truth, scores = _setup(seed=2)
    rng = np.random.default_rng(3)
    look = np.clip(0.5 + 0.4 * np.sin(np.arange(len(weights)) / 9.0), 0, 1)  # a slow look, not an expression
    names = ("eyeLookInLeft", "eyeLookOutRight", "jawOpen")
    rest = {"eyeLookInLeft": 0.1, "eyeLookOutRight": 0.05, "jawOpen": 0.2}
    read = np.column_stack([look + 0.1, look + 0.05, rng.uniform(size=len(look))])
    read[[0, 7, 8]] = np.nan  # frames without a face; the first is held from the next
    rig_names = ("jawOpen", "eyeLookIn_L", "eyeLookOut_R", "eyeLookIn_R")
    entries = gaze_channels(names, rig_names, rest=rest)
    assert entries == (("eyeLookIn_L", "eyeLookInLeft", 0.1), ("eyeLookOut_R", "eyeLookOutRight", 0.05))
    mapping = Mapping(np.array([[1.0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]]), keys.names, rig_names,
                      gaze=entries)
    again = Mapping.from_file(mapping.save(tmp_path / "map.json"), targets=rig_names)  # the file keeps them
    assert again.gaze == entries
    anim = drive_gaze(retarget(Weights(weights, keys.names, 30.0), again), again, read, names)
    expected = np.column_stack([look, look])
    expected[[7, 8]] = (2 * expected[6] + expected[9]) / 3, (expected[6] + 2 * expected[9]) / 3
    expected[0] = expected[1]
    np.testing.assert_allclose(anim.values[:, [1, 2]], expected, atol=1e-12)
    np.testing.assert_allclose(anim.values[:, 0], weights[:, 0])  # the keys' targets as retarget made them
    assert not anim.values[:, 3].any()  # no score names it
    # the same look read through the key weights (what a key mapping can do) is nearly flat
    bundle = KeyScores(np.zeros(6), np.zeros((4, 6)), rig.names, take=np.column_stack([look] * 6), weights=weights)
    through_keys = _take_mapping(keys, rig, np.eye(6), own, bundle, np.zeros(6))
    fitted = through_keys.offset[0] + weights @ through_keys.matrix[0]
    assert np.abs(fitted - look).mean() > 10 * np.abs(expected[1:, 0] - look[1:]).mean() + 0.1


def test_gaze_entries_are_checked(tmp_path):
    import json

    import pytest

    from keyshape.exceptions import InputError, RigError
    from keyshape.targets import Mapping

    with pytest.raises(InputError, match="no key gain or offset"):
        Mapping(np.ones((1, 1)), ("k",), ("eyeLookIn_L",), gaze=(("eyeLookIn_L", "eyeLookInLeft", 0.1),))
    with pytest.raises(RigError, match="gaze targets the rig does not have"):
        Mapping(np.zeros((1, 1)), ("k",), ("jawOpen",), gaze=(("eyeLookIn_L", "eyeLookInLeft", 0.1),))
    bad = tmp_path / "map.json"
    bad.write_text(json.dumps({"format": "keyshape-map", "version": 1, "gains": {"k": {"jawOpen": 1.0}},
                               "gaze": {"eyeLookIn_L": {"score": "eyeLookInLeft", "rest": 1.5}}}))
    with pytest.raises(InputError, match=r"map\.json: .*rest must be in \[0, 1\]"):
        Mapping.from_file(bad, targets=("jawOpen", "eyeLookIn_L"))


def test_the_fitted_gains_are_never_negative_nor_negligible():
    """Issue 36 item 11: map.json's gains are >= 0, as `retarget --help` says, even where the take's
    readings fall with a key (the fit was unbounded below zero, 165 of 522 gains negative on an RPM
    run), and none is left in (0, 1e-3): such a gain moves nothing."""
    from keyshape.targets._mapping import SMALLEST_GAIN

    keys, rig, own, gains, _, weights, truth, scores = _setup(seed=3, low=-1.0)  # readings fall with some keys
    assert (gains < -0.02).sum() >= 3
    bundle = KeyScores(np.zeros(6), np.zeros((4, 6)), rig.names, take=scores, weights=weights)
    mapping = _take_mapping(keys, rig, np.eye(6), own, bundle, np.zeros(6))
    assert (mapping.matrix >= 0).all() and not ((mapping.matrix > 0) & (mapping.matrix < SMALLEST_GAIN)).any()
    assert (mapping.matrix[gains > 0.05] > 0).all()  # what a key does raise, it still raises
    fitted = mapping.offset + weights @ mapping.matrix.T
    best_constant = np.abs(scores - scores.mean(axis=0)).mean()
    assert np.abs(fitted - truth).mean() < 0.7 * best_constant  # and the fit still explains the take
