"""Key-shape selection: real frames, planted extremes, SPA quality, strong keys under a bound,
automatic K, determinism, validation, long takes (a pool of candidates)."""

import numpy as np
import pytest

from keyshape.alignment import align
from keyshape.containers import KeyShapes, Track
from keyshape.datasets import make_performance
from keyshape.exceptions import InputError
from keyshape.keyshapes import MAX_CANDIDATES, MAX_KEYS, METHODS, KChoice, _select, choose_n_keys, find_keyshapes
from keyshape.keyshapes import _search as keyshapes
from keyshape.metrics import face_scale, reconstruction_error


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


@pytest.mark.parametrize("upper", [None, 1.0])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("n_keys", [4, 10])
def test_spa_error_is_no_worse_than_the_papers_methods(seed, n_keys, upper):
    perf, aligned, neutral = _aligned(n_frames=200, n_keys=12, noise=0.5, random_state=seed)
    errors = {}
    for method in METHODS:
        keys = find_keyshapes(aligned, regions=perf.regions, n_keys=n_keys, method=method, neutral_frame=neutral,
                              upper=upper)
        errors[method] = reconstruction_error(aligned, keys, upper=upper)
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
    with pytest.raises(InputError, match="upper must be None or a number > 0; got 0"):
        find_keyshapes(aligned, regions=perf.regions, neutral_frame=neutral, upper=0)
    with pytest.raises(InputError, match="n_keys must be an int, a dict of region -> int, or 'auto'; got 'all'"):
        find_keyshapes(aligned, regions=perf.regions, n_keys="all", neutral_frame=neutral)
    with pytest.raises(InputError, match="max_error must be a number > 0"):
        choose_n_keys(aligned, regions=perf.regions, neutral_frame=neutral, max_error=0)
    with pytest.raises(InputError, match="max_keys must be an int >= 1; got 0"):
        find_keyshapes(aligned, regions=perf.regions, n_keys="auto", neutral_frame=neutral, max_keys=0)


# --------------------------------------------------------------------------- strong keys under a bound


def _tiny_key_data():
    """Rows: 150 faint moves along e3 (0.02..0.2), 20 strong frames near e1 and 20 near e2, and
    a planted faint frame 0.2·e3 (the last row). The faint frame explains every faint move
    exactly at a weight <= 1, so the reconstruction error alone makes it the third key."""
    rng = np.random.default_rng(0)
    e1, e2, e3 = np.eye(6)[:3]
    faint = rng.uniform(0.02, 0.2, (150, 1)) * e3
    strong = np.vstack([rng.uniform(0.7, 1.0, (20, 1)) * e1, rng.uniform(0.7, 1.0, (20, 1)) * e2])
    X = np.vstack([faint, strong, 0.2 * e3])
    return X + rng.normal(0.0, 1e-3, X.shape)


def test_without_the_strength_floor_a_bounded_fit_would_pick_a_faint_frame():
    X = _tiny_key_data()
    strength = np.linalg.norm(X, axis=1)
    faint = strength < _select.MIN_STRENGTH * np.quantile(strength, 0.95)
    assert faint[_select.spa(X, 3, upper=1.0, min_strength=0.0)].any()  # the error alone prefers it


@pytest.mark.parametrize("upper", [1.0, None])
def test_spa_never_picks_a_faint_frame(upper):
    X = _tiny_key_data()
    strength = np.linalg.norm(X, axis=1)
    floor = _select.MIN_STRENGTH * np.quantile(strength, 0.95)
    for n_keys in (1, 2, 3, 4):
        rows = _select.spa(X, n_keys, upper=upper)
        assert (strength[rows] >= floor).all(), (n_keys, rows)


