"""VRM avatars as rigs (issue 37): expressions read as the mix of their morph-target binds, named as
the avatar names them, in VRM 1.0 and 0.x; broken files refused in one line; the VMC output sends the
avatar's own expression names to a real OSC receiver."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from vrm_avatars import expected_delta, make_vrm, read_glb, write_glb

from keyshape.containers import KeyShapes
from keyshape.datasets import make_performance
from keyshape.exceptions import InputError, RigError
from keyshape.io import load_rig, load_vrm

NAMES_1 = ("aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft", "blinkRight", "happy", "lookUp", "smirk")
NAMES_0 = ("A", "I", "U", "E", "O", "Blink", "Blink_L", "Blink_R", "Joy", "LookUp", "Smirk")


@pytest.mark.parametrize("version, names", [("1.0", NAMES_1), ("0.x", NAMES_0)])
def test_expressions_are_the_weighted_sums_of_their_binds(tmp_path, version, names):
    avatar = make_vrm(tmp_path / "a.vrm", version)
    vrm = load_vrm(avatar.path)
    assert vrm.version == version and vrm.spec_version == ("1.0" if version == "1.0" else "0.0")
    assert vrm.rig.names == names == tuple(avatar.expressions) and vrm.arkit == ()
    np.testing.assert_allclose(vrm.rig.vertices, avatar.vertices, atol=1e-6)  # world space, facing +Z
    for name, binds in avatar.expressions.items():
        np.testing.assert_allclose(vrm.rig.deltas[names.index(name)], expected_delta(avatar, binds), atol=1e-7,
                                   err_msg=name)
    # the mixes are not trivial: "ih" is 0.6 wide + 0.2 open, "ee" moves the teeth (mesh 1) by half its morph
    ih = vrm.rig.deltas[names.index(names[1])]
    np.testing.assert_allclose(ih[:6], 0.6 * avatar.morphs[0, 1][:6] + 0.2 * avatar.morphs[0, 0][:6], atol=1e-7)
    ee = vrm.rig.deltas[names.index(names[3])]
    np.testing.assert_allclose(ee[6:], 0.5 * avatar.morphs[1, 0][6:], atol=1e-7)
    assert np.abs(ee[6:]).max() > 1e-3
    np.testing.assert_array_equal(vrm.rig.deltas[names.index(names[9])], 0.0)  # a look with no binds
    assert load_rig(avatar.path).names == names  # load_rig reads .vrm as a rig


def test_presets_in_either_spelling(tmp_path):
    one = load_vrm(make_vrm(tmp_path / "one.vrm", "1.0").path)
    zero = load_vrm(make_vrm(tmp_path / "zero.vrm", "0.x").path)
    assert [one.name_of(p) for p in ("aa", "oh", "blink", "blinkLeft", "happy")] == \
           ["aa", "oh", "blink", "blinkLeft", "happy"]
    assert [zero.name_of(p) for p in ("aa", "oh", "blink", "blinkLeft", "happy")] == \
           ["A", "O", "Blink", "Blink_L", "Joy"]
    assert zero.name_of("surprised") is None and zero.expressions[-1].preset is None  # Smirk is custom
    assert zero.expressions[1].binds == ((0, 1, 0.6), (0, 0, 0.2))  # 0..100 read as 0..1
    # the same avatar stored facing -Z (VRM 0.x) and +Z (1.0) reads to the same rig
    np.testing.assert_allclose(zero.rig.vertices, one.rig.vertices, atol=1e-7)
    np.testing.assert_array_equal(zero.rig.faces, one.rig.faces)
    np.testing.assert_allclose(zero.rig.deltas, one.rig.deltas, atol=1e-7)


@pytest.mark.parametrize("version", ["1.0", "0.x"])
def test_perfect_sync_keeps_the_arkit_morphs(tmp_path, version):
    avatar = make_vrm(tmp_path / "ps.vrm", version, perfect_sync=True)
    vrm = load_vrm(avatar.path)
    # jawOpen is an expression (bound to the jawOpen morph); mouthSmileLeft is only a morph target
    assert vrm.arkit == ("mouthSmileLeft",) and vrm.rig.names.count("jawOpen") == 1
    assert vrm.rig.names[-2:] == ("jawOpen", "mouthSmileLeft")
    np.testing.assert_allclose(vrm.rig.deltas[-1], avatar.morphs[0, 6], atol=1e-7)
    np.testing.assert_allclose(vrm.rig.deltas[-2], avatar.morphs[0, 5], atol=1e-7)
    assert "mouthOpen" not in vrm.rig.names  # morphs without ARKit names are reached through expressions


def _broken(tmp_path, version, change):
    path = make_vrm(tmp_path / "b.vrm", version).path
    document, blob = read_glb(path)
    change(document)
    return write_glb(path, document, blob)


def _vrm1(document):
    return document["extensions"]["VRMC_vrm"]["expressions"]


def _groups(document):
    return document["extensions"]["VRM"]["blendShapeMaster"]["blendShapeGroups"]


BROKEN = {
    "no extension": ("1.0", lambda d: d.pop("extensions"), "not a VRM avatar"),
    "morph out of range": ("1.0", lambda d: _vrm1(d)["preset"]["aa"]["morphTargetBinds"][0].update(index=9),
                           "binds morph target 9 of mesh 0, which has 5"),
    "node without a mesh": ("1.0", lambda d: _vrm1(d)["preset"]["aa"]["morphTargetBinds"][0].update(node=2),
                            "binds node 2, which has no mesh"),
    "unknown preset": ("1.0", lambda d: _vrm1(d)["preset"].update(yawn={}), "'yawn', not a VRM 1.0 preset"),
    "weight not a number": ("1.0", lambda d: _vrm1(d)["preset"]["ou"]["morphTargetBinds"][0].update(weight="x"),
                            "numeric weight"),
    "binds not a list": ("0.x", lambda d: _groups(d)[0].update(binds={"mesh": 0}), "binds is not a list"),
    "mesh out of range": ("0.x", lambda d: _groups(d)[2]["binds"][0].update(mesh=5),
                          "binds mesh 5, which has no morph targets"),
    "two of one name": ("0.x", lambda d: _groups(d)[1].update(presetName="a"), "two expressions are named 'A'"),
    "a group without a name": ("0.x", lambda d: _groups(d)[-1].update(name=""), "neither a preset nor a name"),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_a_broken_avatar_is_one_line_naming_the_file(tmp_path, case):
    version, change, problem = BROKEN[case]
    path = _broken(tmp_path, version, change)
    with pytest.raises(RigError) as error:
        load_rig(path)
    message = str(error.value)
    assert str(path) in message and problem in message and "\n" not in message, message


def test_a_truncated_or_missing_avatar(tmp_path):
    path = make_vrm(tmp_path / "t.vrm", "1.0").path
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(RigError, match=r"t\.vrm") as error:
        load_rig(path)
    assert "\n" not in str(error.value)
    with pytest.raises(RigError, match="no such VRM file"):
        load_rig(tmp_path / "missing.vrm")
    with pytest.raises(InputError, match="OBJ files only"):
        load_rig(make_vrm(tmp_path / "u.vrm", "0.x").path, unit=0.01)


@pytest.mark.parametrize("version, sent", [("0.x", ("A", "I", "U", "E", "O", "Blink")),
                                           ("1.0", ("aa", "ih", "ou", "ee", "oh", "blink"))])
def test_vmc_sends_the_avatars_own_names(tmp_path, version, sent):
    """What `live --rig avatar.vrm --map MAP --vmc` sends (the CLI's own live_targets and VmcSender), into
    a real python-osc receiver on loopback: the avatar's expression names in its version's spelling, the
    mapped values on them."""
    from test_live import _Receiver

    from keyshape.live import LiveFrame, VmcSender, live_targets

    avatar = make_vrm(tmp_path / "avatar.vrm", version)
    perf = make_performance(n_frames=12, n_landmarks=20, n_keys=6)
    keys = KeyShapes(perf.neutral, perf.key_deltas, tuple(f"k{i}" for i in range(perf.n_keys)),
                     np.zeros(perf.n_keys, int), perf.key_regions, perf.regions)
    vowels = sent[:5]
    gains = {f"k{i}": {vowels[i % 5]: 1.0} for i in range(perf.n_keys)}
    gains["k0"][sent[5]] = 0.5
    (tmp_path / "map.json").write_text(json.dumps(gains))
    targets = live_targets(keys, rig=avatar.path, mapping=tmp_path / "map.json")
    assert targets.names == tuple(avatar.expressions)
    weights = np.linspace(0.2, 0.9, perf.n_keys)
    values = targets.mapping.matrix @ weights
    frame = LiveFrame(0, 1.0, 0.0, targets.names, values, values, np.array([0.0, 0.0, 0.0, 1.0]), None, True,
                      np.zeros((4, 4, 3), np.uint8))
    with _Receiver() as receiver:
        sender = VmcSender("127.0.0.1", receiver.port, names=targets.names)
        sender.send(frame)
        sender.close()
        deadline = time.monotonic() + 5
        while not receiver.bundles and time.monotonic() < deadline:
            time.sleep(0.01)
    (got,) = receiver.bundles
    blend = dict(args for address, args in got if address == "/VMC/Ext/Blend/Val")
    assert tuple(blend) == tuple(avatar.expressions) and set(sent) <= set(blend)
    assert blend[sent[5]] == pytest.approx(0.5 * weights[0], abs=1e-6)  # Blink / blink, half of k0
    assert blend[vowels[0]] == pytest.approx(min(1.0, weights[0] + weights[5]), abs=1e-6)  # k0 + k5, clipped
    assert blend[vowels[1]] == pytest.approx(weights[1], abs=1e-6)
    assert blend[tuple(avatar.expressions)[8]] == 0.0  # Joy / happy: no key drives it


@pytest.mark.slow
def test_live_command_sends_the_vrm_0_names(demo_clip, tmp_path):
    """`keyshape live CLIP --keys K --rig avatar.vrm --map MAP --vmc 127.0.0.1:PORT` on a VRM 0.x avatar:
    every bundle a real OSC receiver gets carries the avatar's own names, `A`..`O`, `Blink`, in its order."""
    from test_live import _live, _Receiver

    from keyshape.io import save_keys

    avatar = make_vrm(tmp_path / "avatar.vrm", "0.x")
    perf = make_performance(n_frames=40, n_landmarks=478)  # MediaPipe's landmark count
    save_keys(KeyShapes(perf.neutral, perf.key_deltas, ["a", "b", "c", "d"], perf.extreme_frames,
                        perf.key_regions, perf.regions), tmp_path / "keys.json")
    (tmp_path / "map.json").write_text(json.dumps({"a": {"A": 1.0}, "b": {"O": 1.0}, "c": {"Blink": 1.0},
                                                   "d": {"I": 0.5, "E": 0.5, "U": 0.2}}))
    with _Receiver() as receiver:
        proc = _live(demo_clip, "--keys", tmp_path / "keys.json", "--rig", avatar.path, "--map",
                     tmp_path / "map.json", "--vmc", f"127.0.0.1:{receiver.port}", "--duration", "1")
        out, err = proc.communicate(timeout=120)
        time.sleep(0.2)
    assert proc.returncode == 0, err
    assert len(receiver.bundles) >= 5, out
    for got in receiver.bundles:
        names = [args[0] for address, args in got if address == "/VMC/Ext/Blend/Val"]
        assert tuple(names) == NAMES_0


def _vrm_parts(version: str) -> tuple[dict, bytes, bytes]:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = make_vrm(Path(folder) / "a.vrm", version, perfect_sync=True).path
        return (*read_glb(path), path.read_bytes())


def _glb_of(text: bytes, blob: bytes) -> bytes:
    import struct

    text += b" " * (-len(text) % 4)
    body = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(blob), b"BIN\0") + blob
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def _fuzz():
    from hypothesis import strategies as st
    from test_readers_fuzz import byte_edits, json_edits

    cases = []
    for version in ("1.0", "0.x"):
        document, blob, data = _vrm_parts(version)
        cases += [json_edits(document).map(lambda text, blob=blob: _glb_of(text, blob)),
                  json_edits(document["extensions"]).map(
                      lambda text, d=document, b=blob: _glb_of(json.dumps({**d, "extensions": json.loads(text)})
                                                               .encode(), b)),
                  byte_edits(data)]
    return st.one_of(cases)


