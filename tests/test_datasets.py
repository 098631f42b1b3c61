"""The synthetic performance generator: shapes, truth consistency, determinism."""

import numpy as np
import pytest

from keyshape.datasets import make_performance
from keyshape.exceptions import InputError


@pytest.mark.parametrize("n_dims", [2, 3])
def test_shapes_and_truth(n_dims):
    perf = make_performance(n_frames=60, n_landmarks=30, n_dims=n_dims, n_keys=4, noise=0.0, n_missing=4)
    assert perf.track.points.shape == (60, 30, n_dims)
    assert perf.true_weights.shape == (60, 4) and (perf.true_weights >= 0).all()
    assert perf.key_deltas.shape == (4, 30, n_dims) and perf.neutral.shape == (30, n_dims)
    assert perf.track.valid.sum() == 56
    np.testing.assert_allclose(np.linalg.det(perf.true_poses.rotations), 1.0)
    image = perf.true_poses.to_image(perf.canonical)
    valid = perf.track.valid
    np.testing.assert_allclose(perf.track.points[valid], image[valid], atol=1e-9)


def test_planted_extremes_regions_and_stable():
    perf = make_performance(n_keys=6)
    np.testing.assert_array_equal(perf.true_weights[perf.extreme_frames], np.eye(6))
    assert perf.track.valid[perf.extreme_frames].all() and perf.track.valid[perf.neutral_frame]
    assert not perf.true_weights[perf.neutral_frame].any()
    cover = np.sort(np.concatenate(list(perf.regions.values())))
    np.testing.assert_array_equal(cover, np.arange(perf.track.n_landmarks))
    assert not perf.key_deltas[:, perf.stable].any()
    for k, region in enumerate(perf.key_regions):
        outside = np.setdiff1d(np.arange(perf.track.n_landmarks), perf.regions[region])
        assert not perf.key_deltas[k, outside].any()
        cols = [j for j, r in enumerate(perf.key_regions) if r == region]
        assert perf.true_weights[:, cols].sum(axis=1).max() <= 1.0 + 1e-12


def test_deterministic_under_random_state():
    a, b = make_performance(random_state=7), make_performance(random_state=7)
    np.testing.assert_array_equal(a.track.points, b.track.points)
    assert not np.array_equal(a.track.points, make_performance(random_state=8).track.points)


def test_rejects_bad_sizes():
    with pytest.raises(InputError, match="n_dims must be 2 or 3"):
        make_performance(n_dims=4)
    with pytest.raises(InputError, match="n_keys must be in"):
        make_performance(n_frames=10, n_keys=6)
