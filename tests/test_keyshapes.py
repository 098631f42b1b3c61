"""Key-shape selection: real frames, planted extremes, SPA quality, determinism, validation."""

import numpy as np
import pytest

from keyshape.align import align
from keyshape.containers import KeyShapes
from keyshape.datasets import make_performance
from keyshape.exceptions import InputError
from keyshape.keyshapes import METHODS, find_keyshapes
from keyshape.metrics import reconstruction_error


def _aligned(**kwargs):
    perf = make_performance(**kwargs)
    aligned, _ = align(perf.track, reference=perf.neutral, stable=perf.stable)
    return perf, aligned, perf.neutral_frame


@pytest.fixture(scope="module")
def noisy():
    return _aligned(n_frames=200, n_keys=6, noise=0.5, n_missing=8, random_state=1)


@pytest.mark.parametrize("method", METHODS)
def test_keys_are_real_distinct_frames_never_neutral_or_nan(noisy, method):
    perf, aligned, neutral = noisy
    keys = find_keyshapes(aligned, regions=perf.regions, n_keys=5, method=method, neutral_frame=neutral)
    assert isinstance(keys, KeyShapes) and keys.n_keys == 10 and keys.method == method
    for region in perf.regions:
        frames = keys.frames[keys.keys_of(region)]
        assert len(set(frames.tolist())) == len(frames) == 5
    assert neutral not in keys.frames and perf.track.valid[keys.frames].all()
    assert keys.names == tuple(f"{r}_{i:02d}" for r in ("upper", "lower") for i in range(5))
    np.testing.assert_array_equal(keys.neutral, aligned.points[neutral])


@pytest.mark.parametrize("method", METHODS)
def test_deltas_are_key_minus_neutral_inside_the_region_only(noisy, method):
    perf, aligned, neutral = noisy
    keys = find_keyshapes(
        aligned, regions=perf.regions, n_keys={"upper": 2, "lower": 3}, method=method,
        neutral_frame=neutral, stable=perf.stable,
    )
    np.testing.assert_array_equal(keys.stable, perf.stable)
    for k, (frame, region) in enumerate(zip(keys.frames, keys.key_regions)):
        inside = keys.regions[region]
        outside = np.setdiff1d(np.arange(aligned.n_landmarks), inside)
        np.testing.assert_allclose(keys.deltas[k, inside], aligned.points[frame, inside] - keys.neutral[inside])
        assert not keys.deltas[k, outside].any()


@pytest.mark.parametrize("method", ["spa", "hull"])
def test_finds_the_planted_extremes(method):
    perf, aligned, neutral = _aligned(n_frames=200, n_keys=6, noise=0.02, random_state=3)
    keys = find_keyshapes(aligned, regions=perf.regions, n_keys=3, method=method, neutral_frame=neutral)
    assert sorted(keys.frames.tolist()) == sorted(perf.extreme_frames.tolist())


def test_spread_finds_extremes_along_the_components():
    perf, aligned, neutral = _aligned(n_frames=200, n_keys=2, noise=0.0, random_state=0)
    keys = find_keyshapes(aligned, regions=perf.regions, n_keys=1, method="spread", neutral_frame=neutral)
    # One key per region, one-dimensional motion: the largest |projection| is the planted extreme.
    assert sorted(keys.frames.tolist()) == sorted(perf.extreme_frames.tolist())


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("n_keys", [4, 10])
def test_spa_error_is_no_worse_than_the_papers_methods(seed, n_keys):
    perf, aligned, neutral = _aligned(n_frames=200, n_keys=12, noise=0.5, random_state=seed)
    errors = {}
    for method in METHODS:
        keys = find_keyshapes(aligned, regions=perf.regions, n_keys=n_keys, method=method, neutral_frame=neutral)
        errors[method] = reconstruction_error(aligned, keys)
    for region in perf.regions:
        assert errors["spa"][region] <= min(errors["spread"][region], errors["hull"][region]) + 1e-9


