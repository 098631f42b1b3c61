"""Issue 34, "Nothing lost, round two": the numbers that reach a file (items 6, 7, 8 and the Low
items on the readers), each driving the real command in a child process.

A failing command must exit with one line naming what is wrong and write no output.
"""

from __future__ import annotations

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
