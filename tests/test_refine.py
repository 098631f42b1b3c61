"""Render and compare (keyshape.targets._refine): the solve and the fit through the keys on data with
known answers; the whole path on a real render runs in test_rendered_loop.py (ICT-FaceKit)."""

import numpy as np
import pytest

from keyshape.containers import Rig, Track, Weights
from keyshape.targets import Mapping, refine_mapping
from keyshape.targets._refine import (
    _smooth_seen,
    fit_in_landmarks,
    fit_through_keys,
    refinable_targets,
    solve_corrections,
)


def _similarity(points, scale, angle, shift):
    c, s = np.cos(angle), np.sin(angle)
    return scale * points @ np.array([[c, -s], [s, c]]).T + shift


def _scene(rng, n_frames=60, n_points=60, n_targets=3):
    """Renders with known landmark responses, and a video made of them by known corrections, a take
    similarity, per-frame head moves and a constant proportion offset."""
    rest = rng.uniform(100, 400, (n_points, 2))
    depth = rng.normal(0, 20, n_points)
    response = rng.normal(0, 15, (n_targets, n_points, 2))  # px per unit weight, in the render
    route = rng.uniform(0.3, 0.6, (n_frames, n_targets))
    truth = rng.uniform(-0.25, 0.25, (n_frames, n_targets))
    truth[rng.permutation(n_frames)[: int(0.7 * n_frames)]] = 0  # mostly at the route's level: the take
    # median of the residual is then the proportions' offset (the level stays with the route)
    base = np.repeat(rest[None], n_frames, axis=0)
    base3 = np.concatenate([base, np.broadcast_to(depth[None, :, None], (n_frames, n_points, 1))], axis=2)
    steps = np.minimum(route + 0.2, 1) - route
    raised = np.stack([base + steps[:, j, None, None] * response[j][None] for j in range(n_targets)])
    moved = base + np.einsum("fj,jpd->fpd", truth, response)
    offset = rng.normal(0, 3, (n_points, 2))  # the actor's and the character's proportions
    shift = rng.normal(0, 2, (n_frames, 1, 2))  # the head's small moves per frame
    video = _similarity(moved + offset, 1.3, 0.1, np.array([40.0, -25.0])) + shift
    return video, base3, raised, route, truth


def test_solve_corrections_recovers_known_target_changes():
    rng = np.random.default_rng(0)
    video, base, raised, route, truth = _scene(rng)
    found, (before, after) = solve_corrections(video, base, raised, route, ridge=1e-6)
    np.testing.assert_allclose(found, truth, atol=0.03)
    assert after < 0.1 * before


def test_solve_corrections_keeps_the_weights_in_range_and_skips_unseen_frames():
    rng = np.random.default_rng(1)
    video, base, raised, route, _ = _scene(rng)
    route[:, 0] = 0.95  # near the top: the corrections cannot push past 1
    video[5] = np.nan  # no face in the video
    base[7, 3] = np.nan  # nor in the render
    found, _ = solve_corrections(video, base, raised, route, ridge=1e-6)
    assert np.isnan(found[5]).all() and np.isnan(found[7]).all()
    seen = np.isfinite(found).all(axis=1)
    assert seen.sum() == len(found) - 2
    total = route[seen] + found[seen]
    assert (total >= -1e-9).all() and (total <= 1 + 1e-9).all()


def test_fit_through_keys_recovers_a_constant_and_gains():
    rng = np.random.default_rng(2)
    weights = rng.uniform(0, 1, (200, 5))
    offset = np.array([0.1, 0.0, 0.3])
    gains = np.maximum(rng.uniform(-0.05, 0.6, (3, 5)), 0.0)
    refined = offset + weights @ gains.T
    refined[10] = np.nan  # a frame without a face is left out
    weights[20, 2] = np.nan  # NaN key weights read as 0, as retarget reads them
    refined[20] = offset + np.nan_to_num(weights[20]) @ gains.T
    found_offset, found_gains = fit_through_keys(refined, weights, ridge=1e-9)
    np.testing.assert_allclose(found_offset, offset, atol=1e-5)
    np.testing.assert_allclose(found_gains, gains, atol=1e-5)
    falling = 0.6 - np.nan_to_num(weights) @ np.full((5, 3), 0.1)  # (200, 3) readings that fall with every key
    _, found_gains = fit_through_keys(falling, weights)
    assert (found_gains >= 0).all()  # a mapping's gains are >= 0 (`retarget --help`)


