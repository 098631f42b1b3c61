"""The command line end to end: the real clip through every verb, and bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from keyshape.cli import main
from keyshape.containers import Rig
from keyshape.io.gltf import read_glb_animation
from keyshape.io.keys_json import load_keys
from keyshape.io.rig import load_rig, save_obj_folder
from keyshape.io.track import load_track
from keyshape.io.weights_csv import load_weights_csv

from gltf_validator import validate

VERBS = ["track", "keys", "solve", "retarget", "run", "demo"]


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "keyshape", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=600, check=False)  # callers check the exit code


def test_help_explains_every_verb():
    result = _cli("--help")
    assert result.returncode == 0
    for verb in VERBS:
        assert verb in result.stdout
    for verb, option in [("keys", "--method"), ("keys", "--regions"), ("keys", "--neutral"),
                         ("retarget", "--rig"), ("run", "--count"), ("track", "-o")]:
        text = _cli(verb, "--help").stdout
        assert option in text, (verb, option)


def test_usage_error_exits_2():
    assert _cli("keys").returncode == 2
    assert _cli("keys", "a.npz", "-o", "k.json", "--method", "pca").returncode == 2


def test_demo_writes_every_output(demo_out):
    names = {p.name for p in demo_out.iterdir()}
    assert {"track.npz", "keys.json", "weights.csv", "animation.glb"} <= names
    track = load_track(demo_out / "track.npz")
    assert track.n_frames == 472 and track.valid.mean() >= 0.95
    keys = load_keys(demo_out / "keys.json")
    assert (~keys.mirrored).sum() == 16 and set(keys.regions) == {"upper", "lower"}  # 8 frames per region
    assert 0 < keys.mirrored.sum() <= 16  # and the mirrors that add reach
    assert track.valid[keys.frames].all() and keys.neutral_frame not in keys.frames
    weights = load_weights_csv(demo_out / "weights.csv")
    assert weights.names == keys.names and weights.n_frames == 472
    assert np.nanmin(weights.values) >= 0


def test_demo_glb_is_valid_and_animated(demo_out):
    report = validate(demo_out / "animation.glb")
    assert report["numErrors"] == 0, report["messages"][:5]
    anim = read_glb_animation(demo_out / "animation.glb")
    weights = load_weights_csv(demo_out / "weights.csv")
    assert report["numWarnings"] == 0, report["messages"][:5]
    from keyshape.targets import GAZE_NAMES

    assert tuple(anim.names) == (*weights.names, *GAZE_NAMES)  # the built-in head's eyes follow the gaze
    np.testing.assert_allclose(anim.weights[:, :weights.n_channels], np.nan_to_num(weights.values), atol=1e-6)
    assert anim.weights[:, weights.n_channels:].max() > 0.05
    assert anim.rotations is not None and len(anim.rotations) == 472
    assert anim.times[-1] == pytest.approx(471 / 23.976, rel=1e-4)


@pytest.mark.parametrize("method", ["spa", "hull", "spread"])
def test_verbs_one_by_one(demo_out, tmp_path, method):
    track = demo_out / "track.npz"
    keys = tmp_path / "keys.json"
    assert main(["keys", str(track), "-o", str(keys), "--method", method, "--count", "5", "-q",
                 "--regions", "eyes"]) == 0
    k = load_keys(keys)
    assert (~k.mirrored).sum() == 20 and k.method == method
    weights = tmp_path / "w.csv"
    assert main(["solve", str(track), str(keys), "-o", str(weights), "-q"]) == 0
    assert load_weights_csv(weights).names == k.names


def test_retarget_onto_an_obj_rig(demo_out, tmp_path):
    """The sculpting route: a rig exported as OBJs, one target per key, drives the character."""
    glb_rig = load_rig(demo_out / "animation.glb")
    n = len(load_weights_csv(demo_out / "weights.csv").names)  # one target per key: the gaze targets left out
    glb_rig = Rig(glb_rig.vertices, glb_rig.faces, glb_rig.deltas[:n], glb_rig.names[:n])
    folder = save_obj_folder(glb_rig, tmp_path / "rig")
    out = tmp_path / "anim.glb"
    assert main(["retarget", str(demo_out / "weights.csv"), "--rig", str(folder), "--track",
                 str(demo_out / "track.npz"), "-o", str(out), "-q"]) == 0
    assert validate(out)["numErrors"] == 0
    anim = read_glb_animation(out)
    weights = load_weights_csv(demo_out / "weights.csv")
    columns = [weights.names.index(name) for name in anim.names]  # the rig's own target order
    assert sorted(anim.names) == sorted(weights.names)
    np.testing.assert_allclose(anim.weights, np.nan_to_num(weights.values[:, columns]), atol=1e-6)


def test_neutral_option(demo_out, tmp_path):
    keys = tmp_path / "k.json"
    assert main(["keys", str(demo_out / "track.npz"), "-o", str(keys), "--neutral", "100", "-q"]) == 0
    assert load_keys(keys).neutral_frame == 100
    assert 100 not in load_keys(keys).frames


def _assert_clean_failure(result, out_path, *needles):
    assert result.returncode == 1, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in lines[0]
    assert not out_path.exists()
    assert not list(out_path.parent.glob(".*part*"))


def test_missing_file(tmp_path):
    out = tmp_path / "t.npz"
    _assert_clean_failure(_cli("track", tmp_path / "missing.mp4", "-o", out), out,
                          "missing.mp4", "not found")


def test_not_a_video(tmp_path):
    fake = tmp_path / "notes.mp4"
    fake.write_text("just text\n" * 100)
    out = tmp_path / "t.npz"
    _assert_clean_failure(_cli("track", fake, "-o", out), out, "notes.mp4", "not a video")


def test_video_with_no_face(faceless_video, tmp_path):
    out = tmp_path / "outdir"
    _assert_clean_failure(_cli("run", faceless_video, "-o", out), out, "noise.mp4", "no face")


def test_track_with_wrong_shape(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, points=np.zeros((10, 478)), fps=30.0)
    out = tmp_path / "k.json"
    _assert_clean_failure(_cli("keys", bad, "-o", out), out, "bad.npz", "points must have shape")


def test_rig_without_needed_targets(demo_out, tmp_path):
    rig = load_rig(demo_out / "animation.glb")
    from keyshape.containers import Rig

    partial = Rig(rig.vertices, rig.faces, rig.deltas[:3], ("smile", *rig.names[1:3]))
    folder = save_obj_folder(partial, tmp_path / "rig")
    out = tmp_path / "anim.glb"
    result = _cli("retarget", demo_out / "weights.csv", "--rig", folder, "-o", out)
    _assert_clean_failure(result, out, "upper_00", "lower_07")


def test_run_on_a_2d_track_from_another_tool(demo_out, tmp_path):
    """keys and solve accept any points+fps file: here 2D, 68 points (iBUG-like subset)."""
    track = load_track(demo_out / "track.npz")
    ids = np.linspace(0, 467, 68).astype(int)
    path = tmp_path / "other.npz"
    np.savez(path, points=track.points[:, ids, :2], fps=track.fps)
    keys = tmp_path / "k.json"
    assert main(["keys", str(path), "-o", str(keys), "--regions", "whole", "--count", "4", "-q"]) == 0
    assert main(["solve", str(path), str(keys), "-o", str(tmp_path / "w.csv"), "-q"]) == 0
    assert load_weights_csv(tmp_path / "w.csv").n_channels == load_keys(keys).n_keys >= 4


def test_solve_options(demo_out, tmp_path, capsys):
    track, keys = demo_out / "track.npz", demo_out / "keys.json"
    runs = {"default": [], "paper": ["--smooth", "0", "--max", "none"], "convex": ["--convex"]}
    got = {}
    for name, extra in runs.items():
        out = tmp_path / f"{name}.csv"
        assert main(["solve", str(track), str(keys), "-o", str(out), "-q", *extra]) == 0
        got[name] = load_weights_csv(out).values
    assert got["default"].min() >= 0 and got["default"].max() <= 1 + 1e-9
    jitter = {k: np.abs(np.diff(v, 2, axis=0)).mean() for k, v in got.items()}
    assert jitter["default"] < 0.6 * jitter["paper"]  # zero-lag smoothing by default
    k = load_keys(keys)
    for region in k.regions:
        sums = got["convex"][:, k.keys_of(region)].sum(axis=1)
        assert sums.max() <= 1 + 1e-5  # the CSV keeps 6 decimals
    with pytest.raises(SystemExit) as exc:
        main(["solve", str(track), str(keys), "-o", str(tmp_path / "x.csv"), "--max", "-1"])
    assert exc.value.code == 2
    # a bound above what a weights file holds is refused before any work (apply would refuse the file)
    with pytest.raises(SystemExit) as exc:
        main(["solve", str(track), str(keys), "-o", str(tmp_path / "x.csv"), "--max", "6"])
    assert exc.value.code == 2
    assert "at most 5" in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()


def test_count_auto_reaches_the_target(demo_out, tmp_path, capsys):
    keys_path = tmp_path / "auto.json"
    assert main(["keys", str(demo_out / "track.npz"), "-o", str(keys_path), "--count", "auto",
                 "--max-error", "1.5"]) == 0
    line = next(text for text in capsys.readouterr().out.splitlines() if text.startswith("fit:"))
    import re

    found = re.findall(r"(\w+): K = (\d+), RMS error ([\d.]+)", line)
    assert {r for r, _, _ in found} == {"upper", "lower"}
    keys = load_keys(keys_path)
    from keyshape.app import fit_errors

    exact, _ = fit_errors(load_track(demo_out / "track.npz"), keys)
    for region, k, error in found:
        # the line rounds to 0.01 (the demo's upper region reaches 1.498); the exact figure is below
        assert float(error) <= 1.5 and exact[region] < 1.5
        assert abs(float(error) - exact[region]) <= 0.005
        assert len(keys.keys_of(region)) == int(k) and 1 <= int(k) <= 24


def test_gaze_reaches_live_link(demo_out, tmp_path):
    import json

    from keyshape.io.livelink import ROTATION_NAMES, read_livelink_csv

    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"upper_00": {"eyeBlinkLeft": 1.0}, "lower_00": {"jawOpen": 1.0}}))
    out = tmp_path / "take.csv"
    assert main(["retarget", str(demo_out / "weights.csv"), "--map", str(mapping), "--format", "livelink",
                 "--track", str(demo_out / "track.npz"), "-o", str(out), "-q"]) == 0
    take = read_livelink_csv(out, fps=23.976)
    eyes = take.rotations[:, [ROTATION_NAMES.index(n) for n in ("LeftEyeYaw", "LeftEyePitch",
                                                               "RightEyeYaw", "RightEyePitch")]]
    assert np.abs(eyes).max() > np.radians(3)  # the actor's eyes move in this clip
    left, right = eyes[:, 0], eyes[:, 2]
    assert np.corrcoef(left, right)[0, 1] > 0.5  # both eyes turn together


def test_run_auto_targets_onto_a_human_like_rig(demo_clip, demo_out, tmp_path):
    """One command, no sculpting: the stylised head of the demo, as a rig with its own shapes."""
    out = tmp_path / "auto"
    assert main(["run", str(demo_clip), "--end", "96", "--rig", str(demo_out / "animation.glb"),
                 "--auto-targets", "--no-preview", "-o", str(out), "-q"]) == 0
    report = validate(out / "animation.glb")
    assert report["numErrors"] == 0, report["messages"][:5]
    anim = read_glb_animation(out / "animation.glb")
    assert anim.weights.shape[0] == 96 and anim.weights.max() > 0.05
    # the proposal is saved beside the outputs, and it is exactly what drove the character, but for
    # the gaze targets, which follow the gaze scores frame by frame (less the character's at rest)
    from keyshape.targets import Mapping, drive_gaze, retarget

    mapping = Mapping.from_file(out / "map.json", targets=list(anim.names))
    track = load_track(out / "track.npz")
    driven = retarget(load_weights_csv(out / "weights.csv"), mapping)
    np.testing.assert_allclose(drive_gaze(driven, mapping, track.blendshapes, track.blendshape_names).values,
                               anim.weights, atol=1e-5)
    rest = json.loads((out / "correspondence.json").read_text())["rest_scores"]
    gaze = [anim.names.index(t) for t, _, _ in mapping.gaze]
    assert len(gaze) == 8 and not mapping.matrix[gaze].any() and anim.weights[:, gaze].std(axis=0).max() > 0.02
    assert {t: r for t, _, r in mapping.gaze}["eyeLookInLeft"] == pytest.approx(rest["eyeLookInLeft"], abs=1e-6)
    # retarget with the track reproduces the run's animation, gaze included
    again_glb = tmp_path / "again.glb"
    assert main(["retarget", str(out / "weights.csv"), "--rig", str(demo_out / "animation.glb"), "--map",
                 str(out / "map.json"), "--track", str(out / "track.npz"), "-o", str(again_glb), "-q"]) == 0
    redone = read_glb_animation(again_glb)
    np.testing.assert_allclose(np.column_stack([redone.weights[:, redone.names.index(n)] for n in anim.names]),
                               anim.weights, atol=1e-5)
    assert len(json.loads((out / "correspondence.json").read_text())["landmarks"]) > 50
    # edited files go back in: the same keys and correspondence give the same map
    again = tmp_path / "again"
    assert main(["run", str(demo_clip), "--end", "96", "--rig", str(demo_out / "animation.glb"),
                 "--auto-targets", "--correspondence", str(out / "correspondence.json"),
                 "--keys", str(out / "keys.json"), "--no-preview", "-o", str(again), "-q"]) == 0
    first, second = (Mapping.from_file(d / "map.json", targets=list(anim.names)) for d in (out, again))
    assert first.sources == second.sources  # the files round to a few digits
    np.testing.assert_allclose(second.matrix, first.matrix, atol=1e-4)


@pytest.mark.parametrize("option", [("--correspondence", "c.json"), ("--no-refine",), ("--floor",)])
def test_run_correspondence_needs_auto_targets(demo_clip, tmp_path, option):
    given = [tmp_path / o if o.endswith(".json") else o for o in option]
    result = _cli("run", demo_clip, *given, "-o", tmp_path / "o")
    assert result.returncode == 2 and "only apply with --auto-targets" in result.stderr
    assert not (tmp_path / "o").exists()


def test_run_auto_targets_on_a_robot_asks_for_a_correspondence(demo_clip, tmp_path):
    from conftest import SHARED

    robot = SHARED / "data" / "robot-expressive" / "RobotExpressive.glb"
    if not robot.is_file():
        pytest.skip("shared/ (the robot test rig) is absent")
    out = tmp_path / "robot"
    result = _cli("run", demo_clip, "--end", "24", "--rig", robot, "--auto-targets", "--no-preview",
                  "-o", out)
    _assert_clean_failure(result, out, "correspondence")


def test_retarget_onto_the_demos_own_character_turns_its_eyes(demo_out, tmp_path, capsys):
    """The demo's animation.glb carries gaze targets no key drives: retarget lets them through
    without --allow-extra, turns them by the irises with --track, and says so without it."""
    from keyshape.cli import main
    from keyshape.targets import GAZE_NAMES

    weights = load_weights_csv(demo_out / "weights.csv")
    rig = str(demo_out / "animation.glb")
    out = tmp_path / "again.glb"
    assert main(["retarget", str(demo_out / "weights.csv"), "--rig", rig, "--track", str(demo_out / "track.npz"),
                 "-o", str(out)]) == 0
    again, first = read_glb_animation(out), read_glb_animation(demo_out / "animation.glb")
    gaze = [again.names.index(n) for n in GAZE_NAMES]
    np.testing.assert_allclose(again.weights[:, gaze], first.weights[:, [first.names.index(n) for n in GAZE_NAMES]],
                               atol=1e-5)  # the same eyes as `demo` wrote
    np.testing.assert_allclose(again.weights[:, :weights.n_channels], np.nan_to_num(weights.values), atol=1e-6)
    np.testing.assert_allclose(again.rotations, first.rotations, atol=1e-5)  # the head turns as in `demo` too
    capsys.readouterr()
    still = tmp_path / "still.glb"
    assert main(["retarget", str(demo_out / "weights.csv"), "--rig", rig, "-o", str(still)]) == 0
    assert "gaze targets no key drives stay at rest" in capsys.readouterr().out
    assert np.abs(read_glb_animation(still).weights[:, gaze]).max() == 0
