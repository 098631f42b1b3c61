import numpy as np

from keyshape.capture.filters import find_gaps, gap_report, hold_neutral, one_euro


def test_find_gaps():
    valid = np.array([0, 1, 1, 0, 0, 0, 1, 0], dtype=bool)
    assert find_gaps(valid) == [(0, 1), (3, 3), (7, 1)]
    assert find_gaps(np.ones(4, bool)) == []


def test_gap_report_bridges_short_inner_gaps_only():
    valid = np.ones(100, bool)
    valid[:2] = False      # at the start: held
    valid[10:15] = False   # short, inner: bridged
    valid[40:80] = False   # long: held
    report = gap_report(valid, max_bridge=12)
    assert report.n_missing == 47 and report.longest == 40
    assert report.bridged == ((10, 5),)
    assert report.held == ((0, 2), (40, 40))
    assert "1 bridged" in str(report) and "2 held at neutral" in str(report)
    held = hold_neutral(np.full((100, 2), 0.7), report)
    assert (held[40:80] == 0).all() and (held[10:15] == 0.7).all()


def test_one_euro_smooths_jitter_and_follows_motion():
    rng = np.random.default_rng(0)
    t = np.arange(300) / 30
    truth = np.where(t < 5, 0.0, 50.0)[:, None]
    noisy = truth + rng.normal(0, 1.0, truth.shape)
    filtered = one_euro(noisy, 30, min_cutoff=0.5, beta=0.05)
    rest = slice(30, 140)
    assert filtered[rest].std() < 0.5 * noisy[rest].std()
    assert abs(filtered[-1, 0] - 50) < 1.0  # catches up after the jump


def test_one_euro_restarts_after_nan():
    x = np.ones((6, 2))
    x[3] = np.nan
    x[4:] = 10
    out = one_euro(x, 30)
    assert np.isnan(out[3]).all() and (out[4] == 10).all()
