"""Automatic targets onto VRM avatars (issue 37, item 2): on the hand-written avatars, a key that opens
the jaw drives the open vowel more than the rounded one, a puckered key the rounded one, the blink key
the blinks, no emotion is driven, a perfect-sync avatar gets its ARKit targets, a VRM 0.x avatar its
0.x names; `run --auto-targets` on the real clip writes a map.json over the avatar's expressions and
an animation.vrma the Khronos validator passes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from vrm_avatars import make_vrm

from keyshape.containers import KeyShapes
from keyshape.targets import KeyScores, auto_targets

SCORES = ("_neutral", "eyeBlinkLeft", "eyeBlinkRight", "eyeLookUpLeft", "eyeLookDownLeft", "eyeLookOutLeft",
          "eyeLookOutRight", "jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthStretchLeft",
          "mouthStretchRight", "mouthSmileLeft", "mouthSmileRight", "browInnerUp")
KEYS = {"lower_jaw": {"jawOpen": 0.6}, "lower_pucker": {"mouthPucker": 0.7, "mouthFunnel": 0.2},
        "lower_smile": {"mouthSmileLeft": 0.5, "mouthSmileRight": 0.5, "mouthStretchLeft": 0.4,
                        "mouthStretchRight": 0.4, "jawOpen": 0.05},
        "upper_blink": {"eyeBlinkLeft": 0.8, "eyeBlinkRight": 0.7}}


def _keys_and_scores() -> tuple[KeyShapes, KeyScores]:
    """Four keys (three of the mouth, one blink) and their scores: a neutral at 0.1 everywhere, each
    key's scores the neutral's plus its own changes (and a blink change on a mouth key, to be ignored)."""
    rng = np.random.default_rng(2)
    regions = {"upper": np.array([145, 159, 374, 386]), "lower": np.array([13, 14, 0, 17])}
    deltas = np.zeros((len(KEYS), 478, 3))
    names = tuple(KEYS)
    keys = KeyShapes(rng.normal(size=(478, 3)), deltas, names, np.arange(1, 5), tuple(n.split("_")[0] for n in names),
                     regions)
    neutral = np.full(len(SCORES), 0.1)
    rows = np.tile(neutral, (len(KEYS), 1))
    for k, change in enumerate(KEYS.values()):
        for score, value in change.items():
            rows[k, SCORES.index(score)] += value
    rows[0, SCORES.index("eyeBlinkLeft")] += 0.5  # a mouth key's blink: not a blink key
    return keys, KeyScores(neutral, rows, SCORES)


def _gain(mapping, key, target) -> float:
    return float(mapping.matrix[mapping.targets.index(target), mapping.sources.index(key)])


@pytest.mark.parametrize("version", ["1.0", "0.x"])
def test_standard_avatar_vowels_blinks_looks(tmp_path, version):
    avatar = make_vrm(tmp_path / "avatar.vrm", version)
    keys, scores = _keys_and_scores()
    auto = auto_targets(keys, avatar.path, scores=scores)
    m = auto.mapping
    spelling = {"1.0": ("aa", "ih", "ou", "ee", "oh", "blinkLeft", "blinkRight", "happy", "lookUp"),
                "0.x": ("A", "I", "U", "E", "O", "Blink_L", "Blink_R", "Joy", "LookUp")}[version]
    n = dict(zip(("aa", "ih", "ou", "ee", "oh", "L", "R", "joy", "up"), spelling))
    assert set(m.targets) == set(avatar.expressions) and (m.matrix >= 0).all()
    assert _gain(m, "lower_jaw", n["aa"]) > 0.3 and _gain(m, "lower_jaw", n["aa"]) > 2 * _gain(m, "lower_jaw", n["ou"])
    assert _gain(m, "lower_pucker", n["ou"]) > 0.3
    assert _gain(m, "lower_pucker", n["ou"]) > 2 * max(_gain(m, "lower_pucker", n["aa"]),
                                                       _gain(m, "lower_pucker", n["ih"]))
    spread = {v: _gain(m, "lower_smile", n[v]) for v in ("aa", "ih", "ou", "ee", "oh")}
    assert max(spread, key=spread.get) in ("ih", "ee") and spread["ou"] == 0
    # the blink key drives each side by its own score; the mouth key's stray blink drives nothing
    assert _gain(m, "upper_blink", n["L"]) == pytest.approx(0.8)
    assert _gain(m, "upper_blink", n["R"]) == pytest.approx(0.7)
    assert _gain(m, "lower_jaw", n["L"]) == 0 and _gain(m, "upper_blink", n["aa"]) == 0
    assert not m.matrix[m.targets.index(n["joy"])].any() and not m.matrix[m.targets.index("blink" if version ==
                                                                                            "1.0" else "Blink")].any()
    assert (n["up"], "eyeLookUpLeft", 0.0) in m.gaze and auto.correspondence is None
    saved = json.loads(m.save(tmp_path / "map.json").read_text())  # what the take writes: the avatar's names
    assert set(saved["gains"]["lower_jaw"]) <= set(avatar.expressions) and n["aa"] in saved["gains"]["lower_jaw"]


def test_only_blink_when_the_avatar_has_no_sides(tmp_path):
    from keyshape.targets._vrm import vrm_mapping

    keys, scores = _keys_and_scores()
    m = vrm_mapping(keys, ["aa", "ih", "ou", "ee", "oh", "blink", "happy"], scores)
    assert _gain(m, "upper_blink", "blink") == pytest.approx(0.75) and not m.gaze


def test_perfect_sync_avatar_gets_its_arkit_targets(tmp_path):
    avatar = make_vrm(tmp_path / "avatar.vrm", "1.0", perfect_sync=True)
    keys, scores = _keys_and_scores()
    m = auto_targets(keys, avatar.path, scores=scores).mapping
    assert _gain(m, "lower_jaw", "jawOpen") == pytest.approx(0.6)
    assert _gain(m, "lower_smile", "mouthSmileLeft") == pytest.approx(0.5)
    assert _gain(m, "upper_blink", "jawOpen") == 0  # a blink key drives no mouth target
    assert not m.matrix[[m.targets.index(t) for t in ("aa", "ou", "blink", "happy")]].any()  # the ARKit route
    assert m.offset[m.targets.index("jawOpen")] == pytest.approx(0.1)


def test_vowels_of_a_prototype_are_that_vowel():
    from keyshape.targets._vrm import VOWEL_PROTOTYPES, vowel_weights

    np.testing.assert_allclose(vowel_weights(VOWEL_PROTOTYPES.T * 0.5), np.eye(5) * 0.5, atol=1e-9)
    assert not vowel_weights(-VOWEL_PROTOTYPES.T).any()  # a mouth more closed than the neutral: no vowel


@pytest.mark.slow
@pytest.mark.validator
@pytest.mark.parametrize("version, sync", [("1.0", False), ("0.x", False), ("1.0", True)])
def test_run_auto_targets_on_a_vrm_avatar(demo_clip, tmp_path, version, sync):
    """The real clip through `run --rig avatar.vrm --auto-targets`: map.json over the avatar's names (gains
    >= 0, vowels and blinks driven, emotions not), animation.vrma carrying it, valid for Khronos."""
    from test_vrma import expression_track, read_vrma

    from keyshape.cli import main
    from keyshape.io import load_weights_csv
    from keyshape.io.rig import load_rig
    from keyshape.targets import Mapping, retarget

    from gltf_validator import validate

    avatar = make_vrm(tmp_path / "avatar.vrm", version, skeleton=True, perfect_sync=sync)
    out = tmp_path / "take"
    assert main(["run", str(demo_clip), "--rig", str(avatar.path), "--auto-targets", "--no-preview",
                 "-o", str(out), "-q"]) == 0
    mapping = Mapping.from_file(out / "map.json")
    vowels, blinks, joy = (("aa", "ih", "ou", "ee", "oh"), ("blink", "blinkLeft", "blinkRight"), "happy") \
        if version == "1.0" else (("A", "I", "U", "E", "O"), ("Blink", "Blink_L", "Blink_R"), "Joy")
    gains = json.loads((out / "map.json").read_text())["gains"]
    driven = {t for row in gains.values() for t in row}
    if sync:  # the ARKit route: its ARKit targets, not the presets
        assert "jawOpen" in driven and not driven & {*vowels, *blinks, joy}
        vowels = ("jawOpen",)
    else:
        assert driven & set(vowels) and driven & set(blinks)
    assert driven & set(vowels) and joy not in driven and driven <= set(load_rig(avatar.path).names)
    assert (mapping.matrix >= 0).all() and not (out / "correspondence.json").exists()
    extension, tracks, _ = read_vrma(out / "animation.vrma")
    weights = load_weights_csv(out / "weights.csv")
    anim = retarget(weights, mapping)
    spelled = dict(zip(vowels, ("aa", "ih", "ou", "ee", "oh") if not sync else ("jawOpen",)))
    for name in sorted(driven & set(vowels)):
        group = "custom" if sync else "preset"
        np.testing.assert_allclose(expression_track(extension, tracks, group, spelled[name]),
                                   np.clip(anim.values[:, anim.names.index(name)], 0, 1), atol=1e-5)
    glb = tmp_path / "animation.glb"
    glb.write_bytes((out / "animation.vrma").read_bytes())
    report = validate(glb)
    assert report["numErrors"] == 0, report["messages"]


def test_keys_of_another_take_read_off_the_take():
    """Keys whose frames are not in the take (NaN scores there): each key's change comes from the take's
    scores regressed on its weights, so a jaw key still drives `aa` by the jaw's change per unit weight."""
    from keyshape.targets._vrm import vrm_mapping

    keys, scores = _keys_and_scores()
    rng = np.random.default_rng(5)
    weights = rng.random((60, keys.n_keys))
    take = scores.neutral[None] + weights @ (scores.keys - scores.neutral[None])
    reused = KeyScores(np.full(len(SCORES), np.nan), np.full(scores.keys.shape, np.nan), SCORES, take, weights)
    direct, fitted = vrm_mapping(keys, ["aa", "ih", "ou", "ee", "oh", "blink"], scores), \
        vrm_mapping(keys, ["aa", "ih", "ou", "ee", "oh", "blink"], reused)
    np.testing.assert_allclose(fitted.matrix, direct.matrix, atol=1e-6)
    assert _gain(fitted, "lower_jaw", "aa") > 0.3
