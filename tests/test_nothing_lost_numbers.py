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
