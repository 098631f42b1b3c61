"""``keyshape solve`` streamed over chunks of frames: the same weights as the whole-take path."""

import numpy as np
import pytest

from keyshape.alignment import align
from keyshape.app import solve_take, solve_track_file
from keyshape.cli import main
from keyshape.containers import KeyShapes, Track
from keyshape.datasets import make_performance
from keyshape.decompose import GramTake, solve_weights
from keyshape.exceptions import InputError
from keyshape.io import load_track, load_weights_csv, open_track, save_track
from keyshape.io.track import write_track_arrays
from keyshape.io.validate import check_track_arrays

TOL = 1e-6  # the solvers' certificate (1e-7 relative objective gap) keeps weights this close


@pytest.fixture(scope="module")
def perf():
    return make_performance(n_frames=600, n_landmarks=40, n_keys=6, noise=0.3, n_missing=20, random_state=4)


@pytest.fixture(scope="module")
def keys(perf):
    names = [f"k{i}" for i in range(perf.n_keys)]
    return KeyShapes(perf.neutral, perf.key_deltas, names, perf.extreme_frames, perf.key_regions, perf.regions,
                     stable=perf.stable)


def _with_gaps(track: Track) -> Track:
    points = np.array(track.points)
    points[100:106] = np.nan  # bridged (6 frames at 30 fps < 0.5 s)
    points[300:340] = np.nan  # held at neutral
    points[-3:] = np.nan  # held at the end
    return Track(points.astype(np.float32), track.fps, frame_index=np.arange(track.n_frames) + 7)


@pytest.mark.parametrize("smoothness, upper, convex", [(0.1, 1.0, False), (0.0, 1.0, False), (0.0, None, False),
                                                       (0.5, 1.0, True)])
@pytest.mark.parametrize("chunk", [64, 4096])
def test_solve_track_file_matches_solve_take(perf, keys, tmp_path, smoothness, upper, convex, chunk):
    track = _with_gaps(perf.track)
    path = save_track(track, tmp_path / "take.npz")
    whole = solve_take(load_track(path), keys, smoothness=smoothness, upper=upper, convex=convex)
    streamed = solve_track_file(path, keys, smoothness=smoothness, upper=upper, convex=convex, chunk=chunk)
    assert streamed.gaps == whole.gaps
    np.testing.assert_array_equal(np.isnan(streamed.weights.values), np.isnan(whole.weights.values))
    np.testing.assert_allclose(streamed.weights.values, whole.weights.values, atol=TOL, rtol=0)
    np.testing.assert_array_equal(streamed.weights.frame_index, whole.weights.frame_index)
    np.testing.assert_array_equal(streamed.weights.time, whole.weights.time)
    assert streamed.weights.names == whole.weights.names and streamed.weights.fps == whole.weights.fps


def test_gram_take_matches_solve_weights(perf, keys):
    aligned = align(perf.track, reference=keys.neutral, stable=perf.stable)[0]
    take = GramTake(keys, aligned.n_frames)
    for lo in range(0, aligned.n_frames, 50):
        take.add(lo, aligned.points[lo : lo + 50][:, take.landmarks])
    for options in ({"smoothness": 0.1, "upper": 1.0}, {"smoothness": 0.0}):
        expected = solve_weights(aligned[120:480], keys, **options).values
        np.testing.assert_allclose(take.solve(120, 480, **options), expected, atol=TOL, rtol=0)


def _hidden(perf, n_missing=True):
    """The take with a hand over the mouth (visibility 0.2, then 0: the region gone for a while) and
    a few percent hidden everywhere, as real tracks read; frames without a face and gaps too."""
    rng = np.random.default_rng(5)
    seen = np.clip(1.0 - rng.exponential(0.03, perf.track.points.shape[:2]), 0.0, 1.0)
    seen[50:80, perf.regions["lower"]] = 0.2
    seen[60:70, perf.regions["lower"]] = 0.0
    track = _with_gaps(perf.track) if n_missing else perf.track
    return Track(track.points, track.fps, frame_index=track.frame_index, visibility=seen)


@pytest.mark.parametrize("chunk", [64, 4096])
def test_hidden_landmarks_are_streamed_in_weighted_gram_form(perf, keys, tmp_path, chunk):
    """A take with visibility is streamed (no whole-take copy) and gives solve_take's weights."""
    path = save_track(_hidden(perf), tmp_path / "hidden.npz")
    whole = solve_take(load_track(path), keys)  # visibility is stored as float32
    streamed = solve_track_file(path, keys, chunk=chunk)
    assert streamed.gaps == whole.gaps
    np.testing.assert_array_equal(np.isnan(streamed.weights.values), np.isnan(whole.weights.values))
    np.testing.assert_allclose(streamed.weights.values, whole.weights.values, atol=TOL, rtol=0)
    unweighted = solve_take(Track(load_track(path).points, perf.track.fps, frame_index=whole.weights.frame_index), keys)
    assert np.nanmax(np.abs(unweighted.weights.values - whole.weights.values)) > 100 * TOL  # the visibility counts


