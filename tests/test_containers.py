import numpy as np
import pytest

from keyshape.containers import KeyShapes, Rig, Track, Weights, blend
from keyshape.exceptions import InputError


def test_track_validates_and_freezes():
    with pytest.raises(InputError, match=r"points must have shape \(n_frames, n_landmarks, 2 or 3\); got \(4, 5\)"):
        Track(np.zeros((4, 5)), 30)
    with pytest.raises(InputError, match="fps must be a positive number"):
        Track(np.zeros((2, 3, 2)), 0)
    pts = np.ones((3, 4, 2))
    pts[1, 2, 0] = np.nan  # one missing coordinate makes the whole frame missing
    track = Track(pts, 25)
    assert track.valid.tolist() == [True, False, True]
    assert np.isnan(track.points[1]).all()
    with pytest.raises(ValueError):
        track.points[0, 0, 0] = 5.0
    assert pts[0, 0, 0] == 1.0  # the caller's array is untouched


def test_track_slices_keep_metadata():
    track = Track(np.arange(60, dtype=float).reshape(5, 4, 3), 24, (640, 360), np.ones((5, 2)), ("a", "b"),
                  np.tile(np.eye(4), (5, 1, 1)))
    part = track[1:3]
    assert part.n_frames == 2 and part.blendshapes.shape == (2, 2) and part.head_matrix.shape == (2, 4, 4)
    np.testing.assert_array_equal(part.points, track.points[1:3])
    assert part.image_size == (640, 360) and part.fps == 24
    with pytest.raises(TypeError, match="sliced by frames"):
        track[2]


def test_blend_and_pose_agree():
    rng = np.random.default_rng(0)
    neutral, deltas, w = rng.normal(size=(6, 3)), rng.normal(size=(2, 6, 3)), rng.random((4, 2))
    expected = neutral + w[:, 0, None, None] * deltas[0] + w[:, 1, None, None] * deltas[1]
    np.testing.assert_allclose(blend(neutral, deltas, w), expected)
    rig = Rig(neutral, [[0, 1, 2]], deltas, ("x", "y"))
    np.testing.assert_allclose(rig.pose(w), expected)
    keys = KeyShapes(neutral, deltas, ("x", "y"), [1, 2], ("r", "r"), {"r": np.arange(6)})
    np.testing.assert_allclose(keys.pose(w), expected)


def test_bad_shapes_name_the_problem():
    with pytest.raises(InputError, match="weights must have shape"):
        Weights(np.zeros((3, 2)), ("a",), 30)
    with pytest.raises(InputError, match="key names must be unique"):
        KeyShapes(np.zeros((2, 2)), np.zeros((2, 2, 2)), ("a", "a"), [0, 1], ("r", "r"), {"r": [0, 1]})
    with pytest.raises(InputError, match=r"faces index vertices 0\.\.2"):
        Rig(np.zeros((3, 3)), [[0, 1, 5]], np.zeros((0, 3, 3)), ())
