"""Issue 34, "Nothing lost, round two": one test per item, each driving the real command.

Every command runs as a user runs it, ``python -m keyshape ...`` in a child process (real signals
where the item is about signals); a failing one must exit with one line naming the file, write no
output and leave every file of the user's byte-identical.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from conftest import read_frames, write_video


def keyshape(*argv, cwd=None, timeout=600) -> subprocess.CompletedProcess:
    """``keyshape argv`` in a child process (the child inherits PYTHONPATH)."""
    return subprocess.run([sys.executable, "-m", "keyshape", *map(str, argv)], check=False,
                          capture_output=True, text=True, cwd=cwd, timeout=timeout)


def one_line_error(done: subprocess.CompletedProcess, code: int = 1, says: str = "") -> str:
    """The error line of a failed call: exit ``code``, no traceback, one ``keyshape...: error:`` line
    (after argparse's usage for code 2), containing ``says``."""
    err = done.stderr
    assert done.returncode == code, err
    assert "Traceback" not in err and "Warning:" not in err, err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("keyshape: warning:")]
    if code == 2:
        lines = [line for line in lines if not line.startswith("usage:") and not line.startswith(" ")]
    assert len(lines) == 1 and ": error: " in lines[0], err
    assert "--debug for details" not in lines[0], err
    assert says in lines[0], lines[0]
    return lines[0]