@pytest.mark.parametrize("upper", [1.0, None])
def test_hidden_landmarks_without_smoothing_are_streamed(perf, keys, tmp_path, upper):
    """Every frame on its own weighted Gram matrix: solve_take's per-frame weights (NaN where the
    region is gone, then filled as there)."""
    path = save_track(_hidden(perf), tmp_path / "hidden.npz")
    whole = solve_take(load_track(path), keys, smoothness=0.0, upper=upper)
    streamed = solve_track_file(path, keys, smoothness=0.0, upper=upper)
    np.testing.assert_array_equal(np.isnan(streamed.weights.values), np.isnan(whole.weights.values))
    np.testing.assert_allclose(streamed.weights.values, whole.weights.values, atol=1e-9, rtol=0)


def test_hidden_landmarks_with_convex_take_the_whole_take_path(perf, keys, tmp_path, monkeypatch):
    from keyshape.app import _pipeline

    path = save_track(_hidden(perf), tmp_path / "hidden.npz")
    calls = []  # (_stream imports solve_take from _pipeline when it needs it)
    monkeypatch.setattr(_pipeline, "solve_take", lambda *a, **k: calls.append(k) or solve_take(*a, **k))
    whole = solve_take(load_track(path), keys, convex=True)
    np.testing.assert_array_equal(solve_track_file(path, keys, convex=True).weights.values, whole.weights.values)
    assert len(calls) == 1
    solve_track_file(path, keys)
    solve_track_file(path, keys, smoothness=0.0)
    assert len(calls) == 1  # the smoothed default and the per-frame solve are streamed


def test_weighted_gram_take_matches_solve_weights(perf, keys):
    track = _hidden(perf, n_missing=False)
    aligned = align(track, reference=keys.neutral, stable=perf.stable)[0]
    aligned = Track(aligned.points, aligned.fps, visibility=track.visibility)
    take = GramTake(keys, aligned.n_frames, weighted=True)
    for lo in range(0, aligned.n_frames, 50):
        frames = slice(lo, lo + 50)
        take.add(lo, aligned.points[frames][:, take.landmarks], aligned.visibility[frames][:, take.landmarks])
    expected = solve_weights(aligned[40:480], keys, smoothness=0.1, upper=1.0).values
    np.testing.assert_allclose(take.solve(40, 480, smoothness=0.1, upper=1.0), expected, atol=TOL, rtol=0)
    expected = solve_weights(aligned, keys, smoothness=0.0, upper=1.0).values
    np.testing.assert_allclose(take.solve(smoothness=0.0, upper=1.0), expected, atol=1e-9, rtol=0)
    with pytest.raises(InputError, match="convex"):
        take.solve(smoothness=0.1, convex=True)


def test_a_landmark_csv_is_loaded_whole(keys, perf, tmp_path):
    path = tmp_path / "take.csv"
    points = perf.track.points[:40].reshape(40, -1)
    header = "frame," + ",".join(f"{a}{i}" for i in range(perf.track.n_landmarks) for a in "xyz")
    np.savetxt(path, np.column_stack([np.arange(40), points]), delimiter=",", header=header, comments="",
               fmt="%.6f")
    assert open_track(path) is None
    whole = solve_take(load_track(path), keys)
    np.testing.assert_array_equal(solve_track_file(path, keys).weights.values, whole.weights.values)


@pytest.mark.parametrize("compress", [False, True])
def test_chunks_read_what_load_track_reads(perf, tmp_path, compress):
    points = np.array(perf.track.points)
    points[5, 3, 1] = np.nan  # a partly tracked frame is no face, as in a Track
    path = tmp_path / "t.npz"
    if compress:  # a file from another tool, deflated and in float64
        np.savez_compressed(path, points=points, fps=30.0)
    else:
        write_track_arrays(path, points=points.astype(np.float32), fps=30.0)
    source, track = open_track(path), load_track(path)
    assert source.shape == track.points.shape
    landmarks = np.array([0, 3, 7, 39])
    got = np.concatenate([p for _, _, p in source.chunks(landmarks, frames=100)])
    np.testing.assert_array_equal(got, track.points[:, landmarks])
    faces = np.concatenate([f for _, f, _ in source.chunks(landmarks, frames=77)])
    np.testing.assert_array_equal(faces, track.valid)


