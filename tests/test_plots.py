"""Pictures: contact sheet, weight curves with fit error, error vs K."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from keyshape.alignment import align
from keyshape.containers import Weights
from keyshape.exceptions import InputError
from keyshape.report import fit_quality, plots

from test_render import synthetic_take


@pytest.fixture(scope="module")
def take():
    perf, keys, weights, _, _ = synthetic_take(n_frames=60, n_missing=4)
    aligned, _ = align(perf.track, reference=keys.neutral, stable=perf.stable)
    return perf, keys, weights, aligned


def read_png(path) -> np.ndarray:
    with Image.open(path) as image:
        assert image.format == "PNG"
        return np.asarray(image.convert("RGB"))


def test_contact_sheet_shows_every_key_and_the_neutral(take, tmp_path):
    perf, keys, _, _ = take
    images = {int(f): np.full((480, 640, 3), 90, np.uint8) for f in [keys.neutral_frame, *keys.frames]}
    path = plots.contact_sheet(keys, perf.track, images, tmp_path / "sheet.png", columns=3)
    picture = read_png(path)
    # 1 neutral + 4 keys in 3 columns: 2 rows of 2.3 x 2.55 inch tiles at 100 dpi
    assert picture.shape == (510, 690, 3)
    # the grey video frames are there, and so are the two region colours
    assert (np.abs(picture.astype(int) - 90).sum(axis=2) == 0).mean() > 0.2
    from keyshape.render.draw import REGION_COLOURS

    for colour in REGION_COLOURS[:2]:
        assert (np.abs(picture.astype(int) - colour).sum(axis=2) < 40).sum() > 10


def test_contact_sheet_without_video_draws_the_landmarks(take, tmp_path):
    perf, keys, _, _ = take
    picture = read_png(plots.contact_sheet(keys, perf.track, {}, tmp_path / "sheet.png"))
    assert picture.shape[1] == 5 * 230  # all five tiles in one row of at most 6
    dark = (np.abs(picture.astype(int) - (0x20, 0x22, 0x26)).sum(axis=2) < 6).mean()
    assert dark > 0.3  # the tiles' dark background


def test_weight_curves_png(take, tmp_path):
    _, keys, weights, aligned = take
    fit = fit_quality(aligned, keys, weights)
    picture = read_png(plots.weight_curves(weights, keys, fit, tmp_path / "w.png"))
    assert picture.shape == (2 * 200 + 260, 1200, 3)
    assert picture.std() > 10
    # the 4 gaps (frames without a face) are shaded grey (#9a9a9a at 35 % over white) in all 3 panels
    grey = (np.abs(picture.astype(int) - 220).sum(axis=2) < 6).sum()
    assert grey > 4 * 3 * 100


def test_runs():
    assert plots._runs(np.array([1, 1, 0, 0, 1, 0, 1], bool)) == [(0, 2), (4, 5), (6, 7)]
    assert plots._runs(np.zeros(3, bool)) == []


def test_error_vs_k_accepts_both_table_forms(tmp_path):
    ks = np.arange(1, 9)
    table = {"spa": {"upper": (ks, 4 / ks), "lower": (ks, 6 / ks)},
             "hull": {"upper": (ks, 5 / ks), "lower": (ks, 7 / ks)}}
    picture = read_png(plots.error_vs_k(table, tmp_path / "k.png", chosen={"upper": 4, "lower": 4}))
    assert picture.shape == (340, 2 * 420, 3)
    single = read_png(plots.error_vs_k({"spa": (ks, 4 / ks)}, tmp_path / "k1.png"))
    assert single.shape == (340, 420, 3)


def test_error_vs_k_rejects_bad_tables(tmp_path):
    with pytest.raises(InputError, match="spa/upper needs as many errors as ks"):
        plots.error_vs_k({"spa": {"upper": ([1, 2, 3], [1.0, 2.0])}}, tmp_path / "k.png")
    with pytest.raises(InputError, match="empty"):
        plots.error_vs_k({}, tmp_path / "k.png")
    assert not list(tmp_path.iterdir())


def test_contact_sheet_keys_from_another_take_show_their_shape(take, tmp_path):
    perf, keys, _, _ = take
    from keyshape.containers import KeyShapes

    other = KeyShapes(keys.neutral, keys.deltas, keys.names, keys.frames, keys.key_regions, keys.regions,
                      takes=("a.mp4", "b.mp4", "a.mp4", "b.mp4"), neutral_take="a.mp4",
                      neutral_frame=keys.neutral_frame)
    frames = [int(keys.neutral_frame), *keys.frames.tolist()]
    images = {f: np.full((480, 640, 3), 90, np.uint8) for f in frames}
    grey = lambda p: (np.abs(read_png(p).astype(int) - 90).sum(axis=2) == 0).mean()  # noqa: E731
    mine = grey(plots.contact_sheet(other, perf.track, images, tmp_path / "a.png", take=("x.mp4", "a.mp4")))
    none = grey(plots.contact_sheet(other, perf.track, images, tmp_path / "n.png", take="x.mp4"))
    assert none == 0 < mine  # only the tiles of take a.mp4 show video frames


def test_weight_curves_colour_every_key_of_a_region_apart_and_explain_the_spans():
    """Issue 36 item 9: a region of 13 keys (8 and 5 mirrors, as the demo's lower face) gets 13 line
    colours; each panel's legend says what the grey, tinted and hatched spans are."""
    from types import SimpleNamespace

    from matplotlib.colors import to_hex

    from keyshape.containers import KeyShapes

    lower = [*(f"lower_0{i}" for i in range(8)), *(f"lower_0{i}_mirror" for i in (1, 2, 3, 4, 6))]
    names = ("upper_00", "upper_01", *lower)
    n, n_keys = 80, len(names)
    rng = np.random.default_rng(0)
    keys = KeyShapes(np.zeros((6, 2)), rng.normal(size=(n_keys, 6, 2)), names, list(range(n_keys)),
                     ("upper", "upper", *["lower"] * len(lower)),
                     {"upper": np.arange(3), "lower": np.arange(3, 6)}, neutral_frame=0)
    values = rng.random((n, n_keys))
    values[10:14] = np.nan
    weights = Weights(values, names, fps=25.0)
    outside = {"upper": np.zeros(n, bool), "lower": np.arange(n) % 20 == 3}
    fit = SimpleNamespace(error={r: rng.random(n) for r in ("upper", "lower")},
                          excess={r: rng.random(n) for r in ("upper", "lower")},
                          outside=outside, unit="% inter-ocular", tolerance=0.5)
    hidden = {"lower": (np.arange(n) >= 40) & (np.arange(n) < 55)}
    figure = plots._weight_figure(weights, keys, fit, hidden)
    upper_ax, lower_ax, _ = figure.axes
    for ax, members in ((upper_ax, names[:2]), (lower_ax, lower)):
        lines = {line.get_label(): line for line in ax.get_lines() if not line.get_label().startswith("_")}
        assert list(lines) == list(members)
        assert len({to_hex(line.get_color()) for line in lines.values()}) == len(members)
        assert all((line.get_linestyle() == "--") == name.endswith("_mirror") for name, line in lines.items())
    legend = [t.get_text() for t in lower_ax.get_legend().get_texts()]
    assert legend == [*lower, "no face", "outside the key-shape hull", "lower hidden: weights bridged"]
    hatched = [h for h in lower_ax.get_legend().legend_handles if getattr(h, "get_hatch", lambda: None)() == "//"]
    assert len(hatched) == 1
    assert [t.get_text() for t in upper_ax.get_legend().get_texts()] == [*names[:2], "no face"]
