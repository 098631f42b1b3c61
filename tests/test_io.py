import json

import numpy as np
import pytest

from keyshape.containers import KeyShapes, Track, Weights
from keyshape.exceptions import InputError
from keyshape.io.keys_json import load_keys, save_keys
from keyshape.io.track import load_track, save_track
from keyshape.io.weights_csv import load_weights_csv, save_weights_csv


def _track(n=5, n_landmarks=4, d=3):
    pts = np.random.default_rng(1).normal(size=(n, n_landmarks, d)) * 100
    pts[2] = np.nan
    return Track(pts, 23.976, (640, 360), np.random.default_rng(2).random((n, 52)),
                 tuple(f"s{i}" for i in range(52)), np.tile(np.eye(4), (n, 1, 1)))


def test_track_round_trip(tmp_path):
    track = _track()
    back = load_track(save_track(track, tmp_path / "t.npz"))
    np.testing.assert_array_equal(back.points, track.points)
    assert back.fps == track.fps and back.image_size == (640, 360)
    assert back.blendshape_names == track.blendshape_names
    np.testing.assert_array_equal(back.valid, [True, True, False, True, True])


def test_track_from_other_tools_needs_only_points_and_fps(tmp_path):
    np.savez(tmp_path / "other.npz", points=np.zeros((3, 68, 2)), fps=30)
    assert load_track(tmp_path / "other.npz").n_landmarks == 68


@pytest.mark.parametrize("arrays, message", [
    ({"points": np.zeros((3, 4))}, "lacks \\['fps'\\]"),
    ({"points": np.zeros((3, 4, 5)), "fps": 30}, "points must have shape"),
    ({"points": np.zeros((3, 4, 2)), "fps": -1}, "fps must be a positive number"),
    ({"points": np.zeros((3, 4, 2)), "fps": 30, "visibility": np.full((3, 4), 1.5, np.float32)}, "visibility"),
    ({"points": np.zeros((3, 4, 2)), "fps": 30, "visibility": np.array([[1, 1, np.nan, 1]] * 3, np.float32)},
     "visibility.*values in \\[0, 1\\]"),
    ({"points": np.zeros((3, 4, 2)), "fps": 30, "visibility": np.full((3, 4), -0.1, np.float32)}, "visibility"),
])
def test_bad_track_files(tmp_path, arrays, message):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match=message):
        load_track(tmp_path / "bad.npz")


def test_not_an_npz(tmp_path):
    (tmp_path / "x.npz").write_text("hello")
    with pytest.raises(InputError, match=r"x\.npz: not a readable \.npz"):
        load_track(tmp_path / "x.npz")


def test_weights_csv_round_trip(tmp_path):
    values = np.random.default_rng(0).random((50, 3))
    values[7] = np.nan
    w = Weights(values, ("upper_00", "upper_01", "lower_00"), 23.976)
    back = load_weights_csv(save_weights_csv(w, tmp_path / "w.csv"))
    assert back.names == w.names
    np.testing.assert_allclose(back.values, w.values, atol=5e-7)
    assert back.fps == pytest.approx(23.976, rel=1e-5)
    header = (tmp_path / "w.csv").read_text().splitlines()[0]
    assert header == "frame,time,upper_00,upper_01,lower_00"


_SPECIAL = np.array([0.0, -0.0, np.nan, np.inf, -np.inf, 1 / 128, 3 / 128, 0.5, 1.0, 1e6, 1e6 - 1e-7, 1e-7, 5e-7,
                     -5e-7, 4.9999999e-7, 1e300, -1e-300, 2.5e-6, 123456.0000005, 0.9999995, 99.9999996])


def _cells(kind: str, rng, shape: tuple[int, int]) -> np.ndarray:
    if kind == "weights":
        return rng.random(shape)
    if kind == "scaled":
        return rng.standard_normal(shape) * 10.0 ** rng.integers(-8, 12, shape)
    if kind == "special":
        return rng.choice(_SPECIAL, shape)
    if kind == "dyadic":  # ties at the sixth decimal: multiples of 1/128
        return rng.integers(-10**6, 10**6, shape) / 2.0 ** rng.integers(0, 12, shape)
    return np.round(rng.random(shape), 4) + rng.choice([0, 5e-7, -5e-7], shape)  # near ties


