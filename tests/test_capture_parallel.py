"""Parallel tracking: the segment plan, seeking, stitching one person, and the real clip."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from keyshape.capture._parallel import Segment, _same_person, _seed, plan_segments
from keyshape.capture.video import frame_pts, iter_frames


@pytest.mark.parametrize("n, workers, overlap", [(472, 2, 12), (1000, 4, 12), (101, 3, 8), (10_000, 7, 15)])
def test_plan_covers_every_frame_once_with_equal_work(n, workers, overlap):
    segments = plan_segments(5, 5 + n, workers, overlap)
    assert len(segments) == workers
    assert segments[0].first == segments[0].share == 5 and segments[-1].end == 5 + n
    for before, after in itertools.pairwise(segments):
        assert after.share == before.end  # shares tile the range
        assert after.share - after.first == overlap  # each later segment warms up first
    work = [s.end - s.first for s in segments]
    assert max(work) - min(work) <= workers  # equal work, warm-up included


def test_plan_gives_short_inputs_fewer_workers():
    assert plan_segments(0, 30, 4, 12) == [Segment(0, 0, 30)]
    assert len(plan_segments(0, 100, 8, 12)) == 2


def test_seeking_gives_the_frames_decoding_gives(demo_clip):
    pts = frame_pts(demo_clip)
    assert len(pts) == 472 and np.all(np.diff(pts) > 0)
    decoded = list(iter_frames(demo_clip, start=230, end=250))
    sought = list(iter_frames(demo_clip, start=230, end=250, pts=pts))
    assert [ms for ms, _ in sought] == [ms for ms, _ in decoded]
    assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(decoded, sought))


def _faces(centres, width=100.0) -> np.ndarray:
    """(n, 478, 3) points: a square face of ``width`` around each centre (NaN centre: no face)."""
    rng = np.random.default_rng(0)
    offsets = rng.uniform(-width / 2, width / 2, (478, 3))
    offsets[0, 0], offsets[1, 0] = -width / 2, width / 2
    return np.array([np.asarray(c, float)[[0, 1, 1]] * (1, 1, 0) + offsets for c in centres])


def test_same_person_when_the_overlaps_agree():
    before = _faces([(100, 100)] * 12)
    assert _same_person(before, _faces([(103, 101)] * 12), _faces([(105, 100)] * 5), last=None)


def test_other_person_when_the_overlaps_disagree():
    before = _faces([(100, 100)] * 12)
    assert not _same_person(before, _faces([(400, 100)] * 12), _faces([(400, 100)] * 5), last=None)


def test_without_a_shared_face_the_followers_rule_decides():
    nothing = _faces([(np.nan, np.nan)] * 12)
    last = (-20, np.array([100.0, 100.0]), 100.0)  # the earlier segment's face, 20 frames before the share
    near, far = _faces([(150, 100)] * 5), _faces([(500, 100)] * 5)
    assert _same_person(nothing, nothing, near, last)
    assert not _same_person(nothing, nothing, far, last)
    assert _same_person(nothing, nothing, far, None)  # nobody followed yet: any face starts it


def test_a_seeded_follower_starts_from_the_earlier_persons_last_face():
    seed = _seed((-3, np.array([100.0, 100.0]), 100.0))
    assert seed["missing"] == 2 and seed["width"] == 100.0 and np.allclose(seed["last"], [100, 100])
    assert _seed(None) == {}


@pytest.mark.slow
def test_parallel_track_matches_the_sequential_one(demo_clip, real_track):
    from keyshape.capture import track_video

    parallel = track_video(demo_clip, progress=False, workers=2)
    assert parallel.points.shape == real_track.points.shape
    assert np.array_equal(parallel.frame_index, real_track.frame_index)
    assert np.array_equal(parallel.time, real_track.time)
    assert np.array_equal(parallel.valid, real_track.valid)
    iod = np.linalg.norm(real_track.points[:, 33, :2] - real_track.points[:, 263, :2], axis=1)
    error = np.linalg.norm(parallel.points[..., :2] - real_track.points[..., :2], axis=2).mean(axis=1) / iod
    assert np.nanmax(error) < 0.01 and np.nanmean(error) < 0.001  # tracking noise: about 1 % of the IOD
    assert np.nanmax(np.abs(parallel.blendshapes - real_track.blendshapes)) < 0.1
    _same_hands(parallel, real_track)


def _same_hands(parallel, sequential):
    """The hands found in each worker give the sequential visibility, within the tracking noise."""
    from keyshape.schemes import mediapipe_scheme

    # (the face windows follow each track's own landmarks, which differ by the tracking noise)
    assert ((parallel.visibility < 1).any(axis=1) != (sequential.visibility < 1).any(axis=1)).mean() < 0.02
    for part in ("lips", "right_eye", "left_eye"):
        region = np.array(mediapipe_scheme()["contours"][part])
        hidden, hidden_1 = parallel.hidden(region), sequential.hidden(region)
        assert (hidden != hidden_1).mean() < 0.02, part


@pytest.mark.slow
def test_a_hand_over_the_face_at_a_segment_start_is_followed_into_it(demo_clip, real_track):
    """Three workers cut the clip at frames 166 and 320: the first cut falls while the hand covers the
    mouth (58-227), where MediaPipe's palm detector would not find it anew; the hand is followed on
    into the second segment as one process follows it."""
    from keyshape.capture import track_video
    from keyshape.capture._parallel import plan_segments

    assert 58 < plan_segments(0, 472, 3, 12)[1].share < 227
    parallel = track_video(demo_clip, progress=False, workers=3)
    _same_hands(parallel, real_track)
    from keyshape.schemes import mediapipe_scheme

    assert parallel.hidden(np.array(mediapipe_scheme()["contours"]["lips"]))[170:220].all()



def test_workers_not_needed_are_stopped(demo_clip, monkeypatch):
    """The workers start before the video is probed; a clip too short to split stops them."""
    from keyshape.capture import _parallel, track_video

    started, start = [], _parallel.start_workers
    monkeypatch.setattr(_parallel, "start_workers", lambda n: started.extend(start(n)) or list(started))
    short = track_video(demo_clip, end=20, progress=False, workers=3)
    assert short.n_frames == 20 and len(started) == 2
    assert all(process.poll() is not None for process in started)


def test_a_worker_imports_mediapipe_without_its_plotting():
    """MediaPipe's drawing helpers import pyplot (half its import time): deferred in keyshape's
    processes, and still there, for real, when used."""
    import os
    import subprocess
    import sys

    code = ("import sys; from keyshape.capture.mediapipe import preload; preload(); "
            "from mediapipe.tasks.python import vision; vision.FaceLandmarker; "
            "print(type(sys.modules['matplotlib.pyplot']).__name__); "
            "import matplotlib.pyplot as plt; plt.get_backend(); "
            "real = sys.modules['matplotlib.pyplot']; print(type(real).__name__, plt.get_backend is real.get_backend)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "MPLBACKEND": "Agg"}).stdout.split()
    assert out == ["_Deferred", "module", "True"]


def test_a_worker_leaves_ctrl_c_to_the_parent():
    """Ctrl-C in a terminal reaches every process of the group: a worker ignores it (the parent
    ends its workers itself), instead of dying with a KeyboardInterrupt traceback of its own."""
    import signal
    import time

    from keyshape.capture import _parallel

    (worker,) = _parallel.start_workers(1)
    try:
        time.sleep(1.0)  # in its imports, or waiting for its job
        worker.send_signal(signal.SIGINT)
        time.sleep(1.0)
        assert worker.poll() is None, "the worker died of Ctrl-C"
    finally:
        _parallel.stop_workers([worker])
    assert worker.poll() is not None


@pytest.mark.parametrize("block", [1, 3, 1024])
def test_the_last_face_is_found_reading_backwards_block_by_block(block):
    from keyshape.capture._parallel import _last_face

    rng = np.random.default_rng(4)
    points = np.full((50, 478, 3), np.nan, np.float32)
    for row in (2, 17, 31):
        points[row] = rng.uniform(100, 300, (478, 3))
    row, centre, width = _last_face(points, block=block)
    assert row == 31 and np.allclose(centre, _last_face(points[31:32])[1]) and width > 0
    assert _last_face(points[:17], block=block)[0] == 2 and _last_face(points[3:17], block=block) is None
