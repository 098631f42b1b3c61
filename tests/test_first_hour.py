"""What a newcomer meets on the command line (issue 36): help that documents `run`, a default
output folder, a track file named as one, an ARKit rig refused before any tracking, stage lines
in a log."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from keyshape.containers import Rig
from keyshape.io.rig import save_obj_folder

from conftest import SHARED

RPM = SHARED / "data" / "rpm" / "RPM_Template_Mesh_XR.glb"


def _cli(*args, cwd=None):
    env = {**os.environ, "COLUMNS": "400"}  # --help unwrapped, to match its sentences whole
    return subprocess.run([sys.executable, "-m", "keyshape", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env, timeout=600, check=False)  # callers check the exit code


def _last_line(text: str) -> str:
    return [line for line in text.splitlines() if line.strip()][-1]


# --------------------------------------------------------------------------- 16: --help


def test_run_help_documents_the_output_folder_and_gives_examples():
    result = _cli("run", "--help")
    assert result.returncode == 0
    text = " ".join(result.stdout.split())
    assert ("-o OUTDIR, --output OUTDIR output folder: track.npz, keys.json, weights.csv, animation.glb, "
            "preview.mp4, the pictures and report.html (default ./keyshape-VIDEONAME, e.g. ./keyshape-take "
            "for take.mp4)") in text
    examples = result.stdout.split("examples:\n", 1)[1].splitlines()
    commands = [line.split("#")[0].split() for line in examples if line.startswith("  keyshape run")]
    assert len(commands) >= 5
    assert ["keyshape", "run", "take.mp4", "--rig", "avatar.glb", "--auto-targets", "-o", "out/"] in commands


def test_sculpt_help_documents_the_kit_folder():
    result = _cli("sculpt", "--help")
    assert result.returncode == 0
    assert ("-o KIT/, --output KIT/ the kit's folder: sculpt.glb, keys.png and README.md are written into it"
            in " ".join(result.stdout.split()))


# --------------------------------------------------------------------------- 15: a track file, no -o


def test_run_on_a_track_file_says_so_and_what_to_run(tmp_path):
    np.savez(tmp_path / "take.npz", points=np.zeros((4, 478, 3)), fps=30.0)
    result = _cli("run", "take.npz", cwd=tmp_path)
    assert result.returncode == 2
    assert _last_line(result.stderr) == (
        "keyshape run: error: take.npz is a track file, not a video: give run the video it was tracked from, "
        "or run `keyshape keys take.npz -o keys.json` then `keyshape solve take.npz keys.json -o weights.csv`")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.npz"]


@pytest.fixture(scope="module")
def default_run(demo_clip, tmp_path_factory):
    """`keyshape run take.mp4 --end 24 --no-preview` in a fresh folder, with no -o, stdout and stderr piped."""
    cwd = tmp_path_factory.mktemp("first_run")
    shutil.copy(demo_clip, cwd / "take.mp4")
    return cwd, _cli("run", "take.mp4", "--end", "24", "--no-preview", cwd=cwd)


def test_run_without_output_writes_keyshape_videoname(default_run):
    cwd, result = default_run
    assert result.returncode == 0, result.stderr
    out = cwd / "keyshape-take"
    assert {"report.html", "animation.glb", "weights.csv", "take.json"} <= {p.name for p in out.iterdir()}
    assert "wrote keyshape-take/: " in result.stdout
    assert sorted(p.name for p in cwd.iterdir()) == ["keyshape-take", "take.mp4"]


# --------------------------------------------------------------------------- 14: stage lines in a log


def test_run_in_a_log_prints_one_line_per_stage(default_run):
    _, result = default_run
    assert result.returncode == 0, result.stderr
    stages = [line for line in result.stdout.splitlines() if line.startswith("keyshape: ")]
    assert stages == ["keyshape: tracking take.mp4",
                      "keyshape: finding the key shapes of 24 frames",
                      stages[2],  # the number of keys is the search's
                      "keyshape: driving the character",
                      "keyshape: writing the animation and the take's files",
                      "keyshape: drawing the pictures and the report"]
    assert stages[2].startswith("keyshape: solving the weights of ") and stages[2].endswith(" keys")
    assert result.stderr == ""  # no bar and no stage line there: an error would be its one line


def test_quiet_run_prints_no_stage_lines(demo_clip, tmp_path):
    result = _cli("run", demo_clip, "--end", "16", "--no-preview", "-q", "-o", tmp_path / "out")
    assert result.returncode == 0, result.stderr
    assert result.stdout == "" and result.stderr == ""


# --------------------------------------------------------------------------- 4: an ARKit rig, no --auto-targets


def _arkit_rig(folder):
    """A tetrahedron with four ARKit-named targets, as an OBJ rig folder."""
    vertices = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], float)
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    names = ("jawOpen", "mouthSmileLeft", "eyeBlinkLeft", "eyeLookInLeft")
    deltas = np.zeros((4, 4, 3))
    deltas[:, 3, 2] = 0.01
    return save_obj_folder(Rig(vertices, faces, deltas, names), folder)


def test_arkit_rig_without_auto_targets_is_refused_before_tracking(demo_clip, tmp_path):
    rig = _arkit_rig(tmp_path / "arkit")
    result = _cli("run", demo_clip, "--rig", rig, "-o", tmp_path / "out")
    assert result.returncode == 1
    assert result.stderr == (
        "keyshape: error: arkit: none of its 4 targets (eyeBlinkLeft, eyeLookInLeft, jawOpen, ...) is named "
        "after a key shape (upper_00, lower_00, ...): add --auto-targets to drive its own shapes, or give "
        "--map MAP.json\n")
    assert "tracking" not in result.stdout  # refused before the first stage
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(not RPM.is_file(), reason="the Ready Player Me avatar of ../shared is not here")
def test_ready_player_me_without_auto_targets_is_refused_in_one_short_line(demo_clip, tmp_path):
    result = _cli("run", demo_clip, "--rig", RPM, "-o", tmp_path / "out")
    assert result.returncode == 1
    assert result.stderr == (
        "keyshape: error: RPM_Template_Mesh_XR.glb: none of its 52 targets (browDownLeft, browDownRight, "
        "browInnerUp, ...) is named after a key shape (upper_00, lower_00, ...): add --auto-targets to drive "
        "its own shapes, or give --map MAP.json\n")
    assert len(result.stderr) < 300 and "--allow-extra" not in result.stderr
    assert "tracking" not in result.stdout
