"""Issue 17: the defects a hostile new user found, one test per row, on real video.

Every failing command goes through :func:`fails`, which checks the exit code, that the error is one
line (no traceback, no "unexpected error" line), that no output was written and that every input
file the command names (and every file in a folder it names) is byte-identical afterwards.
The track, keys and weights readers are fuzzed with hypothesis at the end.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from keyshape.cli import main

from conftest import _digests, read_frames, write_video

# -- the helper every failing call goes through ---------------------------------------------------


def fails(capfd, argv, code: int = 1, says: str | None = None, *, output=None) -> str:
    """Run ``keyshape argv``: exit ``code``, one error line (matching ``says``), no ``output``,
    inputs byte-identical. Returns the error line."""
    argv = [str(a) for a in argv]
    before = _digests(argv)
    capfd.readouterr()
    try:
        got = main(argv)
    except SystemExit as exc:  # argparse's own usage errors
        got = exc.code
    err = capfd.readouterr().err
    assert got == code, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("keyshape: warning:")]
    if code == 1:
        assert len(lines) == 1 and lines[0].startswith("keyshape: error: "), err
        assert "--debug for details" not in lines[0], f"an unexpected exception, not a checked input: {err}"
    else:  # argparse style: the usage, then one error line
        assert re.match(rf"keyshape {argv[0]}: error: ", lines[-1]), err
    if says is not None:
        assert re.search(says, lines[-1]), lines[-1]
    if output is not None:
        assert not Path(output).exists(), f"{output} was written by a failing call"
    assert _digests(argv) == before, "a failing call changed an input file"
    return lines[-1]


def ok(argv) -> None:
    assert main([str(a) for a in argv]) == 0


# -- shared real material (tracked once) ------------------------------------------------------------


@pytest.fixture(scope="session")
def hostile(tmp_path_factory, demo_clip) -> dict[str, Path]:
    """The demo clip tracked from frame 24 to 60 (36 frames), its keys (3 per region), weights,
    and a `keyshape run` folder made from that track."""
    from keyshape.app import RunOptions, run_take
    from keyshape.io import load_track

    root = tmp_path_factory.mktemp("hostile")
    track, keys, weights = root / "take.npz", root / "keys.json", root / "weights.csv"
    ok(["track", demo_clip, "--start", 24, "--end", 60, "-o", track, "-q"])
    ok(["keys", track, "-o", keys, "--count", 3, "-q"])
    ok(["solve", track, keys, "-o", weights, "-q"])
    run = root / "run"
    run_take(demo_clip, run, RunOptions(n_keys=3, preview=False), progress=False, track=load_track(track))
    return {"track": track, "keys": keys, "weights": weights, "run": run, "video": demo_clip}


def _copy(src: Path, dst: Path) -> Path:
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        shutil.copy(src, dst)
    return dst


def _save_track(path: Path, **arrays) -> Path:
    np.savez(path, **arrays)
    return path


def _track_arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def _csv_rows(path: Path) -> list[list[str]]:
    return [line.split(",") for line in path.read_text().splitlines()]


def _write_rows(path: Path, rows) -> Path:
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")
    return path


# -- the rows ----------------------------------------------------------------------------------------


def test_row01_output_equal_to_input(hostile, tmp_path, capfd):
    clip = _copy(hostile["video"], tmp_path / "a.mp4")
    fails(capfd, ["track", clip, "-o", clip], 2, r"would overwrite the input VIDEO")
    track = _copy(hostile["track"], tmp_path / "t.npz")
    fails(capfd, ["keys", track, "-o", track], 2, r"would overwrite the input TRACKS")
    rig = _copy(hostile["run"] / "animation.glb", tmp_path / "rig.glb")
    weights = _copy(hostile["run"] / "weights.csv", tmp_path / "w.csv")
    fails(capfd, ["retarget", weights, "--rig", rig, "-o", rig], 2, r"would overwrite the input --rig")
    link = tmp_path / "same.glb"  # the same file by another name
    os.link(rig, link)
    fails(capfd, ["retarget", weights, "--rig", rig, "-o", tmp_path / "x.glb", "-o", link], 2, "would overwrite")
    fails(capfd, ["preview", hostile["run"], "-o", hostile["run"] / "track.npz"], 2, "would overwrite the input")


def test_row02_start_is_recorded_and_used(hostile, tmp_path):
    from keyshape.capture.video import iter_frames, probe
    from keyshape.io import load_track, load_weights_csv
    from keyshape.render.draw import resize_to_height
    from keyshape.render.preview import _source_frames

    track = load_track(hostile["track"])
    assert track.frame_index.tolist() == list(range(24, 60))
    rate = probe(hostile["video"]).fps
    assert track.time[0] == pytest.approx(24 / rate, abs=1e-3)
    weights = load_weights_csv(hostile["weights"])
    assert weights.frame_index[0] == 24 and weights.time[0] == pytest.approx(track.time[0], abs=1e-5)
    first = next(_source_frames(hostile["video"], track, 120))  # the preview's first picture
    frame24 = next(rgb for i, (_, rgb) in enumerate(iter_frames(hostile["video"], end=25)) if i == 24)
    frame0 = next(rgb for _, rgb in iter_frames(hostile["video"], end=1))
    assert np.array_equal(first, resize_to_height(frame24, 120))
    assert not np.array_equal(first, resize_to_height(frame0, 120))
    from keyshape.viewer.server import load_take

    page = load_take(hostile["run"]).as_json()  # the viewer seeks the video to these times
    assert page["video_times"][0] == pytest.approx(track.time[0], abs=1e-6) and len(page["video_times"]) == 36
    arrays = _track_arrays(hostile["track"])  # a track file from before frame_index and time still loads
    old = load_track(_save_track(tmp_path / "old.npz", points=arrays["points"], fps=arrays["fps"]))
    assert old.frame_index.tolist() == list(range(36)) and old.time[1] == pytest.approx(1 / float(arrays["fps"]))


def _write_vfr(path: Path, frames: np.ndarray, ms: list[int]) -> Path:
    """An H.264 MP4 whose frames are presented at ``ms`` milliseconds (variable frame rate)."""
    import av

    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=40)
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        stream.time_base = stream.codec_context.time_base = Fraction(1, 1000)
        for image, t in zip(frames, ms):
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts, frame.time_base = t, Fraction(1, 1000)
            out.mux(stream.encode(frame))
        out.mux(stream.encode())
    return path


def test_row03_variable_frame_rate_timing_is_kept(hostile, tmp_path):
    from keyshape.io import load_track, load_weights_csv
    from keyshape.io.gltf import read_glb_animation

    ms = [100 * i for i in range(24)] + [2400 + 25 * i for i in range(12)]  # 100 ms, then 25 ms
    clip = _write_vfr(tmp_path / "phone.mp4", read_frames(hostile["video"], 36), ms)
    track, keys, weights = tmp_path / "v.npz", tmp_path / "vk.json", tmp_path / "vw.csv"
    ok(["track", clip, "-o", track, "-q"])
    ok(["keys", track, "-o", keys, "--count", 2, "-q"])
    ok(["solve", track, keys, "-o", weights, "-q"])
    assert load_track(track).time[24] == pytest.approx(2.4)
    solved = load_weights_csv(weights)
    assert solved.time[24] == pytest.approx(2.4) and solved.time[25] == pytest.approx(2.425)
    from keyshape.io import export
    from keyshape.io.gltf import read_rig

    rig = read_rig(hostile["run"] / "animation.glb")
    anim = solved.with_values(np.zeros((solved.n_frames, rig.n_targets)), rig.names)
    export(anim, tmp_path / "a.glb", rig=rig)
    assert read_glb_animation(tmp_path / "a.glb").times[24] == pytest.approx(2.4, abs=1e-5)
    pxr = pytest.importorskip("pxr")
    export(anim, tmp_path / "a.usda", rig=rig)
    stage = pxr.Usd.Stage.Open(str(tmp_path / "a.usda"))
    samples = next(p for p in stage.Traverse() if p.GetTypeName() == "SkelAnimation").GetAttribute(
        "blendShapeWeights").GetTimeSamples()
    assert samples[24] / stage.GetTimeCodesPerSecond() == pytest.approx(2.4, abs=1e-5)


def test_row04_batch_resume_follows_video_and_options(hostile, tmp_path):
    takes, out = tmp_path / "takes", tmp_path / "out"
    takes.mkdir()
    frames = read_frames(hostile["video"], 160)
    write_video(takes / "take.mp4", frames[:30], fps=24)

    def status(count, *extra) -> str:
        assert main(["batch", str(takes), "-o", str(out), "--sequential", "--no-preview", "-q", "--count", count,
                     *extra]) == 0
        return (out / "summary.csv").read_text().splitlines()[1].split(",")[5]

    assert status("2") == "ok"
    assert status("2") == "skipped"
    assert status("3") == "ok"  # an option changed
    assert json.loads((out / "take" / "batch.json").read_text())["options"]["n_keys"] == 3
    assert status("3") == "skipped"
    write_video(takes / "take.mp4", frames[120:150], fps=24)  # the video replaced
    assert status("3") == "ok"
    assert status("3", "--force") == "ok"


def test_row05_sculpt_is_atomic_and_keeps_a_kit(hostile, tmp_path, capfd):
    run = hostile["run"]
    tiny = write_video(tmp_path / "tiny.mp4", read_frames(hostile["video"], 3), fps=24)
    kit = tmp_path / "kit"
    fails(capfd, ["sculpt", run / "keys.json", "--rig", run / "animation.glb", "--track", run / "track.npz",
                  "--video", tiny, "-o", kit], 1, "has no frame")
    assert not (kit / "sculpt.glb").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    good = tmp_path / "good"
    ok(["sculpt", run / "keys.json", "--rig", run / "animation.glb", "-o", good, "-q"])
    (good / "sculpt.glb").write_bytes((good / "sculpt.glb").read_bytes() + b"  ")  # the artist's work
    fails(capfd, ["sculpt", run / "keys.json", "--rig", run / "animation.glb", "-o", good], 1,
          r"already holds a sculpt kit \(sculpt.glb, keys.png, README.md\).*--force")
    ok(["sculpt", run / "keys.json", "--rig", run / "animation.glb", "-o", good, "-q", "--force"])


def test_row06_truncated_video_is_said(hostile, tmp_path, capfd):
    half = tmp_path / "half.mp4"
    data = hostile["video"].read_bytes()
    half.write_bytes(data[: len(data) // 2])
    capfd.readouterr()
    assert main(["track", str(half), "--start", "210", "-o", str(tmp_path / "h.npz"), "-q"]) == 0
    err = capfd.readouterr().err
    assert re.search(r"keyshape: warning: .*half.mp4: only 228 frames could be decoded but its container "
                     r"declares 472", err), err


def test_row07_fps_is_validated(hostile, tmp_path, capfd):
    out = tmp_path / "t.npz"
    for fps in ("-5", "inf", "0", "nan"):
        fails(capfd, ["track", hostile["video"], "--fps", fps, "-o", out], 2, "--fps", output=out)
    arrays = _track_arrays(hostile["track"])
    bad = _save_track(tmp_path / "bad.npz", **{**arrays, "fps": np.float64(-5)})
    fails(capfd, ["keys", bad, "-o", tmp_path / "k.json"], 1, r"fps must be a positive number; got -5",
          output=tmp_path / "k.json")


def _keys_variant(hostile, tmp_path, name, change) -> Path:
    data = json.loads(hostile["keys"].read_text())
    change(data)
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(data))
    return path


def test_row08_keys_json_is_validated(hostile, tmp_path, capfd):
    def first_key(d):
        return d["regions"]["upper"]["keys"][0]

    name = first_key(json.loads(hostile["keys"].read_text()))["name"]

    def set_index(value):
        return lambda d: d["regions"]["upper"]["indices"].__setitem__(0, value)

    cases = {
        "minus_one": (set_index(-1),
                      r"regions.upper.indices: landmark indices must be whole numbers in 0..477; got -1"),
        "too_big": (set_index(999), r"regions.upper.indices: .*got 999"),
        "fraction": (set_index(7.5), r"regions.upper.indices: .*got 7.5"),
        "nan_shape": (lambda d: d["shapes"][first_key(d)["name"]][0].__setitem__(0, float("nan")),
                      rf"shapes.{name}: holds nan"),
        "duplicate": (lambda d: d["regions"]["lower"]["keys"][0].__setitem__("name", first_key(d)["name"]),
                      rf"regions.lower.keys\[0\].name: '{name}' names two keys"),
        "mirror_of_nobody": (lambda d: first_key(d).__setitem__("mirror_of", "nobody"),
                             r"mirror_of must name another key"),
    }
    out = tmp_path / "w.csv"
    for name, (change, message) in cases.items():
        bad = _keys_variant(hostile, tmp_path, name, change)
        fails(capfd, ["solve", hostile["track"], bad, "-o", out], 1, message, output=out)
    mirrored = _keys_variant(hostile, tmp_path, "mirror", lambda d: d["regions"]["upper"]["keys"][1].__setitem__(
        "mirror_of", first_key(d)["name"]))  # the key engineer's optional field is accepted
    ok(["solve", hostile["track"], mirrored, "-o", out, "-q"])


def test_row09_weights_csv_is_validated(hostile, tmp_path, capfd):
    run = hostile["run"]
    rows = _csv_rows(run / "weights.csv")
    out, first = tmp_path / "a.glb", rows[0][2]

    def variant(name, edit) -> Path:
        changed = [list(r) for r in rows]
        edit(changed)
        return _write_rows(tmp_path / f"{name}.csv", changed)

    cases = {
        "negative": (lambda r: r[3].__setitem__(2, "-0.5"), rf"line 4, {first}: -0.5 is outside 0..5"),
        "huge": (lambda r: r[3].__setitem__(2, "7.5"), rf"line 4, {first}: 7.5 is outside 0..5"),
        "nan": (lambda r: r[3].__setitem__(2, "nan"), rf"line 4, {first}: 'nan' is not a finite number"),
        "swapped": (lambda r: r.__setitem__(slice(3, 5), [r[4], r[3]]), r"line 5, frame: .* does not follow"),
    }
    for name, (edit, message) in cases.items():
        fails(capfd, ["retarget", variant(name, edit), "--rig", run / "animation.glb", "-o", out], 1, message,
              output=out)


def test_row10_rig_and_output_folder_checked_before_tracking(hostile, tmp_path, capfd, monkeypatch):
    import keyshape.capture

    def no_tracking(*args, **kwargs):
        raise AssertionError("tracking started")

    monkeypatch.setattr(keyshape.capture, "track_video", no_tracking)
    monkeypatch.setattr(keyshape.capture, "track_to_file", no_tracking)
    junk = tmp_path / "random.glb"
    junk.write_bytes(np.random.default_rng(0).bytes(4096))
    fails(capfd, ["run", hostile["video"], "--rig", junk, "-o", tmp_path / "out"], 1, "random.glb",
          output=tmp_path / "out")
    fails(capfd, ["run", hostile["video"], "-o", "/proc/keyshape-hostile/out"], 1, "cannot write into /proc")
    fails(capfd, ["track", hostile["video"], "-o", "/proc/keyshape-hostile.npz"], 1, "cannot write into /proc")


def test_row11_sigterm_leaves_no_half_written_data(hostile, tmp_path):
    out = tmp_path / "t.npz"
    process = subprocess.Popen([sys.executable, "-m", "keyshape", "track", str(hostile["video"]), "-o", str(out),
                                "-q"], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    # a spool of tracked frames, of the whole take or of a parallel segment: tracking is under way
    # (the take's own spool appears only when the segments are joined, near the end)
    while not list(tmp_path.glob("keyshape-track-*/**/points.f32")) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert list(tmp_path.glob("keyshape-track-*")), "tracking never started"
    time.sleep(0.5)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 143 and err.strip().endswith("keyshape: terminated"), err
    assert "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # no spool, no temporary, no half track


def test_row12_nan_and_inf_tracks_one_rule(hostile, tmp_path, capfd):
    from keyshape.containers import Track

    arrays = _track_arrays(hostile["track"])
    nan = _save_track(tmp_path / "nan.npz", points=np.full_like(arrays["points"], np.nan), fps=arrays["fps"])
    first = fails(capfd, ["solve", nan, hostile["keys"], "-o", tmp_path / "w.csv"], 1, "no frame has a face")
    second = fails(capfd, ["keys", nan, "-o", tmp_path / "k.json"], 1, "no frame has a face")
    assert first == second
    points = arrays["points"].copy()
    points[5:9] = np.inf
    inf = _save_track(tmp_path / "inf.npz", points=points, fps=arrays["fps"])
    for verb in (["keys", inf, "-o", tmp_path / "k.json"], ["solve", inf, hostile["keys"], "-o", tmp_path / "w.csv"],
                 ["arkit", inf, "-o", tmp_path / "a.csv"]):
        fails(capfd, verb, 1, r"points: frame 5 holds inf")
    assert Track(points, 30.0).valid.sum() == len(points) - 4  # the API: an inf frame is a missing face


def test_row13_errors_are_one_line(hostile, tmp_path, capfd):
    arrays = _track_arrays(hostile["track"])
    big = _save_track(tmp_path / "big.npz", **{**arrays, "points": arrays["points"].astype(np.float64) * 1e150})
    fails(capfd, ["keys", big, "-o", tmp_path / "k.json"], 1, r"points: frame 0 holds .*e\+15\d, beyond")
    folder = tmp_path / "existing"
    folder.mkdir()
    fails(capfd, ["keys", hostile["track"], "-o", folder], 2, "is an existing folder")
    header = _write_rows(tmp_path / "header.csv", _csv_rows(hostile["run"] / "weights.csv")[:1])
    fails(capfd, ["retarget", header, "--rig", hostile["run"] / "animation.glb", "-o", tmp_path / "a.glb"], 1,
          "has a header but no rows")
    fewer = _write_rows(tmp_path / "fewer.csv", [r[:-1] for r in _csv_rows(hostile["run"] / "weights.csv")])
    fails(capfd, ["retarget", fewer, "--rig", hostile["run"] / "animation.glb", "-o", tmp_path / "a.glb"], 1,
          "--allow-extra")


def test_row14_messages_say_what_is_wrong(hostile, tmp_path, capfd):
    out = tmp_path / "t.npz"
    fails(capfd, ["track", hostile["video"], "--start", 500, "-o", out], 1,
          r"start frame 500 is past its end \(it has 472 frames")
    fails(capfd, ["track", hostile["video"], "--face", 5, "--end", 3, "-o", out], 1,
          r"no 6th face to follow \(face=5\): at most 1 face was seen")
    fails(capfd, ["keys", hostile["track"], "--regions", "uper-lower", "-o", tmp_path / "k.json"], 2,
          r"'uper-lower' is neither a scheme \(upper-lower, whole, eyes\)")


def test_row15_usage_errors_exit_2(hostile, tmp_path, capfd):
    out = tmp_path / "t.npz"
    fails(capfd, ["track", hostile["video"], "--start", -5, "-o", out], 2, "--start: must be >= 0")
    fails(capfd, ["track", hostile["video"], "--start", 40, "--end", 10, "-o", out], 2, "--end must be after")
    fails(capfd, ["keys", hostile["track"], "--neutral", 999, "-o", tmp_path / "k.json"], 2,
          r"--neutral must be a frame in 0..35; got 999")
    fails(capfd, ["run", hostile["video"], "--end", 30, "--neutral", 999, "-o", tmp_path / "o"], 2,
          r"--neutral must be a frame in 0..29")
    fails(capfd, ["preview", hostile["run"], "--height", 0, "-o", tmp_path / "p.mp4"], 2,
          r"--height: must be between 64 and 4096")


def test_row16_limits_are_in_help(capsys):
    for argv, limit in ((["keys", "--help"], "[1..64]"), (["report-k", "--help"], "[1..200]")):
        with pytest.raises(SystemExit):
            main(argv)
        assert limit in capsys.readouterr().out


def test_row17_reused_output_folder_keeps_no_stale_file(hostile, tmp_path):
    old = _copy(hostile["run"], tmp_path / "old demo")
    (old / "preview.mp4").write_bytes(b"the old 472-frame preview")
    info = json.loads((old / "take.json").read_text())  # the earlier run wrote it: its record says so
    (old / "take.json").write_text(json.dumps({**info, "written": [*info["written"], "preview.mp4"]}))
    (old / "notes.txt").write_text("mine")  # not keyshape's: left alone
    ok(["run", hostile["video"], "--end", 24, "--count", 2, "--no-preview", "-o", old, "-q"])
    assert not (old / "preview.mp4").exists()
    assert (old / "notes.txt").read_text() == "mine"
    assert json.loads((old / "take.json").read_text())["n_frames"] == 24


def test_row18_no_progress_bars_in_logs(hostile, capfd):
    from keyshape.capture import track_video

    capfd.readouterr()
    track_video(hostile["video"], end=4, progress=True)  # stderr is captured: not a terminal
    err = capfd.readouterr().err
    assert "track WolfgangLanger" not in err and "frame/s" not in err, err


def test_row19_broken_inputs_are_said(hostile, tmp_path, capfd):
    from keyshape.exceptions import InputError
    from keyshape.viewer.server import load_take

    gone = _copy(hostile["run"], tmp_path / "gone")
    info = json.loads((gone / "take.json").read_text())
    (gone / "take.json").write_text(json.dumps({**info, "video": str(tmp_path / "moved.mp4")}))
    capfd.readouterr()
    assert main(["report", str(gone), "--no-preview", "-q"]) == 0
    assert re.search(r"keyshape: warning: .*moved.mp4' is not found", capfd.readouterr().err)
    broken = _copy(hostile["run"], tmp_path / "broken")
    (broken / "animation.glb").write_bytes(np.random.default_rng(1).bytes(2000))
    fails(capfd, ["report", broken, "--no-preview"], 1, r"animation.glb: not a glTF")
    with pytest.raises(InputError, match=r"animation.glb: not a glTF"):
        load_take(broken)  # what `keyshape view` serves


def test_row20_hints_are_shell_quoted(hostile, tmp_path, capsys):
    clip = _copy(hostile["video"], tmp_path / "my clip é.mp4")
    out = tmp_path / "uni dir" / "out"
    ok(["run", clip, "--end", 12, "--count", 2, "--no-preview", "-o", out])
    assert f"`keyshape view '{out}'`" in capsys.readouterr().out


# -- fuzzing the readers -------------------------------------------------------------------------------

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture],
                derandomize=True)
BAD_NUMBERS = st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e7, -3e9, 1e300])


@st.composite
def track_corruption(draw):
    kind = draw(st.sampled_from(["truncate", "value", "shape", "fps", "frame_index", "time", "drop", "dtype"]))
    return kind, draw(st.integers(0, 10**6)), draw(BAD_NUMBERS)


def _corrupt_track(source: Path, target: Path, kind: str, n: int, bad: float) -> None:
    if kind == "truncate":
        data = source.read_bytes()
        target.write_bytes(data[: n % len(data)])
        return
    arrays = _track_arrays(source)
    points = arrays["points"]
    if kind == "value":
        flat = points.reshape(-1).astype(np.float64)  # a hostile file may hold any float
        valid = np.flatnonzero(np.isfinite(flat))
        flat[valid[n % len(valid)]] = bad if not np.isnan(bad) else np.inf
        arrays["points"] = flat.reshape(points.shape)
        if np.isnan(bad):
            arrays["points"][:] = np.nan  # all NaN: no face at all
    elif kind == "shape":
        arrays["points"] = points.reshape(points.shape[0], -1)[:, : 1 + n % 7]
    elif kind == "fps":
        arrays["fps"] = np.array([bad if bad < 0 or not np.isfinite(bad) else -bad, 30.0][: 1 + n % 2])
    elif kind == "frame_index":
        index = np.arange(len(points)) + 24
        index[1 + n % (len(index) - 1)] = index[0]
        arrays["frame_index"] = index
    elif kind == "time":
        times = np.arange(len(points)) / 24.0
        times[1 + n % (len(times) - 2)] = bad  # inside the take: never still increasing
        arrays["time"] = times
    elif kind == "drop":
        arrays.pop(["points", "fps"][n % 2])
    elif kind == "dtype":
        arrays["points"] = np.array(["x"] * points.shape[0])
    np.savez(target, **arrays)


@FUZZ
@given(track_corruption())
def test_fuzz_track_reader(hostile, tmp_path, capfd, corruption):
    bad, out = tmp_path / "fuzz.npz", tmp_path / "fuzz-keys.json"
    _corrupt_track(hostile["track"], bad, *corruption)
    fails(capfd, ["keys", bad, "-o", out, "--count", 2], 1, re.escape(str(bad)), output=out)


KEYS_FIELDS = ["format", "n_landmarks", "n_dims", "neutral", "neutral.frame", "shapes", "shapes.neutral",
               "regions", "index", "key.name", "key.frame", "key.take", "key.mirror_of", "key.shape", "stable",
               "text"]
JUNK = st.one_of(st.none(), st.booleans(), st.integers(-10**6, -1), st.integers(10**6, 10**9),
                 st.floats(allow_nan=True, allow_infinity=True).filter(lambda v: not float(v).is_integer()),
                 st.text(max_size=5), st.lists(st.integers(), max_size=2), st.dictionaries(st.text(max_size=3),
                                                                                          st.integers(), max_size=2))


def _not_a_frame(junk):
    """``junk``, unless it is a valid frame number (a large one cannot be told from a real one)."""
    return -1 if isinstance(junk, int) and not isinstance(junk, bool) and junk >= 0 else junk


def _corrupt_keys(data: dict, field: str, n: int, junk):
    region = list(data["regions"].values())[n % len(data["regions"])]
    key = region["keys"][n % len(region["keys"])]
    if field == "format":
        data["format"] = junk if junk != "keyshape-keys" else None
    elif field in ("n_landmarks", "n_dims", "neutral", "shapes", "regions", "stable"):
        data[field] = junk if field != "stable" else [junk]
    elif field == "neutral.frame":
        data["neutral"]["frame"] = _not_a_frame(junk)
    elif field == "shapes.neutral":
        data["shapes"]["neutral"][n % 478] = junk
    elif field == "index":
        region["indices"][n % len(region["indices"])] = junk
    elif field == "key.name":
        key["name"] = f"{junk}?" if isinstance(junk, str) else junk  # no shape by that name, or no string
    elif field == "key.frame":
        key["frame"] = _not_a_frame(junk)
    elif field == "key.take":
        key["take"] = junk if not isinstance(junk, str) else 5
    elif field == "key.mirror_of":
        key["mirror_of"] = junk if junk not in (None, "") and not isinstance(junk, str) else "nobody"
    elif field == "key.shape":
        data["shapes"][key["name"]][n % len(region["indices"])] = junk
    return data


@FUZZ
@given(st.sampled_from(KEYS_FIELDS), st.integers(0, 10**6), JUNK)
def test_fuzz_keys_reader(hostile, tmp_path, capfd, field, n, junk):
    bad, out = tmp_path / "fuzz.json", tmp_path / "fuzz.csv"
    text = hostile["keys"].read_text()
    if field == "text":
        bad.write_text(text[: n % (len(text) - 2)])
    else:
        bad.write_text(json.dumps(_corrupt_keys(json.loads(text), field, n, junk)))
    fails(capfd, ["solve", hostile["track"], bad, "-o", out], 1, re.escape(str(bad)), output=out)


CELLS = st.sampled_from(["-0.5", "7.5", "nan", "inf", "-inf", "abc", "1e400", "0x1p3", " - "])


@FUZZ
@given(st.sampled_from(["cell", "frame", "time", "swap", "header", "ragged", "empty"]), st.integers(0, 10**6), CELLS)
def test_fuzz_weights_reader(hostile, tmp_path, capfd, kind, n, cell):
    rows = _csv_rows(hostile["run"] / "weights.csv")
    body = 2 + n % (len(rows) - 3)  # a row with rows before and after it
    if kind == "cell":
        rows[body][2 + n % (len(rows[0]) - 2)] = cell
    elif kind == "frame":
        rows[body][0] = [cell, "1.5", "-1", rows[body - 1][0] if body > 1 else "x"][n % 4]
    elif kind == "time":
        rows[body][1] = [cell, "", rows[body - 1][1] if body > 1 else "x"][n % 3]
    elif kind == "swap":
        rows[body], rows[body + 1] = rows[body + 1], rows[body]
    elif kind == "header":
        column = n % len(rows[0])
        rows[0][column] = "Frame" if column < 2 else "" if column == 2 else rows[0][2]  # a name twice
    elif kind == "ragged":
        rows[body] = rows[body][:-1]
    elif kind == "empty":
        rows = rows[:1]
    bad, out = _write_rows(tmp_path / "fuzz.csv", rows), tmp_path / "fuzz.glb"
    fails(capfd, ["retarget", bad, "--rig", hostile["run"] / "animation.glb", "-o", out], 1, re.escape(str(bad)),
          output=out)