@pytest.mark.parametrize("where, value, message", [
    ((130, 2, 0), np.inf, "frame 130 holds inf \\(missing faces are NaN\\)"),
    ((7, 1, 1), -3e6, "frame 7 holds -3e\\+06, beyond ±1e\\+06 pixels"),
    (None, np.nan, "no frame has a face \\(all 150 frames are NaN\\)"),
])
def test_streamed_points_are_checked_as_a_loaded_track(tmp_path, where, value, message):
    points = np.random.default_rng(0).normal(size=(150, 6, 3)).astype(np.float32)
    points[where or slice(None)] = value
    path = tmp_path / "bad.npz"
    write_track_arrays(path, points=points, fps=30.0)
    with pytest.raises(InputError, match=message):
        load_track(path)
    with pytest.raises(InputError, match=message):
        for _ in open_track(path).chunks(np.arange(6), frames=64):
            pass
    with pytest.raises(InputError, match=message):  # the whole-array check, in chunks too
        check_track_arrays(path, {"points": points, "fps": np.float64(30)})


def test_cli_solve_streams_the_same_weights(perf, keys, tmp_path):
    from keyshape.io import load_keys, save_keys

    track_path = save_track(_with_gaps(perf.track), tmp_path / "take.npz")
    keys_path = tmp_path / "keys.json"
    save_keys(keys, keys_path)
    main(["solve", str(track_path), str(keys_path), "-o", str(tmp_path / "w.csv"), "-q"])
    written = load_weights_csv(tmp_path / "w.csv")
    whole = solve_take(load_track(track_path), load_keys(keys_path)).weights  # keys.json orders keys by region
    assert written.names == whole.names
    np.testing.assert_allclose(written.values, whole.values, atol=2e-6, rtol=0)  # CSV keeps 6 decimals
    np.testing.assert_array_equal(written.frame_index, whole.frame_index)


@pytest.mark.parametrize("smoothness", [0.1, 0.0])
def test_regions_on_threads_give_the_same_weights(perf, keys, monkeypatch, smoothness):
    """Threads solve the regions (smoothed) or parts of their frames (per frame) as one thread does."""
    from keyshape.decompose import _gramtake

    aligned = align(perf.track, reference=keys.neutral, stable=perf.stable)[0]
    take = GramTake(keys, aligned.n_frames)
    take.add(0, aligned.points[:, take.landmarks])
    one_by_one = take.solve(smoothness=smoothness, upper=1.0)
    monkeypatch.setattr(_gramtake, "_PARALLEL_FRAMES", 0)
    monkeypatch.setattr(_gramtake.os, "cpu_count", lambda: 3)
    np.testing.assert_array_equal(take.solve(smoothness=smoothness, upper=1.0), one_by_one)
    if not smoothness:  # frames 5 ... 96 alone, in three parts: their weights in the whole take
        np.testing.assert_array_equal(take.solve(5, 97, upper=1.0), one_by_one[5:97])


def test_a_track_of_other_landmarks_is_refused_before_it_is_read(keys, tmp_path):
    seen = np.full((30, 10), 0.5)  # visibility of fewer landmarks than the keys index
    path = save_track(Track(np.zeros((30, 10, 3)), 30.0, visibility=seen), tmp_path / "other.npz")
    with pytest.raises(InputError, match="the track has 10 landmarks in 3D but the key set was made from 40 in 3D"):
        solve_track_file(path, keys)


def _gram_by_formula(A: np.ndarray, points: np.ndarray, neutral: np.ndarray, seen: np.ndarray, hidden_below: float):
    """One region's weighted Gram form as written out: ``(G, C, sq, gone, partial)`` of frames
    ``points (n, p, d)``, aligned, with visibility ``seen (n, p)``."""
    n, d = len(points), points.shape[2]
    face = np.isfinite(points[:, 0, 0])
    gone = seen.mean(axis=1) < hidden_below
    G, C, sq = np.zeros((n, A.shape[1], A.shape[1])), np.zeros((n, A.shape[1])), np.zeros(n)
    for t in np.flatnonzero(face & ~gone):
        V = np.diag(np.repeat(seen[t], d))  # coordinate (landmark, dimension) weights
        b = (points[t] - neutral).reshape(-1)
        G[t], C[t], sq[t] = A.T @ V @ A, A.T @ V @ b, b @ V @ b
    return G, C, sq, gone, bool((seen[face] < 1.0).any())


