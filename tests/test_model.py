"""KeyShapeModel: the estimator is the functions discover_keys / solve_take, holding the key set."""

import numpy as np
import pytest

import keyshape as ks
from keyshape.datasets import make_performance
from keyshape.exceptions import NotFittedError


@pytest.fixture(scope="module")
def perf():
    return make_performance(n_frames=120, noise=0.0, random_state=3)


def _model(perf, **kw):
    return ks.KeyShapeModel(2, regions=perf.regions, stable=perf.stable, **kw)


def test_transform_is_the_functions(perf):
    model = _model(perf).fit(perf.track)
    keys = ks.discover_keys(perf.track, regions=perf.regions, n_keys=2, stable=perf.stable)
    assert model.keyshapes_.names == keys.names and np.array_equal(model.keyshapes_.frames, keys.frames)
    expected = ks.solve_take(perf.track, keys).weights.values
    np.testing.assert_array_equal(model.transform(perf.track).values, expected)
    np.testing.assert_array_equal(model.fit_transform(perf.track).values, expected)
    assert model.n_keys_ == keys.n_keys == 4


def test_fit_on_several_takes(perf):
    halves = [perf.track[:60], perf.track[60:]]
    model = _model(perf).fit(halves)
    keys = ks.discover_keys(halves, regions=perf.regions, n_keys=2, stable=perf.stable)
    assert list(zip(model.keyshapes_.takes, model.keyshapes_.frames)) == list(zip(keys.takes, keys.frames))


def test_inverse_transform_rebuilds_the_aligned_take(perf):
    model = _model(perf, smoothness=0, upper=None).fit(perf.track)
    weights = model.transform(perf.track)
    rebuilt = model.inverse_transform(weights)
    aligned = ks.solve_take(perf.track, model.keyshapes_, smoothness=0, upper=None).aligned
    scale = np.ptp(aligned.points[perf.neutral_frame][:, 0])
    assert rebuilt.n_frames == perf.track.n_frames and rebuilt.fps == perf.track.fps
    assert np.nanmax(np.abs(rebuilt.points - aligned.points)) < 0.02 * scale  # the neutral alone is 0.10 off


def test_not_fitted(perf):
    with pytest.raises(NotFittedError, match="not fitted yet"):
        _model(perf).transform(perf.track)


def test_init_does_no_work_and_keeps_parameters():
    model = ks.KeyShapeModel("auto", method="hull", upper=None)
    assert (model.n_keys, model.method, model.upper) == ("auto", "hull", None)
    assert not hasattr(model, "keyshapes_")
