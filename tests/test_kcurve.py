"""Error against the number of key shapes: PCA is the floor, the curves are those of the
selected key sets, the unit is the inter-ocular distance; on the real clip spa wins."""

import numpy as np
import pytest

from keyshape.alignment import align, choose_neutral
from keyshape.datasets import make_performance
from keyshape.exceptions import InputError
from keyshape.keyshapes import CURVE_METHODS, KCurve, choose_n_keys, error_vs_k, find_keyshapes
from keyshape.keyshapes import _search as keyshapes
from keyshape.metrics import face_scale, reconstruction_error


@pytest.fixture(scope="module")
def take():
    perf = make_performance(n_frames=150, n_keys=10, noise=0.4, n_missing=5, random_state=7)
    aligned, _ = align(perf.track, reference=perf.neutral, stable=perf.stable)
    return perf, aligned, perf.neutral_frame


@pytest.fixture(scope="module", params=[None, 1.0], ids=["free", "bounded"])
def curve(request, take):
    perf, aligned, neutral = take
    return error_vs_k(aligned, regions=perf.regions, neutral_frame=neutral, ks=range(1, 16), upper=request.param)


def test_pca_is_below_every_selection_at_every_k(curve):
    for region in curve.errors["pca"]:
        pca = curve.errors["pca"][region]
        for method in ("spread", "hull", "spa"):
            assert (pca <= curve.errors[method][region] + 1e-9).all(), (method, region)


def test_pca_error_never_grows_with_k(curve):
    for errors in curve.errors["pca"].values():
        assert (np.diff(errors) <= 1e-12).all()
        assert errors[-1] < errors[0]


def test_spa_error_never_grows_with_k(curve):
    """spa grows its key set one key at a time, and exchanges only ever lower the error."""
    for errors in curve.errors["spa"].values():
        assert (np.diff(errors) <= 1e-9).all()


def test_curve_is_the_error_of_the_keys_find_keyshapes_returns(take, curve):
    perf, aligned, neutral = take
    scale, unit = face_scale(aligned.points[neutral])
    assert unit == curve.unit == "% face size" and curve.scale == scale
    for method in ("spa", "spread", "hull"):
        for k in (1, 4, 9):
            keys = find_keyshapes(aligned, regions=perf.regions, n_keys=k, method=method,
                                  neutral_frame=neutral, upper=curve.upper)
            expected = reconstruction_error(aligned, keys, upper=curve.upper)
            for region in perf.regions:
                got = curve.errors[method][region][k - 1]
                assert got == pytest.approx(100 * expected[region] / scale, rel=1e-8), (method, k, region)


def test_beyond_the_limit_the_curve_is_still_the_error_of_the_keys_find_keyshapes_returns(take, monkeypatch):
    """With fewer MAX_CANDIDATES than frames the keys come from a pool, their errors from every frame."""
    perf, aligned, neutral = take  # 144 candidate frames
    ks = [1, 4, 9]
    every = error_vs_k(aligned, regions=perf.regions, neutral_frame=neutral, ks=ks, methods=("pca",))
    monkeypatch.setattr(keyshapes, "MAX_CANDIDATES", 60)
    curve = error_vs_k(aligned, regions=perf.regions, neutral_frame=neutral, ks=ks, upper=1.0)
    for region in perf.regions:  # pca from the scatter matrix's eigenvalues: the SVD's
        np.testing.assert_allclose(curve.errors["pca"][region], every.errors["pca"][region], rtol=1e-9)
    for method in ("spa", "spread", "hull"):
        for i, k in enumerate(ks):
            keys = find_keyshapes(aligned, regions=perf.regions, n_keys=k, method=method,
                                  neutral_frame=neutral, upper=1.0)
            expected = reconstruction_error(aligned, keys, upper=1.0)
            for region in perf.regions:
                got = curve.errors[method][region][i]
                assert got == pytest.approx(100 * expected[region] / curve.scale, rel=1e-8), (method, k, region)


def test_auto_k_is_the_first_k_of_the_curve_below_the_target(take, curve):
    perf, aligned, neutral = take
    target = float(np.median(curve.errors["spa"]["lower"]))
    choices = choose_n_keys(aligned, regions=perf.regions, neutral_frame=neutral, max_error=target,
                            upper=curve.upper)
    for region, choice in choices.items():
        errors = curve.errors["spa"][region]
        first = int(np.argmax(errors < target)) + 1 if (errors < target).any() else None
        if first is not None:
            assert choice.k == first and choice.error == pytest.approx(errors[first - 1])