def digests(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder``, by relative path."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def made(tmp_path_factory, demo_clip) -> dict[str, Path]:
    """A short take of the demo clip: its track (frames 24..60), keys (2 per region), weights and a
    `keyshape run` folder of it, made once for the module."""
    root = tmp_path_factory.mktemp("lost")
    track, keys, weights, run = root / "t.npz", root / "k.json", root / "w.csv", root / "run"
    for argv in (["track", demo_clip, "--start", 24, "--end", 60, "-o", track, "-q"],
                 ["keys", track, "--count", 2, "-o", keys, "-q"],
                 ["solve", track, keys, "-o", weights, "-q"],
                 ["run", demo_clip, "--end", 24, "--count", 2, "--no-preview", "-o", run, "-q"]):
        done = keyshape(*argv)
        assert done.returncode == 0, done.stderr
    return {"track": track, "keys": keys, "weights": weights, "run": run, "video": demo_clip}


# -- High 1: a batch take folder is a plain name inside OUTDIR ------------------------------------------


@pytest.mark.parametrize("name", ["...mp4", "..mp4", ".hidden.mp4", "summary.csv.mp4"])
def test_item01_batch_refuses_a_take_whose_folder_is_no_plain_name(tmp_path, demo_clip, name):
    project = tmp_path / "project"
    project.mkdir()
    for mine in ("keys.json", "weights.csv", "animation.blend"):
        (project / mine).write_text(f"the user's own {mine}")
    before = digests(project)
    (tmp_path / "src").mkdir()
    take = shutil.copy(demo_clip, tmp_path / "src" / name)
    done = keyshape("batch", take, "-o", project / "out", "--sequential", "-q")
    one_line_error(done, 1, f"{take}: its name gives no take folder")
    assert digests(project) == before and not (project / "out").exists()


# -- High 2: a reused run folder loses only what an earlier run wrote ------------------------------------


def test_item02_run_in_a_reused_folder_removes_only_what_the_earlier_run_wrote(made, tmp_path):
    folder = shutil.copytree(made["run"], tmp_path / "take")
    info = json.loads((folder / "take.json").read_text())
    assert set(info["written"]) == {p.name for p in folder.iterdir()}  # the record of what the run wrote
    look_alikes = ("animation.blend1", "animation.final.fbx", "animation.glb.bak", "map.json",
                   "correspondence.json", "notes.txt")
    for name in look_alikes:
        (folder / name).write_text(f"the user's own {name}")
    (folder / "preview.mp4").write_bytes(b"an earlier run's preview")  # that run's record says so
    (folder / "take.json").write_text(json.dumps({**info, "written": [*info["written"], "preview.mp4"]}))
    mine = {name: (folder / name).read_bytes() for name in look_alikes}
    done = keyshape("run", made["video"], "--end", 12, "--count", 2, "--no-preview", "-o", folder, "-q")
    assert done.returncode == 0, done.stderr
    assert {name: (folder / name).read_bytes() for name in look_alikes} == mine
    assert not (folder / "preview.mp4").exists()  # stale: written by the earlier run, not by this one
    info = json.loads((folder / "take.json").read_text())
    assert info["n_frames"] == 12 and "preview.mp4" not in info["written"]
    assert set(info["written"]) | set(look_alikes) == {p.name for p in folder.iterdir()}


# -- Medium 4: the run's final move is one step ------------------------------------------------------------

SIGNAL_AT_MOVE = """
import os, signal, sys
from pathlib import Path
out = Path(sys.argv[1]).resolve()
replace, moves = os.replace, []
kind = getattr(signal, os.environ.get("KEYSHAPE_TEST_SIGNAL", "SIGTERM"))
def moving(src, dst, **kw):  # a real signal (SIGTERM), sent at the second file moved into OUTDIR
    if Path(dst).resolve().parent == out and Path(src).parent.name.startswith("." + out.name + "."):
        moves.append(dst)
        if len(moves) == 2:
            os.kill(os.getpid(), kind)
    return replace(src, dst, **kw)
os.replace = moving
from keyshape.cli import main
sys.exit(main(sys.argv[2:]))
"""


def test_item04_a_signal_during_the_final_move_leaves_the_old_take_or_the_new_one(made, tmp_path):
    from keyshape.io import load_track, load_weights_csv

    folder = shutil.copytree(made["run"], tmp_path / "take")
    argv = [folder, "run", made["video"], "--end", 12, "--count", 2, "--no-preview", "-o", folder, "-q"]
    done = subprocess.run([sys.executable, "-c", SIGNAL_AT_MOVE, *map(str, argv)], check=False, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 143 and done.stderr.strip().endswith("keyshape: terminated"), done.stderr
    info = json.loads((folder / "take.json").read_text())  # the switch was not cut: the new take, whole
    assert info["n_frames"] == 12
    assert load_track(folder / "track.npz").n_frames == 12 and load_weights_csv(folder / "weights.csv").n_frames == 12
    assert set(info["written"]) == {p.name for p in folder.iterdir()}
    assert [p.name for p in tmp_path.iterdir()] == ["take"]  # no stage left beside it
    assert keyshape("report", folder, "--no-preview", "-q").returncode == 0



def test_item04_a_switch_cut_short_by_sigkill_is_refused_by_report_and_mended_by_the_next_run(made, tmp_path):
    """SIGKILL cannot be held: the folder is then a mix, which the readers name and the next run mends."""
    folder = shutil.copytree(made["run"], tmp_path / "take")
    info = json.loads((folder / "take.json").read_text())
    (folder / "preview.mp4").write_bytes(b"an earlier run's preview")  # the old take's, stale for the new one
    (folder / "take.json").write_text(json.dumps({**info, "written": [*info["written"], "preview.mp4"]}))
    (folder / "notes.txt").write_text("the user's own")
    argv = [folder, "run", made["video"], "--end", 12, "--count", 2, "--no-preview", "-o", folder, "-q"]
    done = subprocess.run([sys.executable, "-c", SIGNAL_AT_MOVE, *map(str, argv)], check=False, capture_output=True,
                          text=True, timeout=600, env={**os.environ, "KEYSHAPE_TEST_SIGNAL": "SIGKILL"})
    assert done.returncode == -signal.SIGKILL, done.stderr
    assert not (folder / "take.json").exists()  # cut: two files of the new take in, the rest old
    line = one_line_error(keyshape("report", folder, "--no-preview", "-q"), 1, f"{folder}: the last output")
    assert "cut short" in line and ".keyshape-switch" in line
    assert len(list(tmp_path.glob(".take.*.keyshape-stage"))) == 2  # the killed run's claim and its stage
    done = keyshape("run", made["video"], "--end", 12, "--count", 2, "--no-preview", "-o", folder, "-q")
    assert done.returncode == 0, done.stderr
    info = json.loads((folder / "take.json").read_text())
    assert info["n_frames"] == 12 and set(info["written"]) | {"notes.txt"} == {p.name for p in folder.iterdir()}
    assert (folder / "notes.txt").read_text() == "the user's own"
    assert [p.name for p in tmp_path.iterdir()] == ["take"]  # the dead stage went too
    assert keyshape("report", folder, "--no-preview", "-q").returncode == 0


# -- High 3: a live take survives a second Ctrl-C -------------------------------------------------------


@pytest.mark.parametrize("kind", [signal.SIGINT, signal.SIGTERM])
def test_item03_a_second_signal_while_the_recording_is_written_loses_nothing(made, tmp_path, kind):
    from keyshape.io import load_track

    record = tmp_path / "rec"
    proc = subprocess.Popen([sys.executable, "-m", "keyshape", "live", str(made["video"]), "--keys",
                             str(made["keys"]), "--record", str(record), "--vmc", "127.0.0.1:9"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    frames = 478 * 3 * 4 * 20  # the bytes of 20 frames' landmarks
    while time.monotonic() < deadline and not any(p.stat().st_size > frames for p in record.glob(".live-*/points.f32")):
        time.sleep(0.05)  # 20 frames spooled
    proc.send_signal(kind)
    while proc.poll() is None and time.monotonic() < deadline:  # and again, the double Ctrl-C, until it ends
        time.sleep(0.05)
        proc.send_signal(kind)
    out, err = proc.communicate(timeout=60)
    assert {p.name for p in record.iterdir()} == {"track.npz", "keys.json", "weights.csv", "animation.glb",
                                                 "take.json"}  # the spool became the take, whole
    info = json.loads((record / "take.json").read_text())
    assert info["n_frames"] > 5 and load_track(record / "track.npz").n_frames == info["n_frames"]
    assert proc.returncode in (128 + kind, -kind), err  # a signal once it is done ends it at once: -kind
    assert "Traceback" not in err and "keyshape: closing the outputs" in err and "solved" in out


# -- Medium 5: a stopped Ray batch ends as every command does, and leaves nothing behind ---------------


@pytest.fixture(scope="module")
def two_takes(tmp_path_factory, demo_clip) -> Path:
    """A folder of two short real takes (48 frames each) of the demo clip."""
    folder = tmp_path_factory.mktemp("takes")
    frames = read_frames(demo_clip, 200)
    for name, start in (("a", 0), ("b", 100)):
        write_video(folder / f"{name}.mp4", frames[start:start + 48], fps=24)
    return folder


def _stopped_at_the_first_stage(argv, outdir: Path, kind: int, env: dict) -> subprocess.CompletedProcess:
    """``keyshape argv``, sent the real signal ``kind`` once a take's stage folder appears in ``outdir``."""
    proc = subprocess.Popen([sys.executable, "-m", "keyshape", *map(str, argv)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None and not list(outdir.glob(".*")):
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(kind)
    out, err = proc.communicate(timeout=120)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.mark.filterwarnings("ignore::ResourceWarning")
def test_item05_a_ray_batch_stopped_mid_take_exits_143_and_leaves_no_stage_nor_ray_session(two_takes, tmp_path):
    pytest.importorskip("ray")  # the optional extra; without it batch runs sequentially (the next test)
    temp, out = Path(tempfile.mkdtemp(prefix="ks-", dir="/tmp")), tmp_path / "out"  # short: Ray's socket paths
    env = {**os.environ, "TMPDIR": str(temp)}
    env.pop("RAY_TMPDIR", None)
    try:
        done = _stopped_at_the_first_stage(["batch", two_takes, "-o", out, "--workers", 2, "--no-preview"], out,
                                           signal.SIGTERM, env)
        left = list(temp.iterdir())
    finally:
        shutil.rmtree(temp, ignore_errors=True)
    assert done.returncode == 143, done.stderr
    assert done.stderr.strip() == "keyshape: terminated"  # not Ray's 'SIGTERM received' dump
    assert not out.exists() or not [p for p in out.iterdir() if p.name.startswith(".")]  # no take's stage left
    assert not left  # nor Ray's session_* folder


def test_item05_a_rerun_removes_the_stage_of_a_killed_batch(two_takes, tmp_path):
    out = tmp_path / "out"
    done = _stopped_at_the_first_stage(["batch", two_takes, "-o", out, "--sequential", "--no-preview", "-q"], out,
                                       signal.SIGKILL, dict(os.environ))
    assert done.returncode == -signal.SIGKILL
    left = [p.name for p in out.iterdir() if p.name.startswith(".")]
    assert len(left) == 1 and left[0].startswith(".a."), left  # killed mid-take: its stage stays
    (out / ".a.config").mkdir()  # a user's own hidden folder of the same look stays
    done = keyshape("batch", two_takes, "-o", out, "--sequential", "--no-preview", "-q")
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in out.iterdir()) == [".a.config", "a", "b", "summary.csv"]


# -- Medium 9: a folder output is never an input folder ------------------------------------------------


@pytest.mark.parametrize("spelled", ["same", "dot", "link"])
def test_item09_run_refuses_an_output_folder_that_is_its_image_sequence(demo_clip, tmp_path, spelled):
    from PIL import Image

    images = tmp_path / "images"
    images.mkdir()
    for i, frame in enumerate(read_frames(demo_clip, 12)):
        Image.fromarray(frame).save(images / f"frame_{i:03d}.png")
    (tmp_path / "link").symlink_to(images, target_is_directory=True)
    out = {"same": images, "dot": images / ".", "link": tmp_path / "link"}[spelled]
    before = digests(images)
    done = keyshape("run", images, "--count", 2, "--no-preview", "-o", out, "-q")
    one_line_error(done, 2, f"-o {out}: is the input folder VIDEO {images}")
    assert digests(images) == before and sorted(p.name for p in tmp_path.iterdir()) == ["images", "link"]


def test_item09_batch_refuses_its_folder_of_takes_as_outdir(two_takes, tmp_path):
    takes = shutil.copytree(two_takes, tmp_path / "takes")
    before = digests(takes)
    one_line_error(keyshape("batch", takes, "-o", takes, "--sequential", "-q"), 2,
                   f"-o {takes}: is the input folder TAKES {takes}")
    assert digests(takes) == before and sorted(p.name for p in takes.iterdir()) == ["a.mp4", "b.mp4"]


# -- Medium 10: a write that fails for want of room says where, in one line ------------------------------


def _small_files() -> None:
    """In the child: files stop growing at 300 kB (a write beyond fails, EFBIG), for it and its workers."""
    import resource

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))


def test_item10_parallel_track_out_of_room_prints_one_line_naming_where(demo_clip, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    done = subprocess.run([sys.executable, "-m", "keyshape", "track", str(demo_clip), "-o", str(out / "t.npz"),
                           "--workers", "2"], check=False, capture_output=True, text=True, timeout=600,
                          preexec_fn=_small_files)
    line = one_line_error(done, 1, f"{out}{os.sep}keyshape-track-")  # the spool beside the output
    assert line.endswith(": cannot write (File too large)"), line
    assert not list(out.iterdir())  # neither the spool nor a part of the track is left


# -- Medium 11: a glTF file whose indices or byte ranges point nowhere is one line naming it ---------------


def _rewritten_glb(source: Path, target: Path, change) -> Path:
    """``source`` (.glb) with its JSON chunk changed by ``change(document)``, the binary chunk kept,
    every length in the header right (so only the broken reference is wrong)."""
    import struct

    data = source.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + n])
    change(document)
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    rest = data[20 + n:]
    target.write_bytes(struct.pack("<4sII", b"glTF", 2, 20 + len(text) + len(rest))
                       + struct.pack("<I4s", len(text), b"JSON") + text + rest)
    return target


def _set(*where, value):
    """``change`` setting ``document[where[0]][where[1]]...`` to ``value``."""
    def change(document):
        node = document
        for key in where[:-1]:
            node = node[key]
        node[where[-1]] = value
    return change


CORRUPT = {
    "meshes[0].primitives[0].attributes.POSITION is 999": _set("meshes", 0, "primitives", 0, "attributes",
                                                              "POSITION", value=999),
    "meshes[0].primitives[0].targets[0].POSITION is -1": _set("meshes", 0, "primitives", 0, "targets", 0,
                                                             "POSITION", value=-1),
    "accessors[0].bufferView is 77": _set("accessors", 0, "bufferView", value=77),
    "bufferViews[0] ends at byte": _set("bufferViews", 0, "byteLength", value=1 << 40),
    "accessors[0] needs": _set("accessors", 0, "count", value=10 ** 7),
    "animations[0].samplers[0].output is 4000": _set("animations", 0, "samplers", 0, "output", value=4000),
    "animations[0].channels[0].sampler is 9": _set("animations", 0, "channels", 0, "sampler", value=9),
    "nodes[0].mesh is 5": _set("nodes", 0, "mesh", value=5),
}


@pytest.mark.parametrize("says", list(CORRUPT))
def test_item11_retarget_on_a_glb_with_a_broken_reference_says_which_in_one_line(made, tmp_path, says):
    rig = _rewritten_glb(made["run"] / "animation.glb", tmp_path / "rig.glb", CORRUPT[says])
    weights = tmp_path / "w.csv"
    done = keyshape("solve", made["track"], made["run"] / "keys.json", "-o", weights, "-q")
    assert done.returncode == 0, done.stderr
    one_line_error(keyshape("retarget", weights, "--rig", rig, "-o", tmp_path / "out.glb", "-q"), 1,
                   f"{rig}: a damaged glTF: {says}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.glb", "w.csv"]


def test_item11_report_on_a_take_whose_animation_is_damaged_names_it(made, tmp_path):
    folder = shutil.copytree(made["run"], tmp_path / "take")
    _rewritten_glb(made["run"] / "animation.glb", folder / "animation.glb",
                   _set("accessors", 3, "bufferView", value=1000))
    before = digests(folder)
    one_line_error(keyshape("report", folder, "--no-preview", "-q"), 1,
                   f"{folder / 'animation.glb'}: a damaged glTF: accessors[3].bufferView is 1000")
    assert digests(folder) == before


# -- Low ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("argv, says", [(["--vmc", "127.0.0.1:99999"], "argument --vmc: must be HOST:PORT"),
                                        (["--livelink", "studio-pc"], "argument --livelink: must be HOST:PORT"),
                                        (["--view", "--no-browser", "--port", "70000"],
                                         "argument --port: must be between 0 and 65535")])
