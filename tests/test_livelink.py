"""Live Link Face CSV: header and order, timecode, ARKit name matching, head angles, round trip."""

import csv

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from keyshape.containers import Poses, Weights
from keyshape.exceptions import InputError, RigError
from keyshape.io.livelink import (
    LIVELINK_NAMES,
    ROTATION_NAMES,
    livelink_columns,
    read_livelink_csv,
    timecode,
    write_livelink_csv,
)

ARKIT = [n[0].lower() + n[1:] for n in LIVELINK_NAMES]  # eyeBlinkLeft, ...


def _rows(path):
    with open(path, newline="") as handle:
        return list(csv.reader(handle))


def test_header_is_live_links(tmp_path):
    path = write_livelink_csv(tmp_path / "take.csv", Weights(np.zeros((3, 1)), ("jawOpen",), 60))
    header = _rows(path)[0]
    assert header[:2] == ["Timecode", "BlendShapeCount"]
    assert header[2:5] == ["EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft"]
    assert header[16:20] == ["JawForward", "JawRight", "JawLeft", "JawOpen"]
    assert header[54:] == ["HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
                           "RightEyeYaw", "RightEyePitch", "RightEyeRoll"]
    assert len(header) == 2 + 52 + 9
    assert {row[1] for row in _rows(path)[1:]} == {"61"}


def test_round_trip_with_arkit_names(tmp_path):
    rng = np.random.default_rng(0)
    order = rng.permutation(52)  # any channel order
    weights = Weights(rng.random((40, 52)), [ARKIT[i] for i in order], fps=30)
    back = read_livelink_csv(write_livelink_csv(tmp_path / "take.csv", weights), fps=30)
    assert back.weights.names == LIVELINK_NAMES and back.weights.fps == 30
    expected = np.empty_like(weights.values)
    expected[:, order] = weights.values
    np.testing.assert_allclose(back.weights.values, expected, atol=5e-7)
    np.testing.assert_array_equal(back.rotations, 0.0)


def test_split_and_underscore_names(tmp_path):
    names = ["eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R", "cheekPuff_L", "cheekPuff_R",
             "PupilDilate_L", "mouthRollUpper", "jawOpen"]
    sources, unused = livelink_columns(names)
    assert sources["EyeBlinkLeft"] == [0] and sources["EyeBlinkRight"] == [1]
    assert sources["BrowInnerUp"] == [2, 3] and sources["CheekPuff"] == [4, 5]
    assert sources["MouthRollUpper"] == [7] and unused == ["PupilDilate_L"]
    values = np.array([[0.1, 0.2, 0.2, 0.6, 0.0, 1.0, 0.9, 0.3, 0.5]])
    back = read_livelink_csv(write_livelink_csv(tmp_path / "t.csv", Weights(values, names, 60)))
    row = dict(zip(LIVELINK_NAMES, back.weights.values[0]))
    assert row["BrowInnerUp"] == pytest.approx(0.4) and row["CheekPuff"] == pytest.approx(0.5)
    assert row["EyeBlinkRight"] == pytest.approx(0.2) and row["TongueOut"] == 0.0


def test_values_are_clipped_to_arkit_range(tmp_path):
    weights = Weights(np.array([[1.7], [0.25], [np.nan]]), ("jawOpen",), 60)
    back = read_livelink_csv(write_livelink_csv(tmp_path / "t.csv", weights))
    np.testing.assert_array_equal(back.weights.values[:, LIVELINK_NAMES.index("JawOpen")], [1.0, 0.25, 0.0])
    # a negative weight is no weight at all: refused, as every writer refuses it (issue 34, item 6)
    with pytest.raises(InputError, match=r"would be written as -0\.2 at frame 1"):
        write_livelink_csv(tmp_path / "u.csv", Weights(np.array([[1.0], [-0.2]]), ("jawOpen",), 60))


