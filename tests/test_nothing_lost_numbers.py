"""Issue 34, "Nothing lost, round two": the numbers that reach a file (items 6, 7, 8 and the Low
items on the readers), each driving the real command in a child process.

A failing command must exit with one line naming what is wrong and write no output.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest


def keyshape(*argv, cwd=None, timeout=600) -> subprocess.CompletedProcess:
    """``keyshape argv`` in a child process (the child inherits PYTHONPATH)."""
    return subprocess.run([sys.executable, "-m", "keyshape", *map(str, argv)], check=False, capture_output=True,
                          text=True, cwd=cwd, timeout=timeout)


def one_line_error(done: subprocess.CompletedProcess, code: int = 1, says: str = "") -> str:
    """The error line of a failed call: exit ``code``, no traceback or raw warning, one
    ``keyshape...: error:`` line (after argparse's usage for code 2) containing ``says``."""
    err = done.stderr
    assert done.returncode == code, err
    assert "Traceback" not in err and "Warning:" not in err, err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("keyshape: warning:")]
    if code == 2:
        lines = [line for line in lines if not line.startswith("usage:") and not line.startswith(" ")]
    assert len(lines) == 1 and ": error: " in lines[0], err
    assert says in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def made(tmp_path_factory, demo_clip) -> dict[str, Path]:
    """The demo clip's first 60 frames tracked, its keys and weights, made once for the module."""
    root = tmp_path_factory.mktemp("numbers")
    track, keys, weights = root / "t.npz", root / "k.json", root / "w.csv"
    for argv in (["track", demo_clip, "--end", 60, "-o", track, "-q"],
                 ["keys", track, "-o", keys, "-q"],
                 ["solve", track, keys, "-o", weights, "-q"]):
        done = keyshape(*argv)
        assert done.returncode == 0, done.stderr
    return {"track": track, "keys": keys, "weights": weights}


# -- Medium 7: a smoothed solve converges or fails in one line ------------------------------------------


def test_item07_solve_at_extreme_smoothing_fails_in_one_line_and_writes_nothing(made, tmp_path):
    out = tmp_path / "w.csv"
    done = keyshape("solve", made["track"], made["keys"], "--smooth", "1e9", "-o", out)
    line = one_line_error(done, 1, "the smoothed solve did not converge at smoothness 1e+09")
    assert "--smooth" in line and not out.exists()
    # a strong but solvable smoothing still writes its (smoother) weights
    done = keyshape("solve", made["track"], made["keys"], "--smooth", "1e3", "-o", out)
    assert done.returncode == 0 and "Warning" not in done.stderr, done.stderr
    smooth = np.loadtxt(out, delimiter=",", skiprows=1)[:, 2:]
    plain = np.loadtxt(made["weights"], delimiter=",", skiprows=1)[:, 2:]
    assert np.abs(np.diff(smooth, 2, axis=0)).sum() < 0.5 * np.abs(np.diff(plain, 2, axis=0)).sum()


# -- Medium 6: no number outside 0..MAX_WEIGHT reaches an animation file --------------------------------


def _tiny_rig(folder: Path) -> Path:
    """An OBJ folder rig with one target, ``jawOpen``."""
    from keyshape import Rig
    from keyshape.io import save_obj_folder

    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    return save_obj_folder(Rig(vertices, [[0, 1, 2]], np.full((1, 3, 3), 0.01), ("jawOpen",)), folder)


@pytest.mark.parametrize("document", [
    lambda key: {key: {"jawOpen": 1e300}},
    lambda key: {"format": "keyshape-map", "version": 1, "gains": {key: {"jawOpen": 1e300}}},
    lambda key: {"keys": [key], "targets": ["jawOpen"], "matrix": [[1e300]]},
])
def test_item06_a_huge_gain_in_map_json_is_refused_naming_the_file(made, tmp_path, document):
    key = made["weights"].read_text().splitlines()[0].split(",")[2]
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps(document(key)))
    rig = _tiny_rig(tmp_path / "rig")
    outs = [tmp_path / "a.glb", tmp_path / "a.csv"]
    done = keyshape("retarget", made["weights"], "--rig", rig, "--map", mapping, *(f"-o{o}" for o in outs))
    one_line_error(done, 1, f"{mapping}: ")
    assert not any(o.exists() for o in outs)


