"""The closed loop on ICT-FaceKit (skipped when the shared data is absent).

ICT-FaceKit animated with known ARKit weights; its 68 landmark vertices, turned by a head motion
and projected to pixels, are the performance; keyshape finds key shapes, solves the weights and
proposes targets on the same face; the animated vertices are compared with the truth, as a
percentage of the mean displacement from neutral (leaving the face neutral scores 100 %).
The code is ``benchmarks/bench_closed_loop.py``; the figures it prints are in docs/auto-targets.md.
"""

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ICT = ROOT.parent / "shared" / "data" / "ict-facekit" / "ICT-FaceKit_FaceXModel_neutral_and_expressions.tar.xz"


def _bench():
    spec = importlib.util.spec_from_file_location("bench_closed_loop", ROOT / "benchmarks" / "bench_closed_loop.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def bench():
    return _bench()


@pytest.fixture(scope="module")
def ict(bench, request, tmp_path_factory):
    if not ICT.is_file():
        pytest.skip(f"{ICT} not present (shared data)")
    from keyshape.io.rig import load_rig

    cache = getattr(request.config, "cache", None)
    base = cache.mkdir("ict-facekit") if cache is not None else tmp_path_factory.mktemp("ict")
    folder = bench.extract_ict(ICT, base)
    return load_rig(folder, unit=0.01), bench.landmark_vertices(folder)


def test_arkit_performance_is_known_and_bounded(bench):
    names = ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L")
    weights = bench.arkit_performance(names, n_frames=300, seed=1)
    assert weights.shape == (300, 6) and weights.min() >= 0 and weights.max() <= 1
    assert weights[:30].max() < 1e-6  # a neutral start
    assert (weights[:, 1] == weights[:, 2]).all()  # both eyes blink together


def test_closed_loop_3d_with_head_motion(ict, bench):
    rig, landmarks = ict
    result = bench.closed_loop(rig, landmarks, dims=3, head_motion=True)
    figures = result.figures
    assert figures["neutral"] == {"face": pytest.approx(100.0), "all": pytest.approx(100.0)}
    # measured 32 % (face area) / 40 % (whole mesh) through the mapping, 52 % / 69 % by transfer
    assert figures["mapping"]["face"] < 45 and figures["mapping"]["all"] < 55
    assert figures["transfer"]["face"] < 62 and figures["transfer"]["all"] < 80


def test_closed_loop_2d(ict, bench):
    rig, landmarks = ict
    result = bench.closed_loop(rig, landmarks, dims=2, head_motion=False)
    figures = result.figures
    # measured 39 % / 46 % through the mapping, 67 % / 77 % by transfer (a 2D track has no depth)
    assert figures["mapping"]["face"] < 50 and figures["mapping"]["all"] < 55
    assert figures["transfer"]["face"] < 75 and figures["transfer"]["all"] < 85