@pytest.mark.parametrize("fps, frame, expected", [(30, 0, "00:00:00:00.000"), (30, 95, "00:00:03:05.000"),
                                                  (23.976, 24, "00:00:01:00.000"), (60, 3599, "00:00:59:59.000")])
def test_timecode_counts_frames(tmp_path, fps, frame, expected):
    path = write_livelink_csv(tmp_path / "t.csv", Weights(np.zeros((frame + 1, 1)), ("jawOpen",), fps))
    assert _rows(path)[frame + 1][0] == expected


def test_timecode_helper():
    assert timecode(59, 60) == "00:00:00:59.000"
    assert timecode(60 * 3661, 60) == "01:01:01:00.000"


def test_head_angles_from_poses(tmp_path):
    """Turning the head to the image's right (about image y, down) is a negative yaw about glTF +Y."""
    n = 3
    turns = [("y", 20.0), ("x", 10.0), ("z", 5.0)]
    rotations = np.stack([Rotation.from_euler(axis, angle, degrees=True).as_matrix() for axis, angle in turns])
    poses = Poses(rotations, np.zeros((n, 3)), np.ones(n))
    back = read_livelink_csv(write_livelink_csv(tmp_path / "t.csv", Weights(np.zeros((n, 1)), ("jawOpen",), 30),
                                                poses=poses), fps=30)
    yaw, pitch, roll = np.degrees(back.rotations[:, :3]).T
    np.testing.assert_allclose([yaw[0], pitch[0], roll[0]], [-20.0, 0.0, 0.0], atol=1e-4)
    np.testing.assert_allclose([yaw[1], pitch[1], roll[1]], [0.0, 10.0, 0.0], atol=1e-4)
    np.testing.assert_allclose([yaw[2], pitch[2], roll[2]], [0.0, 0.0, -5.0], atol=1e-4)
    np.testing.assert_array_equal(back.rotations[:, 3:], 0.0)  # no gaze yet


def test_no_arkit_names_is_an_error(tmp_path):
    with pytest.raises(RigError, match="no ARKit-named targets"):
        write_livelink_csv(tmp_path / "t.csv", Weights(np.zeros((2, 2)), ("Angry", "Sad"), 30))
    assert not (tmp_path / "t.csv").exists()


def test_reading_bad_files(tmp_path):
    (tmp_path / "w.csv").write_text("frame,time,a\n0,0,1\n")
    with pytest.raises(InputError, match=r"w\.csv: not a Live Link Face CSV"):
        read_livelink_csv(tmp_path / "w.csv")
    good = write_livelink_csv(tmp_path / "g.csv", Weights(np.zeros((2, 1)), ("jawOpen",), 30))
    text = good.read_text().replace("00:00:00:01.000", "frame one")
    (tmp_path / "bad.csv").write_text(text)
    with pytest.raises(InputError, match=r"bad\.csv, line 3: bad Timecode 'frame one'"):
        read_livelink_csv(tmp_path / "bad.csv")


def test_rotation_names():
    assert ROTATION_NAMES[:3] == ("HeadYaw", "HeadPitch", "HeadRoll")


def test_eye_angles(tmp_path):
    n = 4
    left = Rotation.from_euler("y", 12.0, degrees=True).as_matrix()  # image axes: towards image right
    right = Rotation.from_euler("x", -6.0, degrees=True).as_matrix()
    eyes = np.tile(np.stack([left, right]), (n, 1, 1, 1))
    eyes[1] = np.nan  # no estimate: hold the previous
    back = read_livelink_csv(write_livelink_csv(tmp_path / "t.csv", Weights(np.zeros((n, 1)), ("jawOpen",), 30),
                                                eyes=eyes), fps=30)
    np.testing.assert_allclose(np.degrees(back.rotations[:, 3:]), np.tile([-12.0, 0, 0, 0, -6.0, 0], (n, 1)), atol=1e-4)
    np.testing.assert_array_equal(back.rotations[:, :3], 0.0)
