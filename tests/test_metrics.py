"""Metrics: reconstruction error (free and bounded fits), face scale, exact NNLS."""

import numpy as np
import pytest
from scipy.optimize import lsq_linear, nnls

from keyshape.containers import KeyShapes, Track
from keyshape.datasets import make_performance
from keyshape.exceptions import InputError
from keyshape.metrics import face_scale, reconstruction_error

from helpers import nonnegative_fit


def _truth(perf):
    return KeyShapes(
        neutral=perf.neutral, deltas=perf.key_deltas, names=("a", "b", "c", "d"),
        frames=perf.extreme_frames, key_regions=perf.key_regions, regions=perf.regions,
    )


def test_reconstruction_error_is_zero_for_the_true_rig_and_weights():
    perf = make_performance(n_frames=60, n_keys=4, noise=0.0, n_missing=3)
    truth = _truth(perf)
    aligned = perf.track.with_points(np.where(perf.track.valid[:, None, None], perf.canonical, np.nan))
    for weights in (None, perf.true_weights):
        errors = reconstruction_error(aligned, truth, weights=weights)
        assert set(errors) == {"upper", "lower"} and max(errors.values()) < 1e-9
    assert max(reconstruction_error(aligned, truth, upper=1.0).values()) < 1e-9  # true weights are <= 1
    shifted = reconstruction_error(aligned, truth, weights=perf.true_weights + 0.1)
    assert min(shifted.values()) > 0.1


def test_bounded_reconstruction_error_matches_a_bounded_least_squares_reference():
    perf = make_performance(n_frames=40, n_keys=4, noise=0.0, random_state=3)
    truth = _truth(perf)
    rng = np.random.default_rng(3)
    weights = perf.true_weights * rng.uniform(0.5, 2.5, perf.true_weights.shape)  # some beyond 1
    aligned = Track(perf.neutral + np.einsum("fk,kpd->fpd", weights, perf.key_deltas), 30.0)
    for upper in (None, 1.0, 0.5):
        errors = reconstruction_error(aligned, truth, upper=upper)
        for region, lm in perf.regions.items():
            k = truth.keys_of(region)
            A = truth.deltas[k][:, lm].reshape(len(k), -1).T
            B = (aligned.points[:, lm] - truth.neutral[lm]).reshape(40, -1)
            hi = np.inf if upper is None else upper
            fitted = np.stack([lsq_linear(A, b, bounds=(0.0, hi), tol=1e-12).x for b in B])
            expected = np.sqrt(((B - fitted @ A.T) ** 2).sum() / (40 * len(lm)))
            assert errors[region] == pytest.approx(expected, rel=1e-6, abs=1e-6)
    free, bounded = (reconstruction_error(aligned, truth, upper=u) for u in (None, 0.5))
    assert all(bounded[r] > free[r] + 1e-3 for r in perf.regions)  # the bound binds


def test_reconstruction_error_rejects_a_bad_bound():
    perf = make_performance(n_frames=20, n_keys=2, noise=0.0)
    with pytest.raises(InputError, match="upper must be None or a number > 0; got -1"):
        reconstruction_error(perf.track.with_points(perf.canonical), _truth_two(perf), upper=-1)


def _truth_two(perf):
    return KeyShapes(perf.neutral, perf.key_deltas, ("a", "b"), perf.extreme_frames, perf.key_regions, perf.regions)


def test_face_scale_is_the_inter_ocular_distance_when_the_scheme_has_eye_corners():
    rng = np.random.default_rng(0)
    for n_landmarks, corners in ((478, (33, 263)), (468, (33, 263)), (68, (36, 45))):
        neutral = rng.normal(size=(n_landmarks, 3)) * 50
        length, unit = face_scale(neutral)
        assert unit == "% inter-ocular"
        assert length == pytest.approx(np.linalg.norm(neutral[corners[0], :2] - neutral[corners[1], :2]))
    neutral = rng.normal(size=(40, 2)) * 10
    length, unit = face_scale(neutral)
    centred = neutral - neutral.mean(axis=0)
    assert unit == "% face size" and length == pytest.approx(2 * np.sqrt((centred**2).sum(axis=1).mean()))


def test_nonnegative_fit_matches_scipy_nnls():
    rng = np.random.default_rng(5)
    bases, targets = rng.normal(size=(6, 40)), rng.normal(size=(12, 40))
    fitted = nonnegative_fit(targets, bases)
    expected = np.stack([nnls(bases.T, t)[0] for t in targets])
    np.testing.assert_allclose(fitted, expected, atol=1e-8)
    assert (fitted >= 0).all()
