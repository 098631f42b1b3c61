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


@pytest.mark.slow
def test_mouth_visibility_on_the_labelled_clip(real_track):
    """Mouth (the lips) hidden in >= 90 % of the covered frames, seen in >= 95 % of the clear ones."""
    lips = np.array(mediapipe_scheme()["contours"]["lips"])
    mouth = real_track.visibility[:, lips].mean(axis=1)
    covered, ambiguous = _labelled("mouth", real_track.n_frames)
    assert (mouth[covered & ~ambiguous] < 0.5).mean() >= 0.90
    assert (mouth[~covered & ~ambiguous] >= 0.5).mean() >= 0.95


@pytest.mark.slow
def test_covered_eye_is_hidden_on_the_labelled_clip(real_track):
    eye = np.array(mediapipe_scheme()["contours"]["right_eye"])
    seen = real_track.visibility[:, eye].mean(axis=1)
    covered, ambiguous = _labelled("right_eye", real_track.n_frames)
    assert (seen[covered & ~ambiguous] < 0.5).mean() >= 0.90


@pytest.mark.slow
def test_closed_eyes_are_seen_on_the_labelled_clip(real_track):
    """Eyes shut in laughter (MediaPipe's blink score above 0.5 in about 180 of the 472 frames)
    are not a hand: the clear right eye and the left eye read as seen, blinking or not
    (before the eyes' exemplars were drawn per openness: 83 % and 51 % of the blinking frames)."""
    contours = mediapipe_scheme()["contours"]
    names = list(real_track.blendshape_names)
    blink = np.nan_to_num(real_track.blendshapes[:, [names.index("eyeBlinkLeft"),
                                                      names.index("eyeBlinkRight")]]).mean(axis=1)
    assert (blink > 0.5).sum() > 100
    covered, ambiguous = _labelled("right_eye", real_track.n_frames)
    right = real_track.visibility[:, np.array(contours["right_eye"])].mean(axis=1)
    left = real_track.visibility[:, np.array(contours["left_eye"])].mean(axis=1)
    clear = ~covered & ~ambiguous
    assert (right[clear] >= 0.5).mean() >= 0.95
    assert (right[clear & (blink > 0.5)] >= 0.5).mean() >= 0.9
    assert (left[blink > 0.5] >= 0.5).mean() >= 0.9


@pytest.mark.slow
def test_eye_strata_follow_the_lids(real_track):
    """The strata of the eyes' exemplars split the frames by how open the tracked eyes are."""
    from keyshape.capture.visibility import N_STRATA, _strata, _upper_face

    names = list(real_track.blendshape_names)
    blink = np.nan_to_num(real_track.blendshapes[:, names.index("eyeBlinkLeft")])
    strata = _strata(real_track.points, _upper_face(478))
    assert strata.shape == (real_track.n_frames, len(_upper_face(478))) and (strata == strata[:, :1]).all()
    assert set(np.unique(strata)) == set(range(N_STRATA))
    assert blink[strata[:, 0] == 0].mean() > blink[strata[:, 0] == N_STRATA - 1].mean() + 0.3  # bin 0: the shut eyes
    assert _upper_face(5) is None  # a scheme without named eyes: no strata


@pytest.mark.slow
def test_no_default_key_in_a_covered_frame(real_track):
    from keyshape.app import discover_keys

    keys = discover_keys(real_track)
    mouth, _ = _labelled("mouth", real_track.n_frames)
    eye, _ = _labelled("right_eye", real_track.n_frames)
    for region, frame in zip(keys.key_regions, keys.frames):
        assert not (mouth if region == "lower" else eye)[frame], (region, int(frame))


@pytest.mark.slow
def test_patches_read_while_tracking_give_the_two_pass_visibility(demo_clip, real_track):
    """One decode: the patches read as the frames are tracked score exactly as decoding the video
    twice more after tracking (:func:`estimate_visibility`) does."""
    from keyshape.capture.visibility import estimate_visibility

    np.testing.assert_array_equal(real_track.visibility, estimate_visibility(demo_clip, real_track.points))


def test_spooled_patches_read_back_by_slices_and_rows(tmp_path):
    from keyshape.capture._spool import PATCH_SHAPE, Patches, Spool
    from keyshape.capture._track import _Frame

    rng = np.random.default_rng(0)
    spools, patches = [], []
    for k in range(2):
        (tmp_path / str(k)).mkdir()
        with Spool(tmp_path / str(k)) as spool:
            for _ in range(5):
                frame = rng.random(PATCH_SHAPE, dtype=np.float32)
                spool.append(_Frame(np.zeros((478, 3), np.float32), np.zeros(52, np.float32),
                                    np.eye(4, dtype=np.float32), patches=frame))
                patches.append(frame)
            spool.append(_Frame(*(np.full(s, np.nan, np.float32) for s in ((478, 3), 52, (4, 4)))))
            patches.append(np.full(PATCH_SHAPE, np.nan, np.float32))
        spools.append(spool)
    np.testing.assert_array_equal(spools[0].patches()[1:4], np.stack(patches[1:4]))
    joined = Patches([(tmp_path / "0", 2, 4), (tmp_path / "1", 1, 5)])  # rows 2.. of one, 1.. of the other
    expected = np.stack(patches[2:6] + patches[7:12])
    assert joined.shape == (9, *PATCH_SHAPE)
    np.testing.assert_array_equal(joined[:], expected)
    np.testing.assert_array_equal(joined[np.array([0, 3, 4, 8])], expected[[0, 3, 4, 8]])
    np.testing.assert_array_equal(joined[3:7], expected[3:7])
    assert joined[5:5].shape == (0, *PATCH_SHAPE)


@pytest.mark.slow
def test_without_room_for_the_patches_the_video_is_decoded_again(demo_clip, monkeypatch):
    from keyshape.capture import _track, track_video

    kept = track_video(demo_clip, end=60, progress=False)
    monkeypatch.setattr(_track, "room_for_patches", lambda folder, n_frames: False)
    again = track_video(demo_clip, end=60, progress=False)
    np.testing.assert_array_equal(again.points, kept.points)
    np.testing.assert_array_equal(again.visibility, kept.visibility)