@pytest.mark.parametrize("kind", ["weights", "scaled", "special", "dyadic", "rounded"])
def test_weights_csv_cells_are_what_percent_formatting_writes(kind):
    """The numpy cell writer gives the bytes of "%d,%.6f,..." % row (NaN empty), ties and rows it
    leaves to "%" (inf, huge values, frames beyond 10⁸) included."""
    from keyshape.io.weights_csv import _rows

    rng = np.random.default_rng(len(kind))
    for _ in range(40):
        n, c = int(rng.integers(1, 40)), int(rng.integers(0, 6))
        values = _cells(kind, rng, (n, c))
        frames = np.sort(rng.choice([0, 7, 99_999_999, 10**8, 2**53 + 1, 12345], n)) if c % 2 else np.arange(n) * 3
        times = rng.choice(_SPECIAL, n) if c == 3 else rng.random(n) * 10.0 ** rng.integers(0, 8)
        line = ",".join(["%d", "%.6f"] + ["%.6f"] * c) + "\r\n"
        table = np.column_stack([frames, times, values]).astype(float)
        expected = ((line * n) % tuple(table.ravel().tolist())).replace("nan", "")
        assert _rows(frames, times, values) == expected


def test_keys_round_trip(tmp_path):
    neutral = np.arange(12, dtype=float).reshape(4, 3)
    deltas = np.zeros((2, 4, 3))
    deltas[0, :2] = 1.5
    deltas[1, 2:] = -2.0
    keys = KeyShapes(neutral, deltas, ("upper_00", "lower_00"), np.array([5, 9]), ("upper", "lower"),
                     {"upper": [0, 1], "lower": [2, 3]}, ("a.npz", "a.npz"), 3, "a.npz", "spa", [0, 1])
    path = save_keys(keys, tmp_path / "k.json")
    data = json.loads(path.read_text())
    assert data["regions"]["lower"]["keys"] == [{"name": "lower_00", "take": "a.npz", "frame": 9}]
    back = load_keys(path)
    np.testing.assert_allclose(back.deltas, keys.deltas)
    assert back.names == keys.names and back.frames.tolist() == [5, 9] and back.neutral_frame == 3


def test_not_a_key_file(tmp_path):
    (tmp_path / "k.json").write_text("{}")
    with pytest.raises(InputError, match="not a keyshape key file"):
        load_keys(tmp_path / "k.json")


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    def boom(*args):
        raise RuntimeError("disk full")

    monkeypatch.setattr("keyshape.io.weights_csv._rows", boom)
    w = Weights(np.zeros((2, 1)), ("a",), 30)
    with pytest.raises(RuntimeError):
        save_weights_csv(w, tmp_path / "w.csv")
    assert list(tmp_path.iterdir()) == []


def test_landmark_csv_from_another_tool(tmp_path):
    path = tmp_path / "other.csv"
    path.write_text("frame,time,x0,y0,x1,y1,x2,y2\n0,0.0,1,2,3,4,5,6\n1,0.04,,,,,,\n2,0.08,1,2,3,4,5,7\n")
    track = load_track(path)
    assert track.points.shape == (3, 3, 2)
    assert track.valid.tolist() == [True, False, True]
    assert track.fps == pytest.approx(25.0)
    assert track.points[2, 2, 1] == 7


def test_landmark_csv_3d_and_bad_header(tmp_path):
    path = tmp_path / "t3.csv"
    path.write_text("frame,x0,y0,z0,x1,y1,z1\n0,1,2,3,4,5,6\n")
    assert load_track(path, fps=50).n_dims == 3 and load_track(path, fps=50).fps == 50
    bad = tmp_path / "bad.csv"
    bad.write_text("frame,a,b\n0,1,2\n")
    with pytest.raises(InputError, match=r"bad\.csv: landmark columns must be x0,y0"):
        load_track(bad)


def test_written_files_have_the_usual_permissions(tmp_path):
    import os

    path = save_weights_csv(Weights(np.zeros((2, 1)), ("a",), 30), tmp_path / "w.csv")
    mask = os.umask(0)
    os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask
