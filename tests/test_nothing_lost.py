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
import time
from pathlib import Path

import numpy as np
import pytest


def keyshape(*argv, cwd=None, timeout=600) -> subprocess.CompletedProcess:
    """``keyshape argv`` in a child process (the child inherits PYTHONPATH)."""
    return subprocess.run([sys.executable, "-m", "keyshape", *map(str, argv)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


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