def _faint_key_performance():
    """Key 0 (upper) only ever moves faintly (weight <= 0.08; frame 230 is key 0 alone at 0.08),
    key 2 (upper) strongly: the error alone would make frame 230 an upper key."""
    perf = make_performance(n_frames=240, n_keys=4, noise=0.0, random_state=2)
    rng = np.random.default_rng(2)
    weights = np.zeros((240, 4))
    weights[1:100, 0] = rng.uniform(0.01, 0.08, 99)
    weights[100:200, 2] = rng.uniform(0.3, 1.0, 100)
    weights[200:240, [1, 3]] = rng.uniform(0.0, 1.0, (40, 2))
    weights[230] = [0.08, 0.0, 0.0, 0.0]
    points = perf.neutral + np.einsum("fk,kpd->fpd", weights, perf.key_deltas)
    return perf, Track(points + rng.normal(0.0, 0.01, points.shape), 30.0)


@pytest.mark.parametrize("upper", [1.0, None])
def test_keys_are_strong_frames_not_the_planted_faint_one(upper, monkeypatch):
    perf, aligned = _faint_key_performance()
    keys = find_keyshapes(aligned, regions=perf.regions, n_keys=2, neutral_frame=0, upper=upper)
    assert 230 not in keys.frames
    for region, lm in perf.regions.items():
        strength = np.linalg.norm((aligned.points[1:, lm] - aligned.points[0, lm]).reshape(239, -1), axis=1)
        floor = _select.MIN_STRENGTH * np.quantile(strength, 0.95)
        assert (strength[keys.frames[keys.keys_of(region)] - 1] >= floor).all(), region
    # the same selection without the strength floor takes the faint frame: the floor is what avoids it
    monkeypatch.setattr(_select, "MIN_STRENGTH", 0.0)
    assert 230 in find_keyshapes(aligned, regions=perf.regions, n_keys=2, neutral_frame=0, upper=upper).frames


@pytest.mark.parametrize("upper", [None, 1.0])
def test_keys_are_strong_on_a_noisy_performance(noisy, upper):
    perf, aligned, neutral = noisy
    keys = find_keyshapes(aligned, regions=perf.regions, n_keys=8, neutral_frame=neutral, upper=upper)
    valid = np.flatnonzero(aligned.valid)
    valid = valid[valid != neutral]
    for region, lm in perf.regions.items():
        strength = np.linalg.norm(aligned.points[:, lm] - aligned.points[neutral, lm], axis=(1, 2))
        floor = _select.MIN_STRENGTH * np.quantile(strength[valid], 0.95)
        assert (strength[keys.frames[keys.keys_of(region)]] >= floor).all()


def test_bounded_weights_reach_the_keys_at_most_once():
    """With upper=1 every frame's fit stays within the bound and spa's error is that of the bound."""
    perf, aligned, neutral = _aligned(n_frames=200, n_keys=8, noise=0.3, random_state=4)
    keys = find_keyshapes(aligned, regions=perf.regions, n_keys=4, neutral_frame=neutral, upper=1.0)
    bounded = reconstruction_error(aligned, keys, upper=1.0)
    free = reconstruction_error(aligned, keys)
    assert all(free[r] <= bounded[r] + 1e-12 for r in perf.regions)


# --------------------------------------------------------------------------- automatic K


@pytest.mark.parametrize("upper", [1.0, None])
@pytest.mark.parametrize("n_planted", [4, 6, 10])
def test_auto_k_finds_the_planted_number_of_keys(n_planted, upper):
    perf = make_performance(n_frames=240, n_keys=n_planted, noise=0.0, random_state=n_planted)
    aligned = perf.track.with_points(perf.canonical)
    choices = choose_n_keys(aligned, regions=perf.regions, neutral_frame=perf.neutral_frame,
                            max_error=0.05, upper=upper)
    planted = {r: perf.key_regions.count(r) for r in perf.regions}
    assert {r: c.k for r, c in choices.items()} == planted
    assert all(isinstance(c, KChoice) and c.error < 0.05 for c in choices.values())
    # one key fewer does not reach the target
    fewer = find_keyshapes(aligned, regions=perf.regions, n_keys={r: k - 1 for r, k in planted.items()},
                           neutral_frame=perf.neutral_frame, upper=upper)
    scale, _ = face_scale(perf.canonical[perf.neutral_frame])
    errors = reconstruction_error(aligned, fewer, upper=upper)
    # reconstruction_error averages over the same valid frames: convert to % of the face scale
    assert all(100 * e / scale >= 0.05 for e in errors.values())


