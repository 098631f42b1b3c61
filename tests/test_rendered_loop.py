"""The rendered closed loop on ICT-FaceKit (skipped when the shared data is absent).

ICT-FaceKit driven by MediaPipe's scores of the embedded real clip, rendered by keyshape's renderer,
tracked by the real MediaPipe, run through ``--auto-targets`` (``benchmarks/bench_rendered_loop.py``);
the vertices are scored against the truth beside MediaPipe's own scores on the same video.
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ICT = ROOT.parent / "shared" / "data" / "ict-facekit" / "ICT-FaceKit_FaceXModel_neutral_and_expressions.tar.xz"

pytestmark = pytest.mark.slow


def _bench():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("bench_rendered_loop", ROOT / "benchmarks" / "bench_rendered_loop.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_score_names_reach_split_and_sided_targets():
    bench = _bench()
    table = bench.arkit_to_rig(["eyeBlinkLeft", "browInnerUp", "jawOpen", "_neutral"],
                               ["eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R", "jawOpen"])
    np.testing.assert_array_equal(table, [[1, 0, 0, 0], [0, 0, 0, 0], [0, 1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])


def test_rendered_loop(tmp_path):
    if not ICT.is_file():
        pytest.skip(f"{ICT} not present (shared data)")
    bench = _bench()
    folder = bench.extract_ict(ICT, tmp_path / "ict")
    loops = bench.rendered_loop(folder, tmp_path, second_head=True)
    assert set(loops) == {"ICT", "caricature"}
    for loop in loops.values():
        scores = loop.scores
        assert loop.detection_rate > 0.95
        # measured on ICT: keyshape 18.2 % (face) / 29 % (upper) / 14 % (lower), without render and
        # compare 22.3 / 37 / 17; MediaPipe's own scores 35 / 81 / 18; the oracle mappings 11.2 % (>= 0)
        # and 9.9 % (signed + constant). On the caricature: 17.8 / 29 / 14 (22.5 without), MediaPipe 34 / 78 / 18
        assert scores["keyshape"]["face"] < 20 and scores["keyshape"]["lower"] < 16
        assert scores["keyshape"]["face"] < 0.58 * scores["mediapipe"]["face"]
        # render and compare (the targets the scores miss, refined on the landmarks) gains on both heads;
        # since its gains are kept >= 0 (5f13446) it gains 2.7 points on ICT's face (19.6 against 22.3,
        # measured 2026-12-07 and again with the floor's branch), 4.7 before
        assert scores["keyshape"]["face"] < scores["keyshape, --no-refine"]["face"] - 2
        assert scores["keyshape"]["upper"] < scores["keyshape, --no-refine"]["upper"] - 3
        assert scores["oracle (signed + constant)"]["face"] < 15
        assert scores["mediapipe"]["face"] < 45
    ict, other = loops["ICT"].scores, loops["caricature"].scores
    assert abs(ict["keyshape"]["face"] - other["keyshape"]["face"]) < 3  # the proportions change little
    _gaze_follows_the_eyes(bench, folder, tmp_path)


def _gaze_follows_the_eyes(bench, folder, out):
    """The written animation's gaze targets follow the video's eyes frame by frame (their own channel),
    not a constant read through the keys: measured correlation with the truth 0.76-0.98 per target."""
    from keyshape.io import load_rig, load_track
    from keyshape.io.gltf import read_glb_animation

    rig = load_rig(folder, unit=0.01)
    source = load_track(out / "performance.npz")
    truth = bench.truth_from_scores(source.blendshapes, source.blendshape_names, rig.names)
    written = read_glb_animation(out / "run" / "animation.glb")
    for name in ("eyeLookIn_L", "eyeLookOut_L", "eyeLookIn_R", "eyeLookOut_R"):
        ours = written.weights[:, written.names.index(name)]
        assert ours.std() > 0.02, name
        assert np.corrcoef(ours, truth[:, rig.names.index(name)])[0, 1] > 0.6, name


def test_caricature_changes_the_proportions():
    from keyshape.containers import Rig

    bench = _bench()
    rng = np.random.default_rng(0)
    face = rng.uniform(-0.05, 0.05, (68, 3))  # landmark i at vertex i
    face[36:42] = [0.03, 0.03, 0.05] + rng.uniform(-0.006, 0.006, (6, 3))  # an eye, 12 mm across
    away = rng.uniform(0.4, 0.5, (100, 3))  # far from every feature
    vertices = np.vstack([face, away])
    rig = Rig(vertices, np.array([[0, 1, 2]]), 0.001 * rng.normal(size=(2, len(vertices), 3)), ("a", "b"))
    other = bench.caricature(rig, np.arange(68))
    assert other.deltas.shape == rig.deltas.shape and other.names == rig.names
    spread = [np.linalg.norm(v[36:42] - v[36:42].mean(axis=0), axis=1).mean() for v in (vertices, other.vertices)]
    assert spread[1] > 1.15 * spread[0]  # the eye grows (30 % at its centre)
    np.testing.assert_allclose(other.vertices[68:], away, atol=1e-9)
    np.testing.assert_allclose(other.deltas[:, 68:], rig.deltas[:, 68:], atol=1e-9)


def test_the_eyes_turn_with_the_gaze_weights():
    bench = _bench()
    names = ("eyeLookOut_L", "eyeLookIn_L", "eyeLookUp_L", "eyeLookIn_R", "eyeLookDown_R")
    weights = np.array([[0.0, 0.0, 0.0, 0.0, 0.0],
                        [1.0, 0.0, 0.0, 1.0, 0.0],   # both look to the character's left (+x), 30°
                        [0.0, 0.5, 0.0, 0.0, 0.5]])  # left eye in (toward -x) 15°, right eye down 15°
    turns = bench.eye_rotations(weights, names)
    forward = turns @ np.array([0.0, 0.0, 1.0])  # (frames, eyes, 3): where each pupil points
    np.testing.assert_allclose(forward[0], [[0, 0, 1], [0, 0, 1]], atol=1e-12)
    s30, c30, s15, c15 = np.sin(np.pi / 6), np.cos(np.pi / 6), np.sin(np.pi / 12), np.cos(np.pi / 12)
    np.testing.assert_allclose(forward[1], [[s30, 0, c30], [s30, 0, c30]], atol=1e-12)
    np.testing.assert_allclose(forward[2], [[-s15, 0, c15], [0, -s15, c15]], atol=1e-12)
    rng = np.random.default_rng(1)
    sphere = rng.normal(size=(300, 3))
    sphere = 0.012 * sphere / np.linalg.norm(sphere, axis=1, keepdims=True) + [0.03, 0.036, 0.08]
    np.testing.assert_allclose(bench._sphere_centre(sphere[sphere[:, 2] > 0.075]), [0.03, 0.036, 0.08], atol=1e-9)


RPM = ROOT.parent / "shared" / "data" / "rpm" / "RPM_Template_Mesh_XR.glb"


def test_rendered_loop_on_a_ready_player_me_avatar(tmp_path):
    """The second rig family, held out of every choice of the route: a skinned, textured full body
    (its head's 52 ARKit targets), rendered with its texture colours, tracked, run, scored."""
    if not RPM.is_file():
        pytest.skip(f"{RPM} not present (shared data)")
    bench = _bench()
    loop = bench.rpm_loop(RPM, tmp_path)[RPM.stem]
    scores = loop.scores
    assert loop.detection_rate > 0.95
    raw, plain, ours = scores["mediapipe"], scores["keyshape, --no-refine"], scores["keyshape"]
    # measured (BENCHMARKS.md, issue 35): keyshape 30.0 % (face) / 53.7 % (upper) / 23.9 % (lower), without
    # render and compare 33.5 / 58.4 / 27.1, MediaPipe raw 42.4 / 44.4 / 41.9, less the character's rest
    # reading 34.1 / 41.7 / 32.2. The upper face loses to the peer on the lids, which the avatar's eyeLook
    # targets move and keyshape leaves to its eye nodes (the loop does not score those)
    assert ours["face"] < 0.78 * raw["face"] and ours["lower"] < 0.65 * raw["lower"]
    assert ours["face"] < plain["face"] - 1.5 and ours["lower"] < plain["lower"] - 1.5  # render and compare gains
    assert ours["upper"] < 1.3 * raw["upper"]
    rest = scores["mediapipe less rest"]
    assert rest["face"] < raw["face"] - 4 and rest["lower"] < raw["lower"] - 4 and rest["upper"] < raw["upper"]
    assert scores["oracle (signed + constant)"]["face"] < 15
