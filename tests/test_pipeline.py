"""The method end to end on synthetic takes with known answers, and several takes at once."""

from itertools import pairwise

import numpy as np
import pytest

from keyshape.app import discover_keys, solve_take
from keyshape.containers import Track
from keyshape.datasets import make_performance


@pytest.fixture(scope="module")
def perf():
    return make_performance(n_frames=240, n_landmarks=40, n_keys=4, noise=0.3, random_state=3)


def _pure(perf, frames, regions):
    """Each key frame shows one true key of its region alone (>= 0.6, the others <= 0.1): which."""
    found = []
    for frame, region in zip(frames, regions):
        mine = [k for k, r in enumerate(perf.key_regions) if r == region]
        row = perf.true_weights[frame, mine]
        assert row.max() >= 0.6 and np.sort(row)[-2] <= 0.1, (frame, region, row)
        found.append(mine[int(row.argmax())])
    return found


def _residual(solved, keys, weights=None):
    """RMS distance between the aligned landmarks and their blend of the key shapes."""
    recon = keys.pose(solved.weights.values if weights is None else weights)
    return np.sqrt(np.nanmean(np.sum((recon - solved.aligned.points) ** 2, axis=2)))


def _fits(solved, keys, noise=0.3):
    """Residual at the noise level (neutral, keys and frame are all noisy: ~3 sigma sqrt(3)),
    and far below leaving the face neutral."""
    neutral_only = _residual(solved, keys, np.zeros_like(solved.weights.values))
    return _residual(solved, keys) < 3 * noise * np.sqrt(3) and _residual(solved, keys) < 0.5 * neutral_only


def test_single_take_recovers_the_truth(perf):
    keys = discover_keys(perf.track, regions=perf.regions, n_keys=2, neutral=perf.neutral_frame,
                         stable=perf.stable)
    assert sorted(_pure(perf, keys.frames, keys.key_regions)) == [0, 1, 2, 3]  # one per true shape
    solved = solve_take(perf.track, keys)
    assert (solved.weights.values[perf.track.valid] >= 0).all()
    assert _fits(solved, keys)


def _split(track: Track, cuts) -> list[Track]:
    bounds = [0, *cuts, track.n_frames]
    return [Track(track.points[a:b], track.fps) for a, b in pairwise(bounds)]


def test_one_key_set_across_takes(perf):
    cuts = (120, 180)
    takes = _split(perf.track, cuts)
    names = ["a.npz", "b.npz", "c.npz"]
    keys = discover_keys(takes, regions=perf.regions, n_keys=2, neutral=perf.neutral_frame,
                         stable=perf.stable, take=names)
    starts = dict(zip(names, (0, *cuts)))
    for t, f in zip(keys.takes, keys.frames):
        assert 0 <= f < takes[names.index(t)].n_frames
    global_frames = np.array([starts[t] + f for t, f in zip(keys.takes, keys.frames)])
    assert sorted(_pure(perf, global_frames, keys.key_regions)) == [0, 1, 2, 3]
    assert len(set(keys.takes)) > 1  # the key frames come from several takes
    assert keys.neutral_take == "a.npz" and keys.neutral_frame == perf.neutral_frame
    for take in takes:  # every take solves against the shared key set
        assert _fits(solve_take(take, keys), keys)


def test_takes_must_share_a_landmark_scheme(perf):
    other = Track(perf.track.points[:, :30], perf.track.fps)
    with pytest.raises(ValueError, match=r"b\.npz: has 30 landmarks"):
        discover_keys([perf.track, other], regions="whole", take=["a.npz", "b.npz"])


def test_gaps_are_bridged_or_held(perf):
    points = np.array(perf.track.points)
    points[100:106] = np.nan   # short: bridged by the smooth solve
    points[200:] = np.nan      # long and at the end: held at the neutral
    track = Track(points, perf.track.fps)
    keys = discover_keys(track, regions=perf.regions, n_keys=2, neutral=perf.neutral_frame,
                         stable=perf.stable)
    solved = solve_take(track, keys, smoothness=0.1)
    values = solved.weights.values
    assert np.isfinite(values).all()
    assert (values[200:] == 0).all()
    bridge = values[98:108]  # the gap and a frame on each side
    assert np.abs(np.diff(bridge, 2, axis=0)).max() < 0.1  # a smooth curve across the gap
    assert np.abs(values[100:106] - (values[99] + values[106]) / 2).max() < 0.5  # not dropped to 0
    assert solved.gaps.bridged == ((100, 6),) and solved.gaps.held == ((200, 40),)
    per_frame = solve_take(track, keys, smoothness=0, upper=None).weights.values
    assert np.isnan(per_frame[100:106]).all() and np.isnan(per_frame[200:]).all()