def test_auto_keys_are_the_keys_of_that_count():
    perf, aligned, neutral = _aligned(n_frames=200, n_keys=8, noise=0.3, random_state=5)
    choices = choose_n_keys(aligned, regions=perf.regions, neutral_frame=neutral, max_error=1.0)
    auto = find_keyshapes(aligned, regions=perf.regions, n_keys="auto", max_error=1.0, neutral_frame=neutral)
    fixed = find_keyshapes(aligned, regions=perf.regions, n_keys={r: c.k for r, c in choices.items()},
                           neutral_frame=neutral)
    np.testing.assert_array_equal(auto.frames, fixed.frames)
    assert auto.names == fixed.names
    scale, _ = face_scale(aligned.points[neutral])
    reached = reconstruction_error(aligned, auto, upper=1.0)
    for region, choice in choices.items():
        assert choice.error == pytest.approx(100 * reached[region] / scale, rel=1e-9)
        assert choice.error < 1.0


def test_auto_k_stops_at_the_cap_when_the_target_is_out_of_reach(noisy):
    perf, aligned, neutral = noisy
    choices = choose_n_keys(aligned, regions=perf.regions, neutral_frame=neutral, max_error=1e-6, max_keys=5)
    assert all(c.k == 5 and c.error > 1e-6 for c in choices.values())
    assert MAX_KEYS == 24


@pytest.mark.parametrize("method", ["spread", "hull"])
def test_auto_k_works_for_the_papers_methods(method):
    perf = make_performance(n_frames=200, n_keys=4, noise=0.0, random_state=0)
    aligned = perf.track.with_points(perf.canonical)
    choices = choose_n_keys(aligned, regions=perf.regions, neutral_frame=perf.neutral_frame, method=method,
                            max_error=0.05)
    assert all(1 <= c.k <= MAX_KEYS and (c.error < 0.05 or c.k == MAX_KEYS) for c in choices.values())


# --------------------------------------------------------------------------- long takes: a pool of candidates


def test_pool_is_every_row_up_to_the_limit():
    X = np.random.default_rng(0).normal(size=(300, 6))
    pool = _select.pool(X, 300)
    assert pool.whole and pool.X is X and pool.axes is None and pool.q95 is None
    np.testing.assert_array_equal(pool.rows, np.arange(300))


@pytest.fixture(scope="module")
def long_region():
    """``(X, pool)``: the upper region of 3,000 noisy frames, a pool of 400 of its rows."""
    perf, aligned, neutral = _aligned(n_frames=3000, n_keys=16, noise=0.3, random_state=11)
    landmarks = perf.regions["upper"]
    X = (np.delete(aligned.points, neutral, axis=0)[:, landmarks] - aligned.points[neutral, landmarks])
    X = X.reshape(len(X), -1)
    return X, _select.pool(X, 400)


def test_pool_beyond_the_limit_is_bounded_and_knows_all_rows(long_region):
    X, pool = long_region
    assert not pool.whole and pool.rows.size == 400 and (np.diff(pool.rows) > 0).all()
    np.testing.assert_array_equal(pool.X, X[pool.rows])
    assert pool.q95 == pytest.approx(np.quantile(np.linalg.norm(X, axis=1), 0.95))
    axes = _select.principal_axes(X)  # those of every row, up to sign
    assert pool.axes.shape == axes.shape
    np.testing.assert_allclose(np.abs((pool.axes[:3] * axes[:3]).sum(axis=1)), 1.0, atol=1e-8)
    strongest = np.argsort(np.linalg.norm(X, axis=1))[-20:]
    assert np.isin(strongest, pool.rows).all()  # farthest points from the neutral come first


@pytest.mark.parametrize("kernel", [_select.spread, _select.hull], ids=["spread", "hull"])
def test_the_papers_methods_pick_on_the_pool_what_they_pick_on_all_rows(long_region, kernel):
    X, pool = long_region
    for k in (1, 4, 9, 16, 24, 30):
        np.testing.assert_array_equal(pool.rows[kernel(pool.X, k, axes=pool.axes)], kernel(X, k, axes=pool.axes))


