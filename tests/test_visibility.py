"""Occlusion: per-landmark visibility from the video, the track file, and key discovery."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from keyshape.containers import Track
from keyshape.exceptions import InputError
from keyshape.io.track import load_track, save_track
from keyshape.keyshapes._search import visible_frames
from keyshape.schemes import mediapipe_scheme

LABELS = Path(__file__).parents[1] / "benchmarks" / "occlusion_labels.json"


def _labelled(part: str, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(covered, ambiguous) (n_frames,) bool from the hand labels."""
    labels = json.loads(LABELS.read_text())
    covered = np.zeros(n_frames, bool)
    for first, last in labels["covered"][part]:
        covered[first:last + 1] = True
    ambiguous = np.zeros(n_frames, bool)
    ambiguous[labels["ambiguous"][part]] = True
    return covered, ambiguous


def test_visibility_is_checked_and_sliced():
    points = np.zeros((4, 5, 2))
    with pytest.raises(InputError, match="visibility must be"):
        Track(points, 30.0, visibility=np.full((4, 5), 2.0))
    track = Track(points, 30.0, visibility=np.linspace(0, 1, 20).reshape(4, 5))
    assert track[1:3].visibility.shape == (2, 5)
    np.testing.assert_array_equal(track.with_points(points + 1).visibility, track.visibility)
    assert Track(points, 30.0).seen.min() == 1.0


def test_track_file_keeps_visibility_and_old_files_load_as_seen(tmp_path):
    points = np.random.default_rng(0).normal(size=(3, 4, 3))
    seen = np.array([[1, 0.5, 0, 1]] * 3, dtype=float)
    back = load_track(save_track(Track(points, 25.0, visibility=seen), tmp_path / "v.npz"))
    np.testing.assert_allclose(back.visibility, seen)
    old = load_track(save_track(Track(points, 25.0), tmp_path / "old.npz"))
    assert old.visibility is None and (old.seen == 1).all()


def test_keys_never_come_from_frames_whose_region_is_hidden():
    points = np.zeros((6, 4, 2))
    seen = np.ones((6, 4))
    seen[2, :2] = 0.0  # region [0, 1] hidden in frame 2
    track = Track(points, 30.0, visibility=seen)
    assert visible_frames(track, np.arange(1, 6), [0, 1]).tolist() == [1, 3, 4, 5]
    assert visible_frames(track, np.arange(1, 6), [2, 3]).tolist() == [1, 2, 3, 4, 5]
    assert visible_frames(Track(points, 30.0), np.arange(6), [0]).size == 6


def _hand(at=(100.0, 100.0), size=40.0) -> np.ndarray:
    """(21, 2) an upright open hand, fingers together, knuckles ``size`` apart, the wrist below."""
    x0, y0 = at
    hand = np.zeros((21, 2))
    hand[0] = (x0 + size / 2, y0 + size)  # the wrist
    for finger in range(4):  # index .. little: knuckle 5 + 4 f, then three joints up
        x = x0 + finger * size / 3
        for joint in range(4):
            hand[5 + 4 * finger + joint] = (x, y0 - joint * size / 2)
    hand[1:5] = [(x0 - 0.2 * size * k, y0 + size - 0.3 * size * k) for k in range(1, 5)]  # the thumb, out to the left
    return hand


def test_a_hand_covers_what_is_under_its_palm_and_fingers_only():
    from keyshape.capture.visibility import HAND_RADIUS, hand_cover

    hand = _hand()
    radius = HAND_RADIUS * 40.0
    points = np.array([
        [120.0, 80.0],  # between the middle fingers, over the palm: covered
        [100.0, 45.0],  # on the index finger's last bone (its tip at y 40)
        [140.0 + 0.9 * radius, 60.0],  # just beyond the little finger, within its half-width
        [140.0 + 1.5 * radius, 60.0],  # further out: seen
        [120.0, 20.0],  # above the fingertips (at y 40): seen
        [-20.0, 300.0],  # far away
        [80.0, 110.0],  # on the thumb (from (92, 128) out to (68, 92))
    ])
    assert hand_cover(points, hand).tolist() == [True, True, True, False, False, False, True]
    # in 3-D tracks only x, y count; the hand scales with its knuckle span
    assert hand_cover(np.c_[points, np.ones(len(points))], hand).tolist()[:4] == [True, True, True, False]
    assert hand_cover(points * 2, _hand((200.0, 200.0), 80.0)).tolist() == hand_cover(points, hand).tolist()


