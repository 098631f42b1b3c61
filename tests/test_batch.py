"""``keyshape batch``: four real short clips plus a corrupt one, sequentially, on local Ray
(2 workers) and on a Ray head started here on loopback; reruns skip, failures are reported."""

from __future__ import annotations

import csv
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from keyshape.app import BatchRow, SequentialRunner, find_takes, format_table, is_complete, make_runner
from keyshape.cli import main
from keyshape.exceptions import InputError, MissingDependencyError

from conftest import read_frames, write_video

pytestmark = pytest.mark.slow

GOOD = ("single_face", "demo_a", "demo_b", "demo_c")
# Ray's own start-up and shutdown noise; nothing of keyshape's is filtered
RAY_WARNINGS = [pytest.mark.filterwarnings("ignore::ResourceWarning"),
                pytest.mark.filterwarnings("ignore::DeprecationWarning:ray.*"),
                pytest.mark.filterwarnings("ignore::FutureWarning:ray.*"),
                pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")]


def _ray_marks(fn):
    for mark in RAY_WARNINGS:
        fn = mark(fn)
    return fn


@pytest.fixture(scope="module")
def takes(tmp_path_factory, clips, demo_clip) -> Path:
    """A folder of four short real takes (72 and 3 x 48 frames) and a truncated, corrupt one."""
    folder = tmp_path_factory.mktemp("takes")
    shutil.copy(clips / "single_face.mp4", folder / "single_face.mp4")
    frames = read_frames(demo_clip, 300)
    for name, start in zip(GOOD[1:], (0, 120, 250)):
        write_video(folder / f"{name}.mp4", frames[start:start + 48], fps=24)
    (folder / "corrupt.mp4").write_bytes((clips / "single_face.mp4").read_bytes()[:4000])
    return folder


def _batch(*args) -> int:
    return main(["batch", *map(str, args), "--no-preview", "-q"])


def _summary(outdir: Path) -> dict[str, dict]:
    with (outdir / "summary.csv").open(newline="") as f:
        return {row["take"]: row for row in csv.DictReader(f)}


def _weights(path: Path) -> np.ndarray:
    return np.genfromtxt(path, delimiter=",", skip_header=1)


@pytest.fixture(scope="module")
def sequential_out(tmp_path_factory, takes) -> Path:
    out = tmp_path_factory.mktemp("sequential")
    assert _batch(takes, "-o", out, "--sequential") == 1  # the corrupt take fails the batch
    return out


@pytest.fixture(scope="module")
def shared_out(tmp_path_factory, takes) -> Path:
    out = tmp_path_factory.mktemp("shared")
    assert _batch(takes, "-o", out, "--sequential", "--shared-keys") == 1
    return out


def test_corrupt_take_is_reported_and_the_rest_complete(sequential_out):
    from keyshape.io.keys_json import load_keys

    rows = _summary(sequential_out)
    assert list(rows) == sorted(["corrupt.mp4", *(f"{n}.mp4" for n in GOOD)])  # folder order
    assert rows["corrupt.mp4"]["status"] == "failed"
    assert "not a video" in rows["corrupt.mp4"]["error"]
    for name in GOOD:
        row = rows[f"{name}.mp4"]
        assert row["status"] == "ok" and row["error"] == ""
        assert int(row["frames"]) == (72 if name == "single_face" else 48)
        keys = load_keys(sequential_out / name / "keys.json")  # 8 frames per region, and their mirrors
        assert float(row["detection_rate"]) == 1.0 and int(row["keys"]) == keys.n_keys
        assert (~keys.mirrored).sum() == 16
        assert 0 < float(row["error_pct"]) < 6  # all landmarks count (no hand: none hidden)
        assert is_complete(sequential_out / name)
    assert not (sequential_out / "corrupt").exists()
    assert not [p for p in sequential_out.iterdir() if p.name.startswith(".")]  # no staging left


def test_rerun_skips_finished_takes(sequential_out, takes, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(sequential_out, out)
    (out / "demo_b" / "weights.csv").unlink()  # an incomplete take is done again
    (out / "single_face" / "keys.json").write_text("garbage")  # and one whose output was overwritten
    (out / "demo_c" / "notes.txt").write_text("the user's own")  # the user's own file changes nothing
    before = (out / "demo_a" / "weights.csv").stat().st_mtime_ns
    assert _batch(takes, "-o", out, "--sequential") == 1
    rows = _summary(out)
    assert {n: rows[f"{n}.mp4"]["status"] for n in GOOD} == {
        "single_face": "ok", "demo_a": "skipped", "demo_b": "ok", "demo_c": "skipped"}
    redone = (out / "single_face" / "keys.json").read_bytes()
    assert redone == (sequential_out / "single_face" / "keys.json").read_bytes()
    assert (out / "demo_c" / "notes.txt").read_text() == "the user's own"
    assert rows["corrupt.mp4"]["status"] == "failed"
    assert rows["demo_a.mp4"]["frames"] == "48" and rows["demo_a.mp4"]["error_pct"]  # kept from before
    assert (out / "demo_a" / "weights.csv").stat().st_mtime_ns == before
    assert is_complete(out / "demo_b")


@_ray_marks
def test_local_ray_matches_sequential(sequential_out, takes, tmp_path):
    out = tmp_path / "ray"
    assert _batch(takes, "-o", out, "--workers", "2") == 1
    rows = _summary(out)
    assert rows["corrupt.mp4"]["status"] == "failed"
    for name in GOOD:
        assert rows[f"{name}.mp4"]["status"] == "ok"
        for file in ("weights.csv", "keys.json"):
            a, b = sequential_out / name / file, out / name / file
            if file == "keys.json":
                assert b.read_bytes() == a.read_bytes(), name
            else:  # numerically equal is enough
                np.testing.assert_allclose(_weights(b), _weights(a), atol=1e-9, err_msg=name)


def test_shared_keys_one_key_set_for_every_take(shared_out):
    from keyshape.io.keys_json import load_keys

    shared = load_keys(shared_out / "keys.json")
    assert len(set(shared.takes)) > 1  # keys come from several takes
    assert set(shared.takes) <= {f"{n}.mp4" for n in GOOD}
    for name in GOOD:
        keys = load_keys(shared_out / name / "keys.json")
        assert keys.names == shared.names and keys.takes == shared.takes
        np.testing.assert_array_equal(keys.frames, shared.frames)
        np.testing.assert_array_equal(keys.deltas, shared.deltas)
        header = (shared_out / name / "weights.csv").read_text().splitlines()[0]
        assert header == ",".join(["frame", "time", *shared.names])
    rows = _summary(shared_out)
    assert rows["corrupt.mp4"]["status"] == "failed"
    assert all(rows[f"{n}.mp4"]["status"] == "ok" for n in GOOD)
    assert not (shared_out / ".tracks").exists()  # the first pass's tracks are cleaned up


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ray_head(tmp_path_factory):
    """A Ray head on loopback, as a user would start it (`ray start --head`), stopped afterwards.

    Started with ``--block`` in its own process group so that teardown stops exactly this head
    (and its children) by id; ``ray stop`` would stop every Ray on the machine.
    """
    ray_cli = Path(sys.executable).with_name("ray")
    port = _free_port()
    log = (tmp_path_factory.mktemp("ray-head") / "head.log").open("w")
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "RAY_USAGE_STATS_ENABLED": "0"}
    head = subprocess.Popen([str(ray_cli if ray_cli.exists() else "ray"), "start", "--head", "--block",
                             "--port", str(port), "--node-ip-address", "127.0.0.1", "--num-cpus", "2",
                             "--include-dashboard", "false", "--disable-usage-stats"],
                            stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    try:
        _wait_for_port(port, head)
        yield f"127.0.0.1:{port}"
    finally:
        os.killpg(head.pid, signal.SIGTERM)
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()
        log.close()
        current = Path(tempfile.gettempdir()) / "ray" / "ray_current_cluster"  # left by this head
        if current.is_file() and current.read_text().strip() == f"127.0.0.1:{port}":
            current.unlink()


def _wait_for_port(port: int, head: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert head.poll() is None, "ray start --head exited; see head.log"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                time.sleep(2)  # the GCS listens before the raylet has registered
                return
        time.sleep(0.5)
    pytest.fail(f"the Ray head did not listen on 127.0.0.1:{port} within {timeout} s")


@_ray_marks
def test_cluster_address_shared_keys_matches_sequential(ray_head, takes, shared_out, tmp_path):
    out = tmp_path / "cluster"
    assert _batch(takes, "-o", out, "--address", ray_head, "--shared-keys") == 1
    rows = _summary(out)
    assert rows["corrupt.mp4"]["status"] == "failed"
    assert all(rows[f"{n}.mp4"]["status"] == "ok" for n in GOOD)
    assert (out / "keys.json").read_bytes() == (shared_out / "keys.json").read_bytes()
    for name in GOOD:
        np.testing.assert_allclose(_weights(out / name / "weights.csv"),
                                   _weights(shared_out / name / "weights.csv"), atol=1e-9)


# -- without the real work ----------------------------------------------------------------------

def test_find_takes_files_and_folders(tmp_path):
    (tmp_path / "a.mp4").write_bytes(b"")
    (tmp_path / "b.MOV").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("")
    other = tmp_path / "more"
    other.mkdir()
    (other / "c.mkv").write_bytes(b"")
    assert [p.name for p in find_takes([tmp_path, other / "c.mkv"])] == ["a.mp4", "b.MOV", "c.mkv"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no videos in this folder"):
        find_takes([tmp_path / "empty"])
    (other / "a.mov").write_bytes(b"")
    with pytest.raises(InputError, match="share the output folder 'a'"):
        find_takes([tmp_path, other])
    with pytest.raises(InputError, match="no such file"):
        find_takes([tmp_path / "missing.mp4"])


def test_without_ray_runs_sequentially(monkeypatch):
    import keyshape.app._ray as kray

    monkeypatch.setattr(kray, "ray_available", lambda: False)
    assert isinstance(make_runner(), SequentialRunner)
    assert isinstance(make_runner(sequential=True), SequentialRunner)
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(MissingDependencyError, match=r'keyshape\[ray\]'):
        make_runner(address="127.0.0.1:6379").__enter__()


def test_table_lists_failures():
    rows = [BatchRow("a.mp4", 72, 1.0, 16, 0.5, "ok", 3.2),
            BatchRow("b.mp4", status="failed", error="b.mp4: not a video")]
    text = format_table(rows)
    assert "a.mp4" in text and "100.0" in text and "failed" in text
    assert text.splitlines()[-1] == "b.mp4: b.mp4: not a video"