def test_bounded_errors_are_no_lower_than_free_ones_for_pca_and_the_papers_methods(take):
    perf, aligned, neutral = take
    free, bounded = (error_vs_k(aligned, regions=perf.regions, neutral_frame=neutral, ks=[2, 6],
                                methods=("pca", "spread", "hull"), upper=u) for u in (None, 1.0))
    for region in perf.regions:
        np.testing.assert_array_equal(free.errors["pca"][region], bounded.errors["pca"][region])
        for method in ("spread", "hull"):  # same keys, a tighter fit
            assert (bounded.errors[method][region] >= free.errors[method][region] - 1e-12).all()


def test_inter_ocular_unit_for_a_68_landmark_face():
    perf = make_performance(n_frames=60, n_landmarks=68, n_keys=4, noise=0.2, random_state=1)
    aligned, _ = align(perf.track, reference=perf.neutral, stable=perf.stable)
    curve = error_vs_k(aligned, regions=perf.regions, neutral_frame=perf.neutral_frame, ks=[1, 2],
                       methods=("pca", "spa"))
    neutral = aligned.points[perf.neutral_frame]
    assert curve.unit == "% inter-ocular"
    assert curve.scale == pytest.approx(np.linalg.norm(neutral[36, :2] - neutral[45, :2]))
    assert set(curve.errors) == {"pca", "spa"}


def test_table_rows_and_plot(curve, tmp_path):
    from keyshape.report.plots import error_vs_k as plot

    assert isinstance(curve, KCurve) and curve.ks.tolist() == list(range(1, 16))
    rows = list(curve.rows())
    assert len(rows) == 2 * len(CURVE_METHODS) * 15
    assert rows[0] == ("upper", "pca", 1, curve.errors["pca"]["upper"][0])
    table = curve.table
    assert set(table) == set(CURVE_METHODS) and table["spa"]["lower"][0] is curve.ks
    assert plot(table, tmp_path / "k.png", unit=curve.unit).stat().st_size > 1000


def test_validation_messages(take):
    perf, aligned, neutral = take
    with pytest.raises(InputError, match=r"methods must be some of \('pca', 'spread', 'hull', 'spa'\); got \('nmf',\)"):
        error_vs_k(aligned, regions=perf.regions, neutral_frame=neutral, methods=["nmf"])
    message = r"ks must lie in 1\.\.144 \(the valid frames besides the neutral\); got 0\.\.3"
    with pytest.raises(InputError, match=message):
        error_vs_k(aligned, regions=perf.regions, neutral_frame=neutral, ks=[0, 3])
    with pytest.raises(InputError, match=r"ks must lie in 1\.\.144"):
        error_vs_k(aligned, regions=perf.regions, neutral_frame=neutral, ks=[200])
    with pytest.raises(InputError, match="ks must be a non-empty sequence of ints"):
        error_vs_k(aligned, regions=perf.regions, neutral_frame=neutral, ks=[])
    with pytest.raises(InputError, match="upper must be None or a number > 0"):
        error_vs_k(aligned, regions=perf.regions, neutral_frame=neutral, upper=-1.0)


@pytest.mark.slow
def test_spa_beats_the_papers_methods_on_real_footage(real_track):
    """Issue 3: on the real clip, spa has a lower error than spread and hull at every K >= 4,
    with the product's bound 0 <= w <= 1 and without it; --count auto reaches its target."""
    from keyshape.schemes import resolve_regions, stable_points

    regions = resolve_regions("upper-lower", real_track.n_landmarks)
    stable = stable_points(real_track.n_landmarks)
    neutral = choose_neutral(real_track, stable=stable)  # as keyshape keys / pipeline.discover_keys
    aligned, _ = align(real_track, reference=real_track.points[neutral], stable=stable)
    for upper in (1.0, None):
        curve = error_vs_k(aligned, regions=regions, neutral_frame=neutral, upper=upper)
        assert curve.unit == "% inter-ocular"
        for region in regions:
            e = {m: curve.errors[m][region][3:] for m in CURVE_METHODS}  # K = 4 .. 30
            assert (e["spa"] < e["spread"]).all() and (e["spa"] < e["hull"]).all(), (upper, region, e)
            assert (curve.errors["pca"][region] <= curve.errors["spa"][region]).all()
    choices = choose_n_keys(aligned, regions=regions, neutral_frame=neutral, upper=1.0)
    assert all(1 <= c.k < 24 and c.error < 2.0 for c in choices.values()), choices