@pytest.mark.parametrize("posed", [False, True])
def test_weighted_reduction_is_the_formula(perf, keys, posed):
    """The compiled weighted reduction (GramTake.add) gives each frame's Aᵀ V A, Aᵀ V b and bᵀ V b,
    with fractional visibility, frames without a face and frames whose region is hidden."""
    from keyshape.alignment import procrustes, to_canonical
    from keyshape.decompose._weighted import HIDDEN

    rng = np.random.default_rng(3)
    n = 75  # more than one block of the kernel's frames, and a partial one
    take = GramTake(keys, n + 10, weighted=True)
    aligned = align(perf.track[:n], reference=keys.neutral, stable=perf.stable)[0].points[:, take.landmarks]
    aligned = np.array(aligned)
    aligned[[4, 40]] = np.nan  # no face
    seen = rng.uniform(0.0, 1.0, size=aligned.shape[:2]) ** 0.3
    seen[rng.random(seen.shape) < 0.2] = 1.0
    seen[rng.random(seen.shape) < 0.05] = 0.0
    seen[10:13] = 0.0  # every region gone
    seen[20, take._regions[0].span] = 0.5 * HIDDEN  # one region below HIDDEN
    seen[21, take._regions[0].span] = 1.5 * HIDDEN  # one just above
    if posed:  # the points in the image frame, each frame's pose given
        image = np.array(perf.track.points[:n][:, take.landmarks])
        image[[4, 40]] = np.nan
        poses = procrustes(keys.neutral[take.landmarks], image)
        aligned = np.array(to_canonical(image, poses))
        columns = rng.permutation(len(take.landmarks) + 5)[: len(take.landmarks)]
        rows = rng.uniform(size=(n, len(take.landmarks) + 5)).astype(np.float32)
        rows[:, columns] = seen
        seen = rows[:, columns].astype(float)  # the float32 values the kernel reads
        take.add(10, image, rows, poses=poses, columns=columns)
    else:
        take.add(10, aligned, seen)
    np.testing.assert_array_equal(take.valid[10:], np.isfinite(aligned[:, 0, 0]))
    assert not take.valid[:10].any()
    for region in take._regions:
        G, C, sq, gone, partial = _gram_by_formula(region.A, aligned[:, region.span], keys.neutral[take.landmarks][
            region.span], seen[:, region.span], HIDDEN)
        np.testing.assert_array_equal(region.gone[10:], gone)
        assert gone[10:13].all() and (region is not take._regions[0] or (gone[20] and not gone[21]))
        assert region.hidden[0] == partial
        scale = np.abs(G).max()
        np.testing.assert_allclose(region.G[10:], G, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(region.C[10:], C, rtol=0, atol=1e-12 * np.abs(C).max())
        np.testing.assert_allclose(region.sq[10:], sq, rtol=0, atol=1e-12 * sq.max())
        assert (region.G[10:][~take.valid[10:] | gone] == 0).all() and (sq[take.valid[10:] & ~gone] > 0).all()
    full = np.ones(seen.shape)
    full[[4, 40]] = 0.3  # only frames without a face see less than fully: not hidden
    take = GramTake(keys, n, weighted=True)
    take.add(0, aligned, full)
    assert not any(r.hidden[0] for r in take._regions)
    full[5, 0] = 0.99
    take.add(0, aligned, full)
    assert take._regions[0].hidden[0] and not take._regions[1].hidden[0]


def test_weighted_reduction_on_threads_is_the_same(perf, keys, monkeypatch):
    """A chunk's frames split over threads (GramTake.add) give the one-thread arrays exactly."""
    from keyshape.decompose import _gramtake

    track = _hidden(perf)
    aligned = align(track, reference=keys.neutral, stable=perf.stable)[0].points[:, _landmarks(keys)]
    seen = np.asarray(track.visibility)[:, _landmarks(keys)]
    one = GramTake(keys, len(aligned), weighted=True)
    one.add(0, aligned, seen)
    monkeypatch.setattr(_gramtake, "_PARALLEL_REDUCE", 50)
    monkeypatch.setattr(_gramtake.os, "cpu_count", lambda: 3)
    threads = GramTake(keys, len(aligned), weighted=True)
    threads.add(0, aligned, seen)
    np.testing.assert_array_equal(threads.valid, one.valid)
    for a, b in zip(one._regions, threads._regions, strict=True):
        for name in ("G", "C", "sq", "gone", "hidden"):
            np.testing.assert_array_equal(getattr(b, name), getattr(a, name))


def _landmarks(keys):
    return GramTake(keys, 0).landmarks


def test_chunks_read_ahead_in_order_and_raise_in_place():
    from keyshape.app._stream import _read_ahead

    def items():
        yield from range(3)
        raise InputError("bad frame")

    got = []
    with pytest.raises(InputError, match="bad frame"):
        for item in _read_ahead(items()):
            got.append(item)
    assert got == [0, 1, 2]