def test_exact_error_of_all_rows_by_blocks(long_region, monkeypatch):
    X, pool = long_region
    keys = pool.rows[_select.spa(pool.X, 5, upper=1.0, axes=pool.axes, q95=pool.q95)]
    whole = _select.Objective(X, 1.0)(keys)
    monkeypatch.setattr(_select, "_BLOCK_ROWS", 700)
    assert _select.squared_error(X, keys, 1.0) == pytest.approx(whole, rel=1e-10)


@pytest.mark.parametrize("method", METHODS)
def test_a_limit_below_the_frames_searches_a_pool_of_them(noisy, method, monkeypatch):
    perf, aligned, neutral = noisy  # 191 candidate frames
    every = find_keyshapes(aligned, regions=perf.regions, n_keys=4, method=method, neutral_frame=neutral)
    monkeypatch.setattr(keyshapes, "MAX_CANDIDATES", 100)
    pooled = find_keyshapes(aligned, regions=perf.regions, n_keys=4, method=method, neutral_frame=neutral)
    assert neutral not in pooled.frames and aligned.valid[pooled.frames].all()
    for region in perf.regions:
        frames = pooled.frames[pooled.keys_of(region)]
        assert len(set(frames.tolist())) == 4
        if method != "spa":  # the paper's picks are in the pool
            assert sorted(frames) == sorted(every.frames[every.keys_of(region)])
    errors, reference = (reconstruction_error(aligned, keys, upper=1.0) for keys in (pooled, every))
    assert all(errors[r] <= 1.1 * reference[r] for r in perf.regions), (errors, reference)


def test_auto_k_beyond_the_limit_measures_every_frame(noisy, monkeypatch):
    perf, aligned, neutral = noisy
    monkeypatch.setattr(keyshapes, "MAX_CANDIDATES", 100)
    choices = choose_n_keys(aligned, regions=perf.regions, neutral_frame=neutral, max_error=3.0)
    auto = find_keyshapes(aligned, regions=perf.regions, n_keys="auto", max_error=3.0, neutral_frame=neutral)
    fixed = find_keyshapes(aligned, regions=perf.regions, n_keys={r: c.k for r, c in choices.items()},
                           neutral_frame=neutral)
    np.testing.assert_array_equal(auto.frames, fixed.frames)
    scale, _ = face_scale(aligned.points[neutral])
    reached = reconstruction_error(aligned, auto, upper=1.0)
    for region, choice in choices.items():
        assert choice.error == pytest.approx(100 * reached[region] / scale, rel=1e-9) and choice.error < 3.0


def test_long_take_keys_reconstruct_as_well_as_a_search_of_every_frame_on_a_short_one():
    """20,000 frames, keys searched among a pool of MAX_CANDIDATES, against 1,500 frames of the
    same rig, all candidates: both find (nearly all) the planted extremes, with the same error."""
    assert 1500 < MAX_CANDIDATES < 20000
    errors, found = {}, {}
    for n_frames in (1500, 20000):
        perf, aligned, neutral = _aligned(n_frames=n_frames, n_keys=12, noise=0.3, random_state=5)
        keys = find_keyshapes(aligned, regions=perf.regions, n_keys=6, neutral_frame=neutral)
        assert len(set(keys.frames.tolist())) == 12 and neutral not in keys.frames
        errors[n_frames] = reconstruction_error(aligned, keys, upper=1.0)
        found[n_frames] = int(np.isin(perf.extreme_frames, keys.frames).sum())
    assert found[1500] == 12 and found[20000] >= 9, found
    for region, short in errors[1500].items():
        assert errors[20000][region] <= 1.05 * short, (region, errors)


def test_the_keys_help_states_the_limit(capsys):
    from keyshape.cli import main

    with pytest.raises(SystemExit):
        main(["keys", "--help"])
    assert f"more than {MAX_CANDIDATES} frames" in " ".join(capsys.readouterr().out.split())