def test_visibility_from_hands_is_none_without_a_hand_over_the_face():
    from keyshape.capture.visibility import visibility_from_hands

    points = np.tile(np.array([[120.0, 80.0], [300.0, 300.0]]), (4, 1, 1))
    hands = np.full((4, 2, 21, 2), np.nan)
    assert visibility_from_hands(points, hands) is None  # no hand: no visibility at all
    hands[1, 1] = _hand((500.0, 500.0))  # a hand away from the face
    assert visibility_from_hands(points, hands) is None
    hands[2, 0] = _hand()  # over landmark 0 in frame 2
    points[3] = np.nan  # a frame without a face stays seen
    hands[3, 0] = _hand()
    seen = visibility_from_hands(points, hands)
    assert seen.dtype == np.float32 and seen.tolist() == [[1, 1], [1, 1], [0, 1], [1, 1]]


@pytest.mark.slow
def test_mouth_visibility_on_the_labelled_clip(real_track):
    """The mouth (the lips, hidden by the region rule: over 30 % of its landmarks) hidden in
    >= 90 % of the covered frames and seen in >= 98 % of the clear ones."""
    lips = np.array(mediapipe_scheme()["contours"]["lips"])
    hidden = real_track.hidden(lips)
    covered, ambiguous = _labelled("mouth", real_track.n_frames)
    assert hidden[covered & ~ambiguous].mean() >= 0.90
    assert (~hidden[~covered & ~ambiguous]).mean() >= 0.98


@pytest.mark.slow
def test_covered_eye_is_hidden_on_the_labelled_clip(real_track):
    eye = np.array(mediapipe_scheme()["contours"]["right_eye"])
    hidden = real_track.hidden(eye)
    covered, ambiguous = _labelled("right_eye", real_track.n_frames)
    assert hidden[covered & ~ambiguous].mean() >= 0.90
    assert (~hidden[~covered & ~ambiguous]).mean() >= 0.98


@pytest.mark.slow
def test_expressions_are_not_occluders_on_the_labelled_clip(real_track):
    """Eyes shut in laughter (MediaPipe's blink score above 0.5 in about 180 of the 472 frames), the
    distress, the open mouth: nothing after the hand has gone (frames 236 on) is hidden, and the
    closed eyes are seen (the appearance estimate before read a third of such frames as hidden)."""
    from keyshape.schemes import resolve_regions

    contours = mediapipe_scheme()["contours"]
    names = list(real_track.blendshape_names)
    blink = np.nan_to_num(real_track.blendshapes[:, [names.index("eyeBlinkLeft"),
                                                      names.index("eyeBlinkRight")]]).mean(axis=1)
    assert (blink > 0.5).sum() > 100
    left = real_track.hidden(np.array(contours["left_eye"]))
    assert not left[blink > 0.5].any()
    for landmarks in resolve_regions("upper-lower", 478).values():
        assert not real_track.hidden(landmarks)[236:].any()
    assert (real_track.visibility[236:] == 1).all()


@pytest.mark.slow
def test_a_take_without_a_hand_has_no_visibility_and_the_same_results(clips):
    """A real clip with no hand in it: no visibility at all, so its keys, neutral and weights are
    exactly those of ``--visibility off``."""
    from keyshape.app import discover_keys, solve_take
    from keyshape.capture import track_video

    track = track_video(clips / "single_face.mp4", progress=False)
    off = track_video(clips / "single_face.mp4", progress=False, visibility="off")
    assert track.visibility is None and off.visibility is None
    np.testing.assert_array_equal(track.points, off.points)
    keys = discover_keys(track)
    assert keys.frames.tolist() == discover_keys(off).frames.tolist()
    np.testing.assert_array_equal(solve_take(track, keys).weights.values, solve_take(off, keys).weights.values)


