"""The preview shows hidden parts: hidden landmarks as grey crosses, a hidden part named in the frame."""

from __future__ import annotations

import dataclasses

import numpy as np

from keyshape.render.draw import HIDDEN_COLOUR
from keyshape.render.preview import _LandmarkOverlay

from test_render import decode, synthetic_take

HIDDEN_FRAMES = slice(6, 12)


def _hidden_take():
    """A synthetic take whose second region (half the landmarks) has visibility 0 in frames 6-11."""
    perf, keys, weights, _, rig = synthetic_take(n_frames=12, n_missing=0)
    region = list(keys.regions)[1]
    visibility = np.ones(perf.track.points.shape[:2])
    visibility[HIDDEN_FRAMES, keys.regions[region]] = 0.0
    return perf.track, dataclasses.replace(perf.track, visibility=visibility), keys, weights, rig, region


def _pixels(image, points) -> np.ndarray:
    """(n, 3) int: the colours of ``image`` at the rounded ``points (n, 2)``."""
    xy = np.round(points).astype(int)
    return image[xy[:, 1], xy[:, 0]].astype(int)


def test_hidden_landmarks_are_grey_crosses_and_the_part_is_named():
    plain, seen, keys, _, _, region = _hidden_take()
    height, width = 480, 640
    canvas = np.full((height, width, 3), 32, np.uint8)
    with_vis = _LandmarkOverlay(seen, keys, scale=1.0)
    without = _LandmarkOverlay(plain, keys, scale=1.0)
    # a frame where all is seen draws exactly as a track without visibility
    assert np.array_equal(with_vis(canvas, 2), without(canvas, 2))
    hidden_frame = 8
    a, b = with_vis(canvas, hidden_frame), without(canvas, hidden_frame)
    points = seen.points[hidden_frame, :, :2]
    hidden_ix = np.asarray(keys.regions[region])
    other = np.setdiff1d(np.arange(seen.n_landmarks), hidden_ix)
    inside = (points[:, 1] > 50) & (points[:, 0] < width - 3) & (points[:, 1] < height - 3)  # clear of the captions
    hidden_ix, other = hidden_ix[inside[hidden_ix]], other[inside[other]]
    assert len(hidden_ix) > 10 and len(other) > 10
    # hidden landmarks: grey instead of their region's colour; a cross arm lands 2 px off the centre
    assert (np.abs(_pixels(a, points[hidden_ix]) - HIDDEN_COLOUR).sum(axis=1) == 0).mean() > 0.9
    assert (np.abs(_pixels(b, points[hidden_ix]) - HIDDEN_COLOUR).sum(axis=1) > 60).mean() > 0.9
    assert (np.abs(_pixels(a, points[hidden_ix] + 2) - HIDDEN_COLOUR).sum(axis=1) == 0).mean() > 0.5
    # seen landmarks keep their colour
    assert (np.abs(_pixels(a, points[other]) - _pixels(b, points[other])).sum(axis=1) == 0).mean() > 0.9
    # the part is named under the frame caption: white text there only with visibility
    label = (slice(24, 46), slice(4, 120))
    assert (a[label] > 200).all(axis=2).sum() > 30
    assert not np.array_equal(a[label], b[label])
    assert set(with_vis.hidden) == set(keys.regions)
    assert with_vis.hidden[region][HIDDEN_FRAMES].all() and not with_vis.hidden[region][:6].any()


def test_preview_video_marks_hidden_frames(tmp_path):
    from keyshape.render import render_preview

    plain, seen, keys, weights, rig, _ = _hidden_take()
    videos = [decode(render_preview(track, weights, rig, tmp_path / f"{name}.mp4", keys=keys, height=240,
                                    backend="numpy"))[0] for name, track in (("plain", plain), ("seen", seen))]
    label = (slice(24, 46), slice(4, 120))

    def differs(frame: int) -> float:
        return np.abs(videos[0][frame][label].astype(int) - videos[1][frame][label].astype(int)).mean()

    assert differs(8) > 10 * max(differs(2), 0.5)  # the label "<region> hidden" in hidden frames only
    left = (slice(50, 240), slice(0, 240))
    assert np.abs(videos[0][8][left].astype(int) - videos[1][8][left].astype(int)).max() > 60
