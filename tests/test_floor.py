"""The peer's path as the floor (keyshape.targets._floor): score channels for every ARKit target,
less the character's rest reading, and the key route kept where asked."""

import numpy as np

from keyshape.containers import Weights
from keyshape.targets import Mapping, drive_gaze, retarget, score_floor, with_floor

TARGETS = ("jawOpen", "eyeBlink_L", "eyeBlink_R", "eyeLookIn_L", "customShape")
SCORES = ("_neutral", "jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "eyeLookInLeft")


def test_the_floor_is_each_score_less_its_rest_reading():
    floor = score_floor(TARGETS, SCORES, rest={"jawOpen": 0.1, "eyeBlinkLeft": 0.3})
    assert [t for t, _, _ in floor] == ["jawOpen", "eyeBlink_L", "eyeBlink_R", "eyeLookIn_L"]  # no score: none
    route = Mapping(np.ones((5, 2)), ("k0", "k1"), TARGETS, offset=np.full(5, 0.2))
    floored = with_floor(route, floor, keep=())
    scores = np.array([[0.0, 0.5, 0.2, 0.9, 0.4], [0.0, 0.05, 0.8, 0.1, 0.0]])
    keys = Weights(np.array([[0.5, 0.0], [0.0, 1.0]]), ("k0", "k1"), 30.0)
    anim = drive_gaze(retarget(keys, floored), floored, scores, SCORES)
    np.testing.assert_allclose(anim.values[:, :4], [[0.4, 0.0, 0.9, 0.4], [0.0, 0.5, 0.1, 0.0]])  # clipped at 0
    np.testing.assert_allclose(anim.values[:, 4], [0.7, 1.2])  # no score: the keys drive it still


def test_kept_targets_keep_the_route_and_its_own_gaze_channel(tmp_path):
    floor = score_floor(TARGETS, SCORES)
    route = Mapping(np.where(np.arange(5)[:, None] == 3, 0.0, 0.5), ("k0",), TARGETS,
                    gaze=(("eyeLookIn_L", "x", 0.0),))
    floored = with_floor(route, floor, keep={"jawOpen", "eyeLookIn_L"})
    assert [g[0] for g in floored.gaze] == ["eyeBlink_L", "eyeBlink_R", "eyeLookIn_L"]
    assert ("eyeLookIn_L", "x", 0.0) in floored.gaze  # the route's own channel, not the floor's
    np.testing.assert_allclose(floored.matrix[:, 0], [0.5, 0, 0, 0, 0.5])
    path = floored.save(tmp_path / "map.json")
    again = Mapping.from_file(path, targets=TARGETS)  # the floor survives map.json
    assert again.gaze == floored.gaze


def test_gaze_targets_left_to_eye_nodes_stay_off_the_floor():
    floor = score_floor(TARGETS, SCORES, exclude=("eyeLook*",))
    assert [t for t, _, _ in floor] == ["jawOpen", "eyeBlink_L", "eyeBlink_R"]
