"""``keyshape report-k``: the error-vs-K comparison as files and a printed table."""

import csv
import json

import numpy as np
import pytest

from keyshape.cli import main
from keyshape.datasets import make_performance
from keyshape.io.track import save_track
from keyshape.keyshapes import CURVE_METHODS as METHODS


@pytest.fixture(scope="module")
def track_file(tmp_path_factory):
    perf = make_performance(n_frames=80, n_landmarks=68, n_keys=6, noise=0.3, n_missing=2, random_state=3)
    return save_track(perf.track, tmp_path_factory.mktemp("take") / "take.npz")


def _read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_writes_csv_png_and_json_and_prints_a_table(track_file, tmp_path, capsys):
    out = tmp_path / "k"
    assert main(["report-k", str(track_file), "-o", str(out), "--max-k", "6"]) == 0
    rows = _read_csv(out / "error_vs_k.csv")
    assert list(rows[0]) == ["region", "method", "k", "error_pct"]
    assert len(rows) == 2 * len(METHODS) * 6
    assert {(r["region"], r["method"]) for r in rows} == {(g, m) for g in ("upper", "lower") for m in METHODS}
    assert sorted({int(r["k"]) for r in rows}) == list(range(1, 7))
    assert all(float(r["error_pct"]) >= 0 for r in rows)
    assert (out / "error_vs_k.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = json.loads((out / "error_vs_k.json").read_text())
    assert table["spa"]["lower"]["ks"] == list(range(1, 7))
    printed = capsys.readouterr().out
    assert "0 <= w <= 1" in printed and "% inter-ocular" in printed and "--count auto" in printed
    assert printed.count("\nupper ") == len(METHODS) and "K=4" in printed
    assert not list(out.glob(".*part*"))  # atomic writes leave no temporary files


def test_bound_option_changes_the_fits(track_file, tmp_path, capsys):
    errors = {}
    for bound in ("none", "0.3"):
        out = tmp_path / bound
        assert main(["report-k", str(track_file), "-o", str(out), "--max-k", "3", "--max", bound,
                     "--neutral", "5", "-q"]) == 0
        errors[bound] = {(r["region"], r["method"], r["k"]): float(r["error_pct"])
                         for r in _read_csv(out / "error_vs_k.csv")}
    assert capsys.readouterr().out == ""
    for key, free in errors["none"].items():
        if key[1] == "pca":
            assert errors["0.3"][key] == free
        else:
            assert errors["0.3"][key] >= free - 1e-9
    assert any(errors["0.3"][k] > errors["none"][k] + 1e-6 for k in errors["none"] if k[1] != "pca")


def test_the_k_range_is_cut_to_the_frames_there_are(tmp_path):
    perf = make_performance(n_frames=12, n_keys=2, noise=0.2, random_state=0)
    path = save_track(perf.track, tmp_path / "short.npz")
    assert main(["report-k", str(path), "-o", str(tmp_path / "k"), "--regions", "whole", "-q"]) == 0
    rows = _read_csv(tmp_path / "k" / "error_vs_k.csv")
    assert max(int(r["k"]) for r in rows) == 11  # 12 frames, one of them the neutral
    assert {r["region"] for r in rows} == {"whole"}


@pytest.mark.parametrize("argv, message", [
    (["--max", "0"], "must be > 0"),
    (["--max", "lots"], "must be a number or 'none'"),
    (["--max-k", "0"], "must be between 1 and 200"),
    (["--max-error", "-1"], "must be > 0"),
])
def test_usage_errors_exit_2(track_file, tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        main(["report-k", str(track_file), "-o", str(tmp_path / "k"), *argv])
    assert exc.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "k").exists()


def test_a_neutral_frame_out_of_range_is_one_clear_error(track_file, tmp_path, capsys):
    assert main(["report-k", str(track_file), "-o", str(tmp_path / "k"), "--neutral", "999"]) == 2  # usage
    assert "--neutral must be a frame in 0..79; got 999" in capsys.readouterr().err
    assert not (tmp_path / "k").exists()


def test_a_missing_file_is_one_clear_error(tmp_path, capsys):
    assert main(["report-k", str(tmp_path / "nope.npz"), "-o", str(tmp_path / "k")]) == 1
    assert "nope.npz: file not found" in capsys.readouterr().err


def test_neutral_frame_without_a_face(tmp_path, capsys):
    perf = make_performance(n_frames=30, n_landmarks=68, n_keys=2, noise=0.2, n_missing=3, random_state=1)
    path = save_track(perf.track, tmp_path / "gaps.npz")
    missing = int(np.flatnonzero(~perf.track.valid)[0])
    assert main(["report-k", str(path), "-o", str(tmp_path / "k"), "--neutral", str(missing)]) == 1
    assert f"--neutral frame {missing} has no face" in capsys.readouterr().err