def test_item06_a_target_weight_beyond_what_keyshape_reads_is_never_written(made, tmp_path):
    """A gain within bounds that still drives a target past 5 (gain 90): every
    output format refuses it in one line naming the output, and writes nothing."""
    from keyshape.io import load_weights_csv

    weights = load_weights_csv(made["weights"])
    key = weights.names[int(np.nanargmax(weights.values.max(axis=0)))]
    assert np.nanmax(weights.values) * 90 > 5
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({key: {"jawOpen": 90}}))
    rig = _tiny_rig(tmp_path / "rig")
    for out, extra in ((tmp_path / "a.glb", ()), (tmp_path / "a.usda", ()), (tmp_path / "a.csv", ()),
                       (tmp_path / "ll.csv", ("--format", "livelink"))):
        done = keyshape("retarget", made["weights"], "--rig", rig, "--map", mapping, *extra, "-o", out)
        if "usd-core" in done.stderr:  # pip install usd-core: not every environment has it
            continue
        one_line_error(done, 1, f"{out}: 'jawOpen' would be written as ")
        assert not out.exists()
    # the same mapping at gain 4 (weights are at most 1) writes what keyshape itself reads back
    mapping.write_text(json.dumps({key: {"jawOpen": 4}}))
    done = keyshape("retarget", made["weights"], "--map", mapping, "-o", tmp_path / "ok.csv")
    assert done.returncode == 0, done.stderr
    back = load_weights_csv(tmp_path / "ok.csv")
    np.testing.assert_allclose(back.values[:, 0], 4 * np.nan_to_num(weights.values[:, weights.names.index(key)]),
                               atol=1e-5)


def test_item06_every_writer_applies_the_readers_rule():
    """The library writers themselves (not only the command) refuse inf, negative and too large
    weights, and the weights reader refuses the same values."""
    import tempfile

    from keyshape import Rig, Weights
    from keyshape.exceptions import InputError
    from keyshape.io import load_weights_csv, save_weights_csv
    from keyshape.io.gltf import write_glb
    from keyshape.io.livelink import write_livelink_csv

    rig = Rig(np.eye(3), [[0, 1, 2]], np.ones((1, 3, 3)), ("jawOpen",))
    folder = Path(tempfile.mkdtemp())
    for bad in (np.inf, -0.5, 5.5):
        anim = Weights(np.array([[0.0], [bad]]), ("jawOpen",), fps=30)
        for write in (lambda p, a: save_weights_csv(a, p.with_suffix(".csv")),
                      lambda p, a: write_glb(p.with_suffix(".glb"), rig, a),
                      lambda p, a: write_livelink_csv(p.with_suffix(".csv"), a)):
            with pytest.raises(InputError, match=r"would be written as .* at frame 1"):
                write(folder / "out", anim)
        assert not list(folder.iterdir())
        (folder / "w.csv").write_text(f"frame,time,jawOpen\r\n0,0.0,0.0\r\n1,0.033,{bad}\r\n")
        with pytest.raises(InputError, match=r"w\.csv: line 3, jawOpen"):
            load_weights_csv(folder / "w.csv")
        (folder / "w.csv").unlink()
    nan = Weights(np.array([[0.0], [np.nan]]), ("jawOpen",), fps=30)  # no estimate: written empty
    assert load_weights_csv(save_weights_csv(nan, folder / "n.csv")).values[1, 0] != 0.0


# -- Medium 8: a track's blendshape scores are checked ---------------------------------------------------


def _with_scores(track: Path, out: Path, change) -> Path:
    """A copy of the track file ``track`` at ``out`` with ``change(scores)`` applied to its
    ``blendshapes (n_frames, 52)``, every other array as it was."""
    with np.load(track) as data:
        arrays = {name: data[name] for name in data.files}
    change(arrays["blendshapes"])
    np.savez(out, **arrays)
    return out


@pytest.mark.parametrize("change, says", [
    (lambda s: s.fill(np.nan), "blendshapes: frame 0 has a face but no scores (NaN)"),
    (lambda s: s.__setitem__((5, 3), 1.5), "blendshapes: frame 5 holds 1.5; scores are in [0, 1]"),
    (lambda s: s.__setitem__((7, 3), np.nan), "blendshapes: frame 7 holds nan among its scores"),
    (lambda s: s.__setitem__((9, 0), -np.inf), "blendshapes: frame 9 holds -inf among its scores"),
])
def test_item08_broken_blendshape_scores_are_refused_by_every_reader(made, tmp_path, change, says):
    broken = _with_scores(made["track"], tmp_path / "t.npz", change)
    for argv, out in ((["keys", broken], tmp_path / "k.json"), (["solve", broken, made["keys"]], tmp_path / "w.csv"),
                      (["arkit", broken], tmp_path / "a.csv")):
        done = keyshape(*argv, "-o", out)
        one_line_error(done, 1, f"{broken}: {says}")
        assert not out.exists()


def test_item08_the_neutral_of_a_track_without_usable_scores_is_the_median_shape_not_frame_0():
    """The library's rule on a Track built in memory (no file check): all-NaN scores give no
    least-activated frame, so the median-shape rule picks the neutral (frame 0 before)."""
    from keyshape import Track
    from keyshape.alignment import choose_neutral_frame
    from keyshape.alignment._neutral import least_activated
    from keyshape.datasets import make_performance

    perf = make_performance(n_frames=40, random_state=3)
    track = perf.track
    scores = np.full((track.n_frames, 2), np.nan)
    unscored = Track(track.points, track.fps, blendshapes=scores, blendshape_names=("jawOpen", "mouthSmileLeft"))
    assert least_activated(unscored) is None
    stable = np.arange(track.n_landmarks)
    assert choose_neutral_frame(unscored, stable=stable) == choose_neutral_frame(track, stable=stable)


