import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from keyshape.capture.gaze import EYEBALL_RATIO, estimate_gaze
from keyshape.schemes import mediapipe_scheme

EYES = {"right": ((100.0, 100.0), (130.0, 100.0)), "left": ((180.0, 100.0), (150.0, 100.0))}  # outer, inner
CORNER_IDS = {"right": (33, 133), "left": (263, 362)}


def _face(yaw_deg, pitch_deg, roll_deg=0.0):
    """One frame of 478 points: eye corners plus iris rings placed for known angles."""
    pts = np.zeros((478, 3))
    for eye, (outer, inner) in EYES.items():
        o, i = np.array(outer), np.array(inner)
        r = EYEBALL_RATIO * np.linalg.norm(o - i)
        centre = (o + i) / 2 + r * np.array([np.sin(np.radians(yaw_deg)), -np.sin(np.radians(pitch_deg))])
        pts[CORNER_IDS[eye][0], :2], pts[CORNER_IDS[eye][1], :2] = o, i
        ring = mediapipe_scheme()["contours"][f"{eye}_iris"]
        angles = np.linspace(0, 2 * np.pi, len(ring), endpoint=False)
        pts[ring, :2] = centre + 4 * np.c_[np.cos(angles), np.sin(angles)]
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    pts[:, :2] = (pts[:, :2] - 140) @ np.array([[c, s], [-s, c]]) + 140
    return pts


@settings(max_examples=40, deadline=None)
@given(st.floats(-35, 35), st.floats(-25, 25), st.floats(-30, 30))
def test_known_angles_are_recovered(yaw, pitch, roll):
    gaze = estimate_gaze(_face(yaw, pitch, roll)[None])
    np.testing.assert_allclose(gaze.yaw[0], [yaw, yaw], atol=1e-6)
    np.testing.assert_allclose(gaze.pitch[0], [pitch, pitch], atol=1e-6)


def test_signs_and_channels_are_separate():
    frames = np.stack([_face(0, 0), _face(15, 0), _face(0, 10)])
    wink = frames[1].copy()
    ring = mediapipe_scheme()["contours"]["left_iris"]
    wink[ring, 0] -= 5  # only the left iris moves, toward image -x
    gaze = estimate_gaze(np.concatenate([frames, wink[None]]), neutral_frame=0)
    assert gaze.yaw[1, 0] > 10 and gaze.yaw[1, 1] > 10  # both look to the actor's left
    assert gaze.pitch[2].min() > 5  # looking up is positive
    assert gaze.yaw[3, 0] == pytest.approx(gaze.yaw[1, 0])
    assert gaze.yaw[3, 1] < gaze.yaw[1, 1] - 5


def test_neutral_frame_is_straight_ahead():
    frames = np.stack([_face(5, -3), _face(20, 7)])
    gaze = estimate_gaze(frames, neutral_frame=0)
    np.testing.assert_allclose(gaze.yaw[0], 0, atol=1e-9)
    assert gaze.yaw[1, 0] > 10


def test_needs_irises():
    with pytest.raises(ValueError, match="478 landmarks"):
        estimate_gaze(np.zeros((2, 468, 3)))


def test_rotations_turn_the_eye_toward_the_gaze():
    frames = np.stack([_face(0, 0), _face(20, 0), _face(0, 15), _face(-10, -5)])
    gaze = estimate_gaze(frames)
    rot = gaze.rotations()
    assert rot.shape == (4, 2, 3, 3)
    np.testing.assert_allclose(np.einsum("feij,feik->fejk", rot, rot), np.tile(np.eye(3), (4, 2, 1, 1)),
                               atol=1e-12)
    look = rot @ np.array([0.0, 0.0, -1.0])  # rest: toward the camera
    assert look[1, 0, 0] > 0.3 and look[1, 1, 0] > 0.3  # yaw > 0: toward image +x
    assert look[2, 0, 1] < -0.2  # pitch > 0: up (image -y)
    yaw, pitch = np.radians(-10), np.radians(-5)
    np.testing.assert_allclose(look[3, 0], [np.sin(yaw) * np.cos(pitch), -np.sin(pitch),
                                            -np.cos(yaw) * np.cos(pitch)], atol=1e-9)