@pytest.mark.slow
def test_no_default_key_in_a_covered_frame(real_track):
    from keyshape.app import discover_keys

    keys = discover_keys(real_track)
    mouth, _ = _labelled("mouth", real_track.n_frames)
    eye, _ = _labelled("right_eye", real_track.n_frames)
    for region, frame in zip(keys.key_regions, keys.frames):
        assert not (mouth if region == "lower" else eye)[frame], (region, int(frame))


@pytest.mark.slow
def test_hands_found_while_tracking_give_the_second_decode_visibility(demo_clip, real_track):
    """One decode: the hands looked for as the frames are tracked give exactly what looking for
    them in a second decode after tracking (:func:`estimate_visibility`) gives."""
    from keyshape.capture.visibility import estimate_visibility

    np.testing.assert_array_equal(real_track.visibility, estimate_visibility(demo_clip, real_track.points))


def test_spooled_hands_read_back(tmp_path):
    from keyshape.capture._spool import HANDS_SHAPE, Spool
    from keyshape.capture._track import _Frame

    hands = np.full(HANDS_SHAPE, np.nan, np.float32)
    hands[1] = _hand()
    with Spool(tmp_path) as spool:
        for k in range(3):
            spool.append(_Frame(np.zeros((478, 3), np.float32), np.zeros(52, np.float32), np.eye(4, dtype=np.float32),
                                hands=hands if k == 1 else None))
    assert spool.n_frames == 3 and spool.n_hands == 1
    back = spool.arrays()["hands"]
    assert np.isnan(back[[0, 2]]).all() and np.isnan(back[1, 0]).all()
    np.testing.assert_array_equal(back[1, 1], hands[1])


@pytest.mark.slow
def test_visibility_off_looks_for_no_hands(demo_clip, tmp_path):
    """``keyshape track --visibility off``: no visibility in the file; by default the hand over the
    mouth from frame 58 on is there."""
    from keyshape.cli import main

    assert main(["track", str(demo_clip), "--end", "90", "-o", str(tmp_path / "on.npz"), "-q"]) == 0
    assert main(["track", str(demo_clip), "--end", "90", "--visibility", "off", "-o", str(tmp_path / "off.npz"),
                 "-q"]) == 0
    on, off = load_track(tmp_path / "on.npz"), load_track(tmp_path / "off.npz")
    lips = np.array(mediapipe_scheme()["contours"]["lips"])
    assert off.visibility is None and not on.hidden(lips)[:55].any() and on.hidden(lips)[70:].mean() > 0.9
    np.testing.assert_array_equal(on.points, off.points)


@pytest.mark.slow
def test_face_windows_find_a_hand_already_on_the_face(demo_clip, real_track):
    """The hand landmark model asked over the face finds a hand that is already lying over the
    mouth when the finder starts (frames 120-227: nothing to follow from its coming in, where the
    palm detector on single pictures finds it in 13 % of the covered frames), and no hand on the
    clear frames after it has gone (236-471: laughter, distress, shut eyes)."""
    from keyshape.capture import iter_frames
    from keyshape.capture.mediapipe import _FaceWindows, default_hand_model_path
    from keyshape.capture.visibility import hand_cover

    lips = np.array(mediapipe_scheme()["contours"]["lips"])
    over, clear = [], []
    windows = _FaceWindows(default_hand_model_path())
    for i, (ms, rgb) in enumerate(iter_frames(demo_clip)):
        if not (120 <= i <= 227 or i >= 236):
            continue
        if i == 236:
            windows = _FaceWindows(default_hand_model_path())  # nothing followed into the clear stretch
        hands = windows.find(rgb, int(ms), real_track.points[i, :, :2])
        covered = np.zeros(len(lips), bool)
        for hand in hands[np.isfinite(hands).all(axis=(1, 2))]:
            covered |= hand_cover(real_track.points[i, lips, :2], hand)
        (over if i <= 227 else clear).append(covered.mean() > 0.3)
    assert np.mean(over) >= 0.8
    assert not any(clear)