def test_low_bad_addresses_and_ports_are_usage_errors_before_the_source_is_opened(made, argv, says):
    started = time.monotonic()
    one_line_error(keyshape("live", made["video"], "--keys", made["keys"], *argv), 2, says)
    assert time.monotonic() - started < 30  # refused, not after a session


@pytest.mark.parametrize("verb", ["run", "report-k", "live"])
def test_low_a_folder_output_that_is_an_existing_file_is_refused_before_the_work(made, tmp_path, verb):
    mine = tmp_path / "notes.txt"
    mine.write_text("the user's own")
    argv = {"run": ["run", made["video"], "--end", 12, "--count", 2, "-o", mine],
            "report-k": ["report-k", made["track"], "-o", mine],
            "live": ["live", made["video"], "--keys", made["keys"], "--record", mine]}[verb]
    flag = "--record" if verb == "live" else "-o"
    one_line_error(keyshape(*argv), 2, f"{flag} {mine}: is an existing file; give a folder")
    assert mine.read_text() == "the user's own" and [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


def test_low_a_track_too_short_for_keys_names_its_file(made, tmp_path):
    short = tmp_path / "short.npz"
    assert keyshape("track", made["video"], "--end", 1, "-o", short, "-q").returncode == 0
    one_line_error(keyshape("keys", short, "-o", tmp_path / "k.json", "-q"), 1,
                   "short.npz: a track needs at least 2 frames with a face; this one has 1")
    assert [p.name for p in tmp_path.iterdir()] == ["short.npz"]


def test_low_batch_whose_reader_stops_reading_finishes_every_take(two_takes, tmp_path):
    """``keyshape batch ... 2>&1 | head -1``: the pipe closes after the first line; the takes go on."""
    from keyshape.app import is_complete

    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "keyshape", "batch", str(two_takes), "-o", str(out), "--sequential",
                             "--no-preview"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    first = proc.stdout.readline()
    proc.stdout.close()  # as head -1 does
    assert proc.wait(timeout=600) == 0
    assert first.split() == ["ok", "a.mp4"]
    assert is_complete(out / "a") and is_complete(out / "b") and (out / "summary.csv").is_file()


@pytest.mark.parametrize("verb", ["batch", "run"])
def test_low_an_early_sigterm_leaves_no_empty_output_folder(made, two_takes, tmp_path, verb):
    out = tmp_path / "new" / "deep" / "out"
    argv = {"batch": ["batch", two_takes, "-o", out, "--sequential", "--no-preview", "-q"],
            "run": ["run", made["video"], "--end", 12, "--count", 2, "-o", out, "-q"]}[verb]
    seen = out if verb == "batch" else out.parent  # made at batch's start; beside run's stage, at its end
    proc = subprocess.Popen([sys.executable, "-m", "keyshape", *map(str, argv)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None and not seen.exists():
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and err.strip() == "keyshape: terminated", err
    assert list(tmp_path.iterdir()) == []  # neither OUTDIR nor the folders made for it


def test_low_live_says_what_reached_each_receiver_and_fails_when_nothing_did(made):
    """A broadcast address without SO_BROADCAST refuses every packet (EACCES): the session is not
    "sent"; a real receiver on loopback gets every packet and the line says so."""
    import socket

    argv = ["live", made["video"], "--keys", made["keys"], "--duration", 1.5]
    one_line_error(keyshape(*argv, "--vmc", "255.255.255.255:39539"), 1,
                   "no packet reached VMC 255.255.255.255:39539")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver:
        receiver.bind(("127.0.0.1", 0))
        receiver.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        port = receiver.getsockname()[1]
        done = keyshape(*argv, "--vmc", f"127.0.0.1:{port}")
        assert done.returncode == 0, done.stderr
        receiver.setblocking(False)
        received = 0
        while True:
            try:
                receiver.recv(65536)
            except BlockingIOError:
                break
            received += 1
    line = next(text for text in done.stdout.splitlines() if text.startswith(f"live: VMC 127.0.0.1:{port}:"))
    sent = int(line.split(": ")[2].split(" of ")[0])
    assert line.endswith(f"{sent} of {sent} packets sent") and sent == received > 10


@pytest.mark.parametrize("verb", ["run", "track"])
def test_low_an_output_name_at_the_file_systems_limit_is_written(made, tmp_path, verb):
    """A 254-byte output name: the temporary beside it (a stage folder, a ``.part`` file) is cut to
    fit, never a longer name than the file system takes."""
    out = tmp_path / ("a" * 254 if verb == "run" else "b" * 250 + ".npz")
    argv = {"run": ["run", made["video"], "--end", 12, "--count", 2, "--no-preview", "-o", out, "-q"],
            "track": ["track", made["video"], "--end", 12, "-o", out, "-q"]}[verb]
    done = keyshape(*argv)
    assert done.returncode == 0, done.stderr
    assert [p.name for p in tmp_path.iterdir()] == [out.name]
    assert (out / "take.json").is_file() if verb == "run" else out.stat().st_size > 0


def test_low_a_second_run_into_a_folder_being_written_is_refused_before_its_work(made, tmp_path):
    out = tmp_path / "out"
    argv = ["run", made["video"], "--end", 24, "--count", 2, "--no-preview", "-o", out]
    first = subprocess.Popen([sys.executable, "-m", "keyshape", *map(str, argv)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not list(tmp_path.glob(".out.*.keyshape-stage")) and time.monotonic() < deadline:
            time.sleep(0.05)  # the first has claimed the folder
        one_line_error(keyshape(*argv), 1, f"{out}: another keyshape command is writing into it now")
    finally:
        stdout, stderr = first.communicate(timeout=600)
    assert first.returncode == 0, stderr
    assert stdout.count(f"wrote {out}/") == 1 and (out / "take.json").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no claim left beside it
    assert keyshape(*argv, "-q").returncode == 0  # the folder is free again