@pytest.mark.parametrize("method", METHODS)
def test_deterministic(noisy, method):
    perf, aligned, neutral = noisy
    runs = [
        find_keyshapes(aligned, regions=perf.regions, n_keys=4, method=method, neutral_frame=neutral)
        for _ in range(2)
    ]
    np.testing.assert_array_equal(runs[0].frames, runs[1].frames)


def test_whole_face_region_and_zero_keys(noisy):
    perf, aligned, neutral = noisy
    whole = {"whole": np.arange(aligned.n_landmarks)}
    keys = find_keyshapes(aligned, regions=whole, n_keys=3, neutral_frame=neutral)
    assert keys.names == ("whole_00", "whole_01", "whole_02")
    keys = find_keyshapes(aligned, regions=perf.regions, n_keys={"upper": 0, "lower": 2}, neutral_frame=neutral)
    assert keys.key_regions == ("lower", "lower")


def test_validation_messages(noisy):
    perf, aligned, neutral = noisy
    nan_frame = int(np.flatnonzero(~aligned.valid)[0])
    with pytest.raises(InputError, match="method must be one of"):
        find_keyshapes(aligned, regions=perf.regions, method="pca", neutral_frame=neutral)
    with pytest.raises(InputError, match="has no face"):
        find_keyshapes(aligned, regions=perf.regions, neutral_frame=nan_frame)
    with pytest.raises(InputError, match="indices must lie in"):
        find_keyshapes(aligned, regions={"bad": np.array([0, 400])}, neutral_frame=neutral)
    with pytest.raises(InputError, match="no count for regions"):
        find_keyshapes(aligned, regions=perf.regions, n_keys={"upper": 2}, neutral_frame=neutral)
    with pytest.raises(InputError, match="only 191 valid frames"):
        find_keyshapes(aligned, regions=perf.regions, n_keys=500, neutral_frame=neutral)


def test_reconstruction_error_is_zero_for_the_true_rig_and_weights():
    perf = make_performance(n_frames=60, n_keys=4, noise=0.0, n_missing=3)
    truth = KeyShapes(
        neutral=perf.neutral, deltas=perf.key_deltas, names=("a", "b", "c", "d"),
        frames=perf.extreme_frames, key_regions=perf.key_regions, regions=perf.regions,
    )
    aligned = perf.track.with_points(np.where(perf.track.valid[:, None, None], perf.canonical, np.nan))
    for weights in (None, perf.true_weights):
        errors = reconstruction_error(aligned, truth, weights=weights)
        assert set(errors) == {"upper", "lower"} and max(errors.values()) < 1e-9
    shifted = reconstruction_error(aligned, truth, weights=perf.true_weights + 0.1)
    assert min(shifted.values()) > 0.1


def test_nonnegative_fit_matches_scipy_nnls():
    from scipy.optimize import nnls

    from keyshape.metrics import nonnegative_fit

    rng = np.random.default_rng(5)
    bases, targets = rng.normal(size=(6, 40)), rng.normal(size=(12, 40))
    fitted = nonnegative_fit(targets, bases)
    expected = np.stack([nnls(bases.T, t)[0] for t in targets])
    np.testing.assert_allclose(fitted, expected, atol=1e-8)
    assert (fitted >= 0).all()


@pytest.mark.slow
def test_spa_beats_the_papers_methods_on_real_footage(real_track):
    """Issue 3: on the real clip, spa has the lowest error at every K >= 4."""
    from keyshape.align import choose_neutral
    from keyshape.schemes import resolve_regions, stable_points

    regions = resolve_regions("upper-lower", real_track.n_landmarks)
    stable = stable_points(real_track.n_landmarks)
    neutral = choose_neutral(real_track, stable=stable, regions=regions)
    aligned, _ = align(real_track, reference=neutral, stable=stable)
    for n_keys in (4, 8, 16, 30):
        errors = {
            method: reconstruction_error(
                aligned, find_keyshapes(aligned, regions=regions, n_keys=n_keys, method=method, neutral_frame=neutral)
            )
            for method in METHODS
        }
        for region in regions:
            assert errors["spa"][region] < min(errors["spread"][region], errors["hull"][region]), (n_keys, errors)
