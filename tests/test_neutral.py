"""The neutral frame (alignment/_neutral.py): the least activated frame with the whole face in view,
checked against the median-shape rule, and how sure the choice is."""

from __future__ import annotations

import numpy as np
import pytest

from keyshape.alignment import choose_neutral, choose_neutral_frame, explain_neutral, least_activated
from keyshape.containers import Track
from keyshape.datasets import make_performance
from keyshape.metrics import face_scale


def _scored(perf, seen=None, noise=0.02, seed=0):
    """The take with MediaPipe-like scores: each key's weight plus tracker noise, and gaze scores."""
    rng = np.random.default_rng(seed)
    n = perf.n_frames
    scores = np.clip(np.c_[perf.true_weights, rng.uniform(0, 0.8, (n, 2))] + noise * rng.random((n, perf.n_keys + 2)),
                     0, 1)
    names = (*[f"key{k}" for k in range(perf.n_keys)], "eyeLookInLeft", "eyeLookOutRight")
    t = perf.track
    return Track(t.points, t.fps, t.image_size, scores, names, visibility=seen)


def test_a_rest_frame_is_found():
    perf = make_performance(n_frames=300, n_keys=6, random_state=2)
    track = _scored(perf)
    assert least_activated(_scored(perf, noise=0.0)) == np.flatnonzero(perf.true_weights.max(axis=1) == 0)[0]
    frame = choose_neutral_frame(track, stable=perf.stable)
    assert frame == least_activated(track)
    assert perf.true_weights[frame].max() < 0.01  # a rest frame (the planted one or another at rest)
    choice = explain_neutral(track, frame, stable=perf.stable,
                             scale=face_scale(perf.neutral)[0])
    assert choice.share_below == 0.0 and choice.top[0][1] < 0.3 and choice.confidence in ("high", "medium")
    assert "eyeLook" not in " ".join(name for name, _ in choice.top)  # gaze is not an expression


def test_a_hidden_frame_is_never_the_neutral():
    perf = make_performance(n_frames=300, n_keys=6, random_state=2)
    seen = np.ones(perf.track.points.shape[:2])
    seen[perf.neutral_frame, perf.regions["lower"]] = 0.0  # a hand over the mouth at rest
    track = _scored(perf, seen)
    frame = least_activated(track, regions=perf.regions)
    assert frame != perf.neutral_frame and track.valid[frame]


def test_without_scores_the_median_rule_decides():
    perf = make_performance(n_frames=100, random_state=0)
    assert least_activated(perf.track) is None
    assert choose_neutral_frame(perf.track, stable=perf.stable) == choose_neutral(perf.track, stable=perf.stable)
    choice = explain_neutral(perf.track, 0, stable=perf.stable, scale=face_scale(perf.neutral)[0])
    assert choice.activation is None and "no expression scores" in choice.reason


@pytest.mark.slow
def test_the_embedded_clip_neutral_smiles_least(real_track):
    """The clip never rests: the median-shape frame (248) is a smile; the least activated frame with the
    whole face in view smiles less, and the report says the choice is not sure."""
    from keyshape.schemes import resolve_regions, stable_points

    regions, stable = resolve_regions("upper-lower", 478), stable_points(478)
    frame = choose_neutral_frame(real_track, stable=stable, regions=regions)
    median = choose_neutral(real_track, stable=stable, regions=regions)
    names = real_track.blendshape_names
    smile = [names.index("mouthSmileLeft"), names.index("mouthSmileRight")]
    assert real_track.blendshapes[frame, smile].sum() < real_track.blendshapes[median, smile].sum() - 0.3
    choice = explain_neutral(real_track, frame, stable=stable, scale=face_scale(real_track.points[frame])[0],
                             regions=regions)
    assert choice.confidence != "high" and "never rest" in choice.reason
    assert not (real_track.visibility[frame] < 0.5).any()  # not a frame of the hand over the mouth (58-227)
    assert choice.activation < 0.6 * choice.median_activation


def test_a_separate_rest_clip_is_the_neutral():
    """``neutral=`` a clip of the actor at rest: its median aligned shape is the neutral, its name the
    neutral take, and no key comes from it."""
    from keyshape.app import discover_keys

    perf = make_performance(n_frames=200, n_keys=4, noise=0.3, random_state=4)
    at_rest = perf.track.points[perf.neutral_frame]  # the planted rest frame, in image pixels
    rest = at_rest + np.random.default_rng(1).normal(0.0, 0.3, (12, *at_rest.shape))
    keys = discover_keys(perf.track, regions=perf.regions, n_keys=2, neutral=Track(rest, 30.0), take="take",
                         stable=perf.stable, mirror=False)
    assert keys.neutral_take == "neutral" and set(keys.takes) == {"take"} and 0 <= keys.neutral_frame < 12
    rms = np.sqrt(((keys.neutral - at_rest) ** 2).sum(axis=1).mean())
    assert rms < 0.05 * face_scale(at_rest)[0]