def test_fit_in_landmarks_recovers_the_rows_from_every_frame_at_once():
    rng = np.random.default_rng(4)
    n_frames, n_points = 80, 60
    keys = rng.uniform(0, 1, (n_frames, 3))
    offset, gains = np.array([0.2, 0.35]), np.array([[0.3, 0.0, 0.1], [0.0, 0.25, 0.2]])
    truth = offset + keys @ gains.T  # (n_frames, 2): what the character should do
    route = truth.copy()
    wrong = rng.permutation(n_frames)[: int(0.3 * n_frames)]
    route[wrong] = rng.uniform(0.1, 0.9, (len(wrong), 2))  # the route is off on some frames
    rest = rng.uniform(100, 400, (n_points, 2))
    response = rng.normal(0, 15, (2, n_points, 2))
    base = np.concatenate([np.repeat(rest[None], n_frames, axis=0), rng.normal(0, 20, (1, n_points, 1)).repeat(
        n_frames, axis=0)], axis=2)
    steps = np.minimum(route + 0.2, 1) - route
    raised = np.stack([base[..., :2] + steps[:, j, None, None] * response[j][None] for j in range(2)])
    moved = base[..., :2] + np.einsum("fj,jpd->fpd", truth - route, response) + rng.normal(0, 3, (n_points, 2))
    video = _similarity(moved, 0.8, -0.05, np.array([10.0, 5.0])) + rng.normal(0, 2, (n_frames, 1, 2))
    found_offset, found_gains = fit_in_landmarks(video, base, raised, route, keys, ridge=1e-9)
    np.testing.assert_allclose(found_offset, offset, atol=0.03)
    np.testing.assert_allclose(found_gains, gains, atol=0.04)


def test_smoothing_ignores_unseen_frames():
    values = np.full((30, 1), 0.4)
    values[10] = 5.0  # a wild value on a frame that was not seen must not leak
    seen = np.ones(30, bool)
    seen[10] = False
    out = _smooth_seen(values, seen, 3.0)
    assert np.isnan(out[10]).all()
    np.testing.assert_allclose(out[seen], 0.4, atol=1e-12)


def test_refinable_targets_reads_every_arkit_spelling():
    names = ["jawOpen", "mouthLowerDown_L", "MouthLowerDownRight", "eyeSquintLeft", "mouthSmile_L", "browOuterUp_R"]
    assert refinable_targets(names) == {"jawOpen": 0, "mouthLowerDown_L": 1, "MouthLowerDownRight": 2,
                                        "eyeSquintLeft": 3, "browOuterUp_R": 5}


def _tiny_case(names, head=True):
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(10, 3))
    rig = Rig(vertices, np.array([[0, 1, 2]]), 0.01 * rng.normal(size=(len(names), 10, 3)), tuple(names))
    mapping = Mapping(np.full((len(names), 2), 0.5), ("a", "b"), tuple(names))
    track = Track(rng.normal(size=(20, 478, 3)), 30.0,
                  head_matrix=np.tile(np.eye(4), (20, 1, 1)) if head else None)
    return rig, mapping, track, Weights(rng.uniform(0, 1, (20, 2)), ("a", "b"), fps=30.0)


@pytest.mark.parametrize("names, head, reason", [
    (("smile", "frown"), True, "none of the targets"),
    (("jawOpen", "mouthSmile_L"), False, "no MediaPipe head pose"),
])
def test_refine_mapping_says_why_it_leaves_the_mapping_alone(names, head, reason):
    rig, mapping, track, weights = _tiny_case(names, head)
    refinement = refine_mapping(mapping, rig, None, track, weights, progress=False)
    assert refinement.mapping is mapping and refinement.targets == ()
    assert reason in refinement.reason


@pytest.mark.parametrize("front, up", [("+z", "+y"), ("-y", "+z"), ("+x", "+y")])
def test_the_renders_face_the_camera_whichever_way_the_character_looks(front, up):
    from keyshape.capture.model_file import canonical_face
    from keyshape.targets._correspond_auto import view_rotation
    from keyshape.targets._refine import _front_turn

    face = canonical_face()[0]
    view = view_rotation(front, up)
    looking = face @ view  # a character whose face looks along `front`: the view turns it back
    tilted = looking @ np.array([[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]])
    for points in (looking, tilted):  # a tilt (e.g. from other proportions) snaps to the same view
        np.testing.assert_allclose(_front_turn(points - points.mean(axis=0)), view, atol=1e-12)