def test_no_mutated_avatar_gives_a_traceback(tmp_path_factory):
    """Mutations of both avatars (their JSON, their VRM extension, their bytes), as the readers' fuzz
    test draws them: every one loads or raises keyshape's own error in one line."""
    from hypothesis import given
    from test_readers_fuzz import FUZZ, _loads_or_one_line

    @FUZZ
    @given(_fuzz())
    def check(data):
        path = tmp_path_factory.mktemp("vrm-fuzz") / "avatar.vrm"
        path.write_bytes(data)
        _loads_or_one_line(load_rig, path)

    check()


def test_unnamed_morph_targets_are_reached_by_index(tmp_path):
    """Many exporters leave morph targets unnamed: the expressions are the same (binds are indices),
    only the perfect-sync morphs, which need their names, are not kept."""
    avatar = make_vrm(tmp_path / "named.vrm", "1.0", perfect_sync=True)
    named = load_vrm(avatar.path)

    def unname(document):
        for mesh in document["meshes"]:
            mesh.pop("extras")

    path = make_vrm(tmp_path / "ps.vrm", "1.0", perfect_sync=True).path
    document, blob = read_glb(path)
    unname(document)
    unnamed = load_vrm(write_glb(path, document, blob))
    assert unnamed.arkit == () and unnamed.rig.names == named.rig.names[:-1]
    np.testing.assert_array_equal(unnamed.rig.deltas, named.rig.deltas[:-1])
    np.testing.assert_array_equal(unnamed.rig.vertices, named.rig.vertices)