# -- Low: the readers' messages, a BOM, versions, frame rates -------------------------------------------


@pytest.mark.parametrize("text, says", [
    ("frame,x0,y0\n0,1,2\n1,abc,3\n", "line 3, x0: 'abc' is not a number"),
    ("frame,x0,y0\n0,1,2\n\n1,3\n", "line 4: has 2 columns; the header has 3"),
    ("frame,time,x0,y0\n0,0,1,2\n1.5,0.1,3,4\n", "line 3, frame: must be a whole number; got '1.5'"),
])
def test_low_landmark_csv_errors_name_the_line(tmp_path, text, says):
    track = tmp_path / "t.csv"
    track.write_text(text)
    done = keyshape("keys", track, "-o", tmp_path / "k.json")
    one_line_error(done, 1, f"{track}: {says}")


def test_low_a_key_file_without_regions_is_blamed_on_regions(made, tmp_path):
    data = json.loads(made["keys"].read_text())
    del data["regions"]
    keys = tmp_path / "k.json"
    keys.write_text(json.dumps(data))
    line = one_line_error(keyshape("solve", made["track"], keys, "-o", tmp_path / "w.csv"), 1,
                          f"{keys}: a key file needs ")
    assert line.endswith("it lacks 'regions'") and "format" not in line


def test_low_sculpt_refusal_names_the_option_not_the_parameter(made, tmp_path, demo_clip):
    kit = tmp_path / "kit"
    kit.mkdir()
    (kit / "README.md").write_text("sculpted")
    rig = _tiny_rig(tmp_path / "rig") / "neutral.obj"
    line = one_line_error(keyshape("sculpt", made["keys"], "--rig", rig, "--track", made["track"], "--video", demo_clip,
                                   "-o", kit), 1,
                          f"{kit}: already holds a sculpt kit")
    assert line.endswith("replace it with --force") and "overwrite=True" not in line
    assert (kit / "README.md").read_text() == "sculpted"


def test_low_csv_and_json_files_with_a_byte_order_mark_are_read(made, tmp_path):
    bom = b"\xef\xbb\xbf"
    weights, keys, track = tmp_path / "w.csv", tmp_path / "k.json", tmp_path / "t.csv"
    weights.write_bytes(bom + made["weights"].read_bytes())
    keys.write_bytes(bom + made["keys"].read_bytes())
    track.write_bytes(bom + b"frame,x0,y0\n0,1,2\n1,3,4\n")
    key = made["weights"].read_text().splitlines()[0].split(",")[2]
    mapping = tmp_path / "map.json"
    mapping.write_bytes(bom + json.dumps({key: {"jawOpen": 1.0}}).encode())
    done = keyshape("retarget", weights, "--map", mapping, "-o", tmp_path / "out.csv")
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "out.csv").read_text().startswith("frame,time,jawOpen")
    done = keyshape("solve", made["track"], keys, "-o", tmp_path / "w2.csv")
    assert done.returncode == 0, done.stderr
    from keyshape.io import load_track

    assert load_track(track).points.tolist() == [[[1.0, 2.0]], [[3.0, 4.0]]]


def test_low_a_track_of_a_newer_format_version_is_refused(made, tmp_path):
    with np.load(made["track"]) as data:
        arrays = {name: data[name] for name in data.files}
    arrays["format_version"] = np.int64(99)
    track = tmp_path / "t.npz"
    np.savez(track, **arrays)
    for argv in (["keys", track, "-o", tmp_path / "k.json"], ["solve", track, made["keys"], "-o", tmp_path / "w.csv"],
                 ["arkit", track, "-o", tmp_path / "a.csv"]):
        one_line_error(keyshape(*argv), 1, f"{track}: format_version: 99 is newer than this keyshape reads (1)")
    data = json.loads(made["keys"].read_text())
    data["version"] = 99
    keys = tmp_path / "k99.json"
    keys.write_text(json.dumps(data))
    one_line_error(keyshape("solve", made["track"], keys, "-o", tmp_path / "w.csv"), 1,
                   f"{keys}: version: 99 is newer than this keyshape reads (1)")
    assert not list(tmp_path.glob("*.csv")) and not (tmp_path / "k.json").exists()


def test_low_a_frame_rate_above_1000_is_refused(demo_clip, tmp_path):
    out = tmp_path / "t.npz"
    one_line_error(keyshape("track", demo_clip, "--fps", 2000, "-o", out), 2,
                   "argument --fps: must be at most 1000 frames a second")
    assert not out.exists()
    track = tmp_path / "fast.csv"
    track.write_text("frame,time,x0,y0\n0,0.0,1,2\n1,0.0001,3,4\n")  # 10,000 frames a second
    one_line_error(keyshape("keys", track, "-o", tmp_path / "k.json"), 1,
                   f"{track}: fps must be at most 1000 frames a second")