@pytest.mark.slow
@pytest.mark.render
def test_render_and_compare_finds_a_jaw_the_scores_missed(tmp_path):
    """A closed loop on real renders and the real MediaPipe: keyshape's head with a jaw-drop target,
    rendered with the jaw following a key's weight (the "video"); a mapping that holds the jaw still
    at its mean (what the score route gives when the score does not see the jaw) is refined back to
    the jaw's known gain and constant."""
    from keyshape.capture import track_video
    from keyshape.render import frame_points, make_renderer
    from keyshape.render.encode import VideoWriter
    from keyshape.targets import stylised_head

    head = stylised_head()
    v = head.rig.vertices
    below = np.clip((-0.05 - v[:, 1]) / 0.015, 0, 1) * np.exp(-(v[:, 0] / 0.04) ** 2) * (v[:, 2] > -0.02)
    jaw = np.zeros_like(v)
    jaw[:, 1] = -0.012 * below  # the chin and lower lip drop 12 mm at full weight
    rig = Rig(v, head.rig.faces, jaw[None], ("jawOpen",))
    key = 0.5 + 0.5 * np.sin(2 * np.pi * np.arange(72) / 72)  # one key: the mouth opens and closes, slowly
    truth_offset, truth_gain = 0.3, 0.4
    camera = frame_points(v, margin=1.3)
    video = tmp_path / "video.mp4"
    with make_renderer(rig.faces, 512, 512, n_vertices=rig.n_vertices, colours=head.colours) as renderer, \
            VideoWriter(video, 512, 512, 24.0, crf=16) as out:
        for w in key:
            out.write(renderer.render(rig.pose(np.array([[truth_offset + truth_gain * w]]))[0], camera))
    track = track_video(video, progress=False)
    assert track.valid.mean() > 0.95
    still = Mapping(np.zeros((1, 1)), ("k",), ("jawOpen",), offset=np.array([truth_offset + truth_gain * key.mean()]))
    weights = Weights(key[:, None], ("k",), fps=24.0)
    per_frame = refine_mapping(still, rig, head.correspondence(478), track, weights, colours=head.colours,
                               blend=0.0, progress=False)
    assert per_frame.targets == ("jawOpen",) and per_frame.reason == ""
    before, after = per_frame.residual_px
    assert after < 0.7 * before
    gain, offset = per_frame.mapping.matrix[0, 0], per_frame.mapping.offset[0]
    assert gain == pytest.approx(truth_gain, abs=0.15) and offset == pytest.approx(truth_offset, abs=0.12)
    # the default blends in the fit on every frame at once, whose ridge shrinks a gain by about
    # v / (v + 0.1) (v: the key weight's variance, 0.125 here): the same sign, smaller, the same level
    blended = refine_mapping(still, rig, head.correspondence(478), track, weights, colours=head.colours,
                             progress=False).mapping
    assert 0.3 * gain < blended.matrix[0, 0] < gain
    assert blended.offset[0] + blended.matrix[0, 0] * key.mean() == pytest.approx(
        offset + gain * key.mean(), abs=0.05)


def test_the_report_reads_what_render_and_compare_did(tmp_path):
    from keyshape.report._take import _refinement, _refinement_note

    path = tmp_path / "map.json"
    assert _refinement(path) is None  # no file
    path.write_text('{"format": "keyshape-map", "gains": {}}')
    assert _refinement(path) is None  # no entry
    path.write_text('{"format": "keyshape-map", "gains": {}, "refined": {"targets": ["jawOpen"], '
                    '"residual_px": [1.21, 1.05]}}')
    note = _refinement_note(_refinement(path))
    assert "jawOpen" in note and "1.21 px → 1.05 px" in note
    path.write_text('{"refined": {"targets": [], "skipped": "no head pose"}}')
    assert "skipped (no head pose)" in _refinement_note(_refinement(path))


def test_judge_steps_picks_the_candidate_the_landmarks_show():
    from keyshape.targets._refine import judge_steps

    rng = np.random.default_rng(4)
    video, base, raised, route, truth = _scene(rng)
    wrong = route + rng.permutation(truth)  # the right amount of motion, at the wrong frames
    candidates = np.stack([wrong, route + truth, route])  # (3, n_frames, n_targets)
    np.testing.assert_array_equal(judge_steps(video, base, raised, route, candidates), [1, 1, 1])
    # without the right one, the route (no change) explains more than motion at the wrong frames
    np.testing.assert_array_equal(judge_steps(video, base, raised, route, candidates[[0, 2]]), [1, 1, 1])
    held = candidates.copy()
    held[:, :, :] = np.nan  # no frame to judge on: the route as it is
    np.testing.assert_array_equal(judge_steps(video, base, raised, route, held), [1, 1, 1])