@pytest.mark.validator
@pytest.mark.parametrize("version", ["1.0", "0.x"])
def test_the_test_avatars_are_valid_gltf(tmp_path, version):
    """The Khronos validator finds no error in the hand-written avatars (it does not know the VRM
    extensions; VRM 0.x's own name, `VRM`, lacks a vendor prefix, a warning every VRM 0.x file has)."""
    from gltf_validator import validate

    path = make_vrm(tmp_path / "a.vrm", version, perfect_sync=True).path
    glb = path.with_suffix(".glb")
    glb.write_bytes(path.read_bytes())
    report = validate(glb)
    assert report["numErrors"] == 0, report["messages"]
    assert {m["code"] for m in report["messages"] if m["severity"] <= 1} <= {"INVALID_EXTENSION_NAME_FORMAT"}
    assert version == "0.x" or report["numWarnings"] == 0


def test_retarget_onto_an_avatar(tmp_path):
    """`keyshape retarget W.csv --rig avatar.vrm -o anim.glb`: a new file whose morph targets are the
    avatar's expressions (as mixes), animated by the weights."""
    from keyshape.cli import main
    from keyshape.containers import Weights
    from keyshape.io import save_weights_csv
    from keyshape.io.gltf import read_glb_animation

    avatar = make_vrm(tmp_path / "avatar.vrm", "0.x")
    rig = load_rig(avatar.path)
    values = np.random.default_rng(1).random((5, rig.n_targets))
    save_weights_csv(Weights(values, rig.names, 30.0), tmp_path / "w.csv")
    assert main(["retarget", str(tmp_path / "w.csv"), "--rig", str(avatar.path), "-o", str(tmp_path / "a.glb"),
                 "-q"]) == 0
    written = load_rig(tmp_path / "a.glb")
    assert written.names == rig.names == NAMES_0
    np.testing.assert_allclose(written.pose(values), rig.pose(values), atol=1e-6)
    animation = read_glb_animation(tmp_path / "a.glb")
    np.testing.assert_allclose(animation.weights, values, atol=1e-6)
