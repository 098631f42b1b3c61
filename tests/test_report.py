"""Fit quality, the take numbers and the self-contained report.html."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest

from keyshape.containers import KeyShapes, Track, Weights
from keyshape.datasets import make_performance
from keyshape.report import fit_quality, gap_runs, take_numbers, write_take_extras

from test_render import decode, make_take_folder

URL_ATTRIBUTE = re.compile(r"""\b(?:src|href)\s*=\s*["']?\s*([^"'\s>]+)""", re.IGNORECASE)


def test_gap_runs():
    assert gap_runs(np.ones(5, bool)) == (0, 0)
    assert gap_runs(np.array([0, 0, 1, 0, 1, 0, 0, 0], bool)) == (3, 3)
    assert gap_runs(np.zeros(4, bool)) == (1, 4)


def planted():
    """Noiseless take whose keys are the true key shapes, in canonical coordinates."""
    perf = make_performance(n_frames=80, n_keys=4, noise=0.0, rotation_deg=0.0, random_state=3)
    keys = KeyShapes(perf.neutral, perf.key_deltas, ("u0", "l0", "u1", "l1"), perf.extreme_frames,
                     perf.key_regions, perf.regions, neutral_frame=perf.neutral_frame)
    canonical = Track(perf.canonical, perf.track.fps)
    return perf, keys, canonical


def test_fit_quality_is_zero_for_the_true_weights():
    perf, keys, canonical = planted()
    fit = fit_quality(canonical, keys, Weights(perf.true_weights, keys.names, 30.0))
    for region in keys.regions:
        assert np.nanmax(fit.error[region]) < 1e-9 and not fit.outside[region].any()
    assert fit.unit == "% face size" and fit.scale > 0


def test_fit_quality_error_is_rms_in_percent_of_the_scale():
    perf, keys, canonical = planted()
    zero = Weights(np.zeros_like(perf.true_weights), keys.names, 30.0)
    fit = fit_quality(canonical, keys, zero)
    f, lm = 17, keys.regions["upper"]
    moved = canonical.points[f, lm] - keys.neutral[lm]
    expected = np.sqrt((moved**2).sum(axis=1).mean()) / fit.scale * 100
    assert fit.error["upper"][f] == pytest.approx(expected)
    # zero weights are a valid non-negative blend: only the part the span reaches with w >= 0 costs nothing
    assert (fit.excess["upper"] <= fit.error["upper"] + 1e-12).all()


def test_frames_outside_the_hull_are_those_needing_negative_weights():
    perf, keys, canonical = planted()
    weights = perf.true_weights.copy()
    points = canonical.points.copy()
    k, frame = 0, 5  # key u0 (upper), pushed the other way: outside the cone of the upper keys
    points[frame] = keys.neutral - 1.0 * keys.deltas[k]
    weights[frame] = 0.0  # the best non-negative blend of an opposite move is (close to) nothing
    fit = fit_quality(canonical.with_points(points), keys, Weights(weights, keys.names, 30.0), tolerance=1.0)
    assert fit.outside["upper"][frame] and fit.outside["upper"].sum() == 1
    assert not fit.outside["lower"].any()
    assert fit.excess["upper"][frame] == pytest.approx(fit.error["upper"][frame], rel=1e-6)


def test_fit_quality_nan_frames_and_weight_order():
    perf, keys, canonical = planted()
    points = canonical.points.copy()
    points[3] = np.nan
    shuffled = Weights(perf.true_weights[:, ::-1], keys.names[::-1], 30.0)
    fit = fit_quality(canonical.with_points(points), keys, shuffled)
    assert np.isnan(fit.error["upper"][3]) and not fit.outside["upper"][3]
    assert np.nanmax(fit.error["lower"]) < 1e-9
    with pytest.raises(ValueError, match="missing"):
        fit_quality(canonical, keys, Weights(perf.true_weights[:, :2], keys.names[:2], 30.0))


def test_take_numbers():
    perf = make_performance(n_frames=50, n_keys=2, noise=0.0, n_missing=5, random_state=1)
    keys = KeyShapes(perf.neutral, perf.key_deltas, ("u0", "l0"), perf.extreme_frames, perf.key_regions,
                     perf.regions, neutral_frame=perf.neutral_frame)
    points = perf.canonical.copy()
    points[~perf.track.valid] = np.nan
    fit = fit_quality(Track(points, 30.0), keys, Weights(perf.true_weights, keys.names, 30.0))
    numbers = take_numbers(perf.track, keys, fit)
    valid = perf.track.valid
    assert numbers["frames"] == 50 and numbers["frames_with_face"] == 45
    assert numbers["detection_rate"] == 90.0
    runs = "".join("x" if v else "." for v in valid).split("x")
    assert numbers["gaps"] == sum(1 for r in runs if r) and numbers["longest_gap_frames"] == max(map(len, runs))
    assert numbers["regions"]["upper"]["keys"] == 1 and numbers["regions"]["upper"]["rms_error"] == 0.0
    json.dumps(numbers)  # JSON-ready


def test_key_frames_are_the_videos_own_under_start(tmp_path):
    """A take tracked from frame 100 (``--start 100``): keys and neutral are rows of the track, the
    report shows the video's frame numbers and times; a key from another take has none."""
    from keyshape.report._html import write_report

    perf = make_performance(n_frames=50, n_keys=2, noise=0.0, random_state=1)
    track = Track(perf.track.points, 25.0, frame_index=np.arange(100, 150), time=np.arange(100, 150) / 25.0)
    keys = KeyShapes(perf.neutral, perf.key_deltas, ("u0", "l0"), [3, 40], perf.key_regions, perf.regions,
                     takes=("a.mp4", "b.mp4"), neutral_frame=7, neutral_take="a.mp4")
    fit = fit_quality(Track(perf.canonical, 25.0), keys, Weights(perf.true_weights, keys.names, 25.0))
    numbers = take_numbers(track, keys, fit, take="a.mp4")
    assert numbers["key_frames"] == [{"frame": 103, "time": 4.12}, None]
    assert numbers["neutral_video_frame"] == {"frame": 107, "time": 4.28} and numbers["neutral_frame"] == 7
    page = write_report(tmp_path / "report.html", numbers, keys, title="t", images={}).read_text()
    table = page[page.index('<table id="keys">'):]
    assert '<td class="n">103</td><td class="n">4.12 s</td>' in table  # the video's frame and time
    assert '<td class="n">40</td><td class="n">1.60 s</td>' in table  # another take: its own row
    assert "7 (video frame 107)" in page


# --------------------------------------------------------------------------- report.html


@pytest.fixture(scope="module")
def extras(tmp_path_factory):
    folder = make_take_folder(tmp_path_factory.mktemp("take"), n_frames=40, n_missing=4)
    ks = [1, 2, 3]
    (folder / "error_vs_k.json").write_text(json.dumps(
        {"spa": {"upper": {"ks": ks, "errors": [3.0, 2.0, 1.0]}, "lower": {"ks": ks, "errors": [4, 3, 2]}}}))
    return folder, write_take_extras(folder, progress=False)


def test_take_extras_writes_every_file(extras):
    folder, result = extras
    for name in ("report.html", "preview.mp4", "keyshapes.png", "weights.png", "error_vs_k.png"):
        assert (folder / name).stat().st_size > 1000, name
    assert set(result.pictures) == {"keyshapes", "weights", "error_vs_k"}
    frames, rate, count = decode(result.preview)
    assert count == len(frames) == 40 and rate == pytest.approx(25.0)
    assert not list(folder.glob(".*part*"))  # no temporary files left behind


def test_report_is_self_contained(extras):
    folder, result = extras
    text = result.report.read_text(encoding="utf-8")
    targets = URL_ATTRIBUTE.findall(text)
    assert targets, "the report should reference its pictures and video"
    assert not [t for t in targets if re.match(r"(?i)(https?:)?//", t)]
    assert not re.search(r"(?i)https?://", text.replace("http://www.w3.org", ""))
    images = re.findall(r'<img[^>]+src="data:image/png;base64,([^"]+)"', text)
    assert len(images) == 3
    for data in images:
        assert base64.b64decode(data)[:8] == b"\x89PNG\r\n\x1a\n"
    videos = re.findall(r'<video[^>]+src="([^"]+)"', text)
    assert videos == ["preview.mp4"] and (folder / videos[0]).is_file()
    assert "<link" not in text and "@import" not in text and "<script src" not in text


def test_report_numbers_are_right(extras):
    folder, result = extras
    from keyshape.io.keys_json import load_keys
    from keyshape.io.track import load_track

    track, keys = load_track(folder / "track.npz"), load_keys(folder / "keys.json")
    text = result.report.read_text(encoding="utf-8")
    embedded = json.loads(re.search(r'<script type="application/json" id="numbers">(.*?)</script>', text,
                                    re.DOTALL).group(1))
    assert embedded == result.numbers
    assert embedded["frames"] == track.n_frames == 40
    assert embedded["frames_with_face"] == int(track.valid.sum()) == 36
    assert embedded["detection_rate"] == 90.0
    assert embedded["gaps"] == gap_runs(track.valid)[0] and embedded["longest_gap_frames"] == gap_runs(track.valid)[1]
    assert {r: v["keys"] for r, v in embedded["regions"].items()} == {"upper": 2, "lower": 2}
    assert embedded["neutral_frame"] == keys.neutral_frame
    cell = lambda key: re.search(rf'data-key="{key}">([^<]*)<', text).group(1)  # noqa: E731
    assert cell("frames") == "40" and cell("detection rate") == "90.00 %"
    for region, numbers in embedded["regions"].items():
        row = re.search(rf'<tr data-region="{region}">(.*?)</tr>', text).group(1)
        assert f"{numbers['rms_error']:.2f}" in row
    for name in keys.names:
        assert f"<td>{name}</td>" in text


def test_report_verb_without_preview(tmp_path):
    from keyshape.cli import main

    folder = make_take_folder(tmp_path / "take", n_frames=20, n_missing=0, with_video=False)
    assert main(["report", str(folder), "--no-preview", "-q"]) == 0
    text = (folder / "report.html").read_text()
    assert "<video" not in text and "was not found" in text
    assert not (folder / "preview.mp4").exists()
    assert main(["report", str(tmp_path / "missing"), "-q"]) == 1


@pytest.mark.slow
def test_demo_take_end_to_end(demo_out, tmp_path):
    """The real clip: `keyshape demo` wrote the extras; the character moves with the expression."""
    import shutil

    from keyshape.io.keys_json import load_keys
    from keyshape.io.weights_csv import load_weights_csv

    assert {"preview.mp4", "report.html", "keyshapes.png", "weights.png"} <= {p.name for p in demo_out.iterdir()}
    tmp_path = Path(shutil.copytree(demo_out, tmp_path / "demo"))
    result = write_take_extras(tmp_path, progress=False, preview=False)  # keeps the demo's preview
    numbers = result.numbers
    assert numbers["frames"] == 472 and numbers["detection_rate"] >= 95
    shown = load_keys(tmp_path / "keys.json")
    assert {r: v["keys"] for r, v in numbers["regions"].items()} == {r: len(shown.keys_of(r)) for r in shown.regions}
    assert {r: int((~shown.mirrored[shown.keys_of(r)]).sum()) for r in shown.regions} == {"upper": 8, "lower": 8}
    assert all(v["rms_error"] < 5 for v in numbers["regions"].values())  # % inter-ocular distance
    frames, rate, count = decode(result.preview)
    assert count == len(frames) == 472 and rate == pytest.approx(24000 / 1001, abs=1e-3)
    keys, weights = load_keys(tmp_path / "keys.json"), load_weights_csv(tmp_path / "weights.csv")
    lower = keys.keys_of("lower")
    strong = int(np.nanargmax(np.nansum(weights.values[:, lower], axis=1)))
    height = frames[0].shape[0] - 96  # above the weight strip
    panel = slice(frames[0].shape[1] - height, None)
    a, b = frames[keys.neutral_frame][:height, panel], frames[strong][:height, panel]
    assert (np.abs(a.astype(int) - b).sum(axis=2) > 30).mean() > 0.01


def test_report_can_embed_the_video(extras):
    folder, _ = extras
    result = write_take_extras(folder, progress=False, preview=False, embed_video=True)
    text = result.report.read_text(encoding="utf-8")
    video = re.search(r'<video[^>]+src="data:video/mp4;base64,([^"]+)"', text).group(1)
    assert base64.b64decode(video) == (folder / "preview.mp4").read_bytes()


def test_report_states_the_correspondence_quality(tmp_path):
    from keyshape.targets import Correspondence

    folder = make_take_folder(tmp_path / "take", n_frames=20)
    found = Correspondence([0, 3, 5], [[0, 1, 2]] * 3, [[1, 0, 0]] * 3, 478, residual=[0.0, 0.002, 0.03])
    found.save(folder / "correspondence.json")
    result = write_take_extras(folder, progress=False, preview=False)
    quality = result.numbers["correspondence"]
    assert quality["landmarks_kept"] == 3 and quality["moved"] == 1 and quality["median_residual_pct"] == 0.2
    assert "3 of 478 landmarks on its surface" in result.report.read_text(encoding="utf-8")
    given = Correspondence.from_vertex_ids([4, 5, 6])
    assert given.quality() is None and "quality" not in given.to_dict()


def _open_report(browser, path: Path) -> dict:
    """``report.html`` opened from disk in Chromium: what the reader sees of the preview."""
    page = browser.new_page()
    errors = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(path.as_uri())
    page.wait_for_function("(() => { const v = document.getElementById('preview');"
                           " return v.error !== null || v.readyState >= 1; })()", timeout=20_000)
    page.wait_for_timeout(200)
    seen = page.evaluate("""() => {
      const video = document.getElementById('preview'), note = document.getElementById('preview-missing');
      return {playerShown: !video.hidden && video.getBoundingClientRect().height > 0,
              duration: video.duration || 0,
              noteShown: !!note && !note.hidden && note.getBoundingClientRect().height > 0,
              note: note ? note.innerText : null};
    }""")
    page.close()
    assert errors == []
    return seen


@pytest.mark.browser
def test_report_opened_without_its_preview_says_so(extras, browser, tmp_path):
    """Issue 36 item 10: report.html opened on its own tells the reader where the video went and what
    to do (no empty player); beside preview.mp4 it plays it; `report --embed-video` carries it."""
    import shutil

    from keyshape.cli import main

    copy = Path(shutil.copytree(extras[0], tmp_path / "take"))
    assert main(["report", str(copy), "--no-preview", "-q"]) == 0  # the preview.mp4 already there, linked
    beside = _open_report(browser, copy / "report.html")
    assert beside["playerShown"] and beside["duration"] == pytest.approx(40 / 25, abs=0.1)
    assert not beside["noteShown"]

    alone = tmp_path / "mailed" / "report.html"
    alone.parent.mkdir()
    shutil.copy(copy / "report.html", alone)
    seen = _open_report(browser, alone)
    assert seen["noteShown"] and not seen["playerShown"]
    assert seen["note"] == ("The preview video is not here. This page plays preview.mp4 from its own folder, and "
                            "there is no preview.mp4 beside it: open the report in the take's output folder, copy "
                            "preview.mp4 next to it, or write a report that carries the video: "
                            "keyshape report FOLDER --embed-video.")

    assert main(["report", str(copy), "--no-preview", "--embed-video", "-q"]) == 0
    shutil.copy(copy / "report.html", alone)
    embedded = _open_report(browser, alone)
    assert embedded["note"] is None and embedded["playerShown"]
    assert embedded["duration"] == pytest.approx(40 / 25, abs=0.1)


def test_report_on_a_mapped_rig_shows_the_map_and_the_rigs_curves(tmp_path):
    """Issue 36 item 11: with a map.json (an ARKit rig driven through the map), the report heads its keys
    as what the map turns into the rig's shapes, not "the sculpt list", lists each key's targets with their
    gains, and plots the rig's own curves (jawOpen, mouthSmile_L, ...) from animation.glb."""
    from keyshape.containers import Rig
    from keyshape.io.gltf import write_glb
    from keyshape.io.keys_json import load_keys
    from keyshape.io.weights_csv import load_weights_csv
    from keyshape.targets import Mapping, retarget

    folder = make_take_folder(tmp_path / "take", n_frames=30, n_missing=0)
    keys, weights = load_keys(folder / "keys.json"), load_weights_csv(folder / "weights.csv")
    targets = ("jawOpen", "mouthSmile_L", "mouthSmile_R", "browInnerUp")
    gains = {keys.names[0]: {"browInnerUp": 0.8}, keys.names[-1]: {"jawOpen": 0.9, "mouthSmile_L": 0.3}}
    mapping = Mapping.from_dict(gains, targets=targets, sources=keys.names)
    mapping.save(folder / "map.json")
    rig = Rig(np.eye(3), [[0, 1, 2]], np.full((4, 3, 3), 0.01), targets)
    write_glb(folder / "animation.glb", rig, retarget(weights, mapping))
    result = write_take_extras(folder, progress=False, preview=False)
    text = result.report.read_text(encoding="utf-8")
    assert "the sculpt list" not in text
    assert "<h2>Key shapes: what map.json turns into the rig&#x27;s own shapes</h2>" in text
    table = text[text.index('<table id="map">'):]
    row = re.search(rf'<tr data-key="{keys.names[-1]}">(.*?)</tr>', table).group(1)
    assert re.fullmatch(rf'<td>{keys.names[-1]}</td><td class="what">[^<]+</td>'
                        "<td>jawOpen ×0.90, mouthSmile_L ×0.30</td>", row), row
    assert re.search(rf'<tr data-key="{keys.names[1]}">(.*?)</tr>', table).group(1).endswith("<td><i>none</i></td>")
    assert "<h2>The rig&#x27;s own shapes over time (animation.glb)</h2>" in text
    assert len(re.findall(r'<img[^>]+src="data:image/png;base64,', text)) == 3  # sheet, weights, rig curves
    assert not (folder / "rig.png").exists()  # in the page only: the take folder's files stay as they were

    plain = make_take_folder(tmp_path / "plain", n_frames=30, n_missing=0)  # keys drive targets of their names
    text = write_take_extras(plain, progress=False, preview=False).report.read_text(encoding="utf-8")
    assert "Key shapes: the sculpt list" in text and 'id="map"' not in text


# --------------------------------------------------------------------------- what each key is (issue 36 item 12)

_SCORES = ("browInnerUp", "eyeBlinkLeft", "eyeBlinkRight", "jawOpen", "mouthSmileLeft", "mouthSmileRight",
           "mouthFunnel", "eyeLookInLeft", "_neutral")


def _scored_take(rng):
    """12 frames of made-up MediaPipe scores; frame 0 rests, frames 4 and 8 hold the planted expressions."""
    scores = rng.uniform(0.0, 0.03, (12, len(_SCORES)))
    at = {n: i for i, n in enumerate(_SCORES)}
    scores[4, [at["jawOpen"], at["mouthFunnel"], at["browInnerUp"]]] = (0.8, 0.35, 0.9)  # a brow raise as well
    scores[4, at["eyeLookInLeft"]] = 1.0  # gaze: never a key's description
    scores[8, [at["mouthSmileLeft"], at["eyeBlinkRight"]]] = (0.6, 0.5)
    scores[:, at["_neutral"]] = 0.9
    return Track(rng.normal(size=(12, 6, 2)), fps=25.0, blendshapes=scores, blendshape_names=_SCORES)


def _scored_keys(takes=("", "", "", "")):
    regions = {"upper": np.arange(3), "lower": np.arange(3, 6)}
    return KeyShapes(np.zeros((6, 2)), np.ones((4, 6, 2)), ("upper_00", "lower_00", "lower_01", "lower_01_mirror"),
                     [8, 4, 8, 8], ("upper", "lower", "lower", "lower"), regions, takes=takes,
                     mirror_of=("", "", "", "lower_01"))


def test_describe_keys_names_the_expressions_each_key_frame_rises_in():
    from keyshape.report import describe_keys

    track = _scored_take(np.random.default_rng(0))
    upper, jaw, smile, mirrored = describe_keys(_scored_keys(), track)
    # each key by its region's expressions only: frame 8's blink for the upper key, not its smile
    assert upper.startswith("brows and eyes: eyeBlinkRight +0.") and "mouth" not in upper
    # frame 4: the jaw first, the funnel second; the brows it raised too and the gaze are not the mouth's
    assert jaw.startswith("mouth and jaw: jawOpen +0.") and ", mouthFunnel +0." in jaw
    assert "brow" not in jaw and "eyeLook" not in jaw and "_neutral" not in jaw
    rise = track.blendshapes[4, 3] - track.blendshapes[0, 3]  # counted from the neutral frame (0)
    assert f"jawOpen {rise:+.2f}" in jaw
    assert smile.startswith("mouth and jaw: mouthSmileLeft +0.") and "Right" not in smile
    # the mirror: the source's rise with the sides swapped, and which key it mirrors
    assert mirrored == smile.replace("mouthSmileLeft", "mouthSmileRight") + " (lower_01 mirrored)"


def test_describe_keys_slight_and_unusual_expressions():
    """A key whose frame barely moves says "slight" and names that expression once; an expression
    far above its usual level over the take is named as unusual after the strongest ones."""
    from keyshape.report import describe_keys

    track = _scored_take(np.random.default_rng(2))
    scores = np.array(track.blendshapes)
    at = {n: i for i, n in enumerate(_SCORES)}
    scores[8, :] = scores[0, :]
    scores[8, at["eyeBlinkLeft"]] = scores[0, at["eyeBlinkLeft"]] + 0.05  # a slight blink, not seen elsewhere
    scores[:, at["mouthSmileLeft"]] += 0.5  # smiling throughout: the rise at frame 4 is nothing unusual
    scores[4, at["mouthSmileLeft"]] += 0.3
    track = Track(track.points, fps=25.0, blendshapes=scores, blendshape_names=_SCORES)
    upper, jaw, *_ = describe_keys(_scored_keys(), track)
    assert upper == f"brows and eyes: slight eyeBlinkLeft +{scores[8, 1] - scores[0, 1]:.2f}"
    assert jaw.startswith("mouth and jaw: jawOpen +0.") and jaw.count("mouthSmileLeft") <= 1
    scores[4, at["mouthFunnel"]] = scores[0, at["mouthFunnel"]] + 0.08  # small, but nowhere else in the take
    track = Track(track.points, fps=25.0, blendshapes=scores, blendshape_names=_SCORES)
    jaw = describe_keys(_scored_keys(), track)[1]
    assert jaw.endswith(f"; unusually mouthFunnel +{scores[4, 6] - scores[0, 6]:.2f}"), jaw


def test_describe_keys_without_the_key_frames_or_scores_says_the_region():
    from keyshape.report import describe_keys

    track = _scored_take(np.random.default_rng(1))
    other = describe_keys(_scored_keys(("b.mp4",) * 4), track, take="a.mp4")  # a key set from another take
    assert other == ("brows and eyes", "mouth and jaw", "mouth and jaw", "mouth and jaw (lower_01 mirrored)")
    assert describe_keys(_scored_keys(("a.mp4",) * 4), track, take="a.mp4")[1].startswith("mouth and jaw: jawOpen")
    plain = Track(track.points, fps=25.0)  # another tracker's landmarks: no scores
    assert describe_keys(_scored_keys(), plain) == other


def test_describe_keys_of_another_take_where_this_take_weighs_them_most():
    """A reused key set (run --keys): a key not from this take is read at this take's frame where its
    solved weight is largest, when that reaches 0.5, and says which video frame that is."""
    from keyshape.report import describe_keys

    scored = _scored_take(np.random.default_rng(3))
    track = Track(scored.points, 25.0, frame_index=np.arange(100, 112), time=np.arange(100, 112) / 25.0,
                  blendshapes=scored.blendshapes, blendshape_names=_SCORES)
    keys = _scored_keys(("b.mp4",) * 4)
    values = np.full((12, 4), 0.1)
    values[4, 1], values[8, 0] = 0.9, 0.3  # lower_00 weighs 0.9 at row 4; upper_00 never reaches 0.5
    values[6, 3] = 0.95  # a mirror is its source's reflection, not read at its own frame
    upper, jaw, smile, mirrored = describe_keys(keys, track, take="a.mp4", weights=Weights(values, keys.names, 25.0))
    assert upper == "brows and eyes" and smile == "mouth and jaw" and mirrored == "mouth and jaw (lower_01 mirrored)"
    assert jaw.startswith("mouth and jaw: jawOpen +0.") and jaw.endswith(" (as at video frame 104 of this take, "
                                                                        "weight 0.90)")
    assert jaw.split(" (as at")[0] == describe_keys(_scored_keys(), scored)[1]  # frame 4's own line


def test_the_demo_report_and_sheet_say_what_each_key_is(demo_out):
    """Every key of the demo's report has its line; the expressions it names are the ones the
    track's scores rise in most at the key's frame (within its region), checked from track.npz."""
    from keyshape.io.keys_json import load_keys
    from keyshape.io.track import load_track

    keys, track = load_keys(demo_out / "keys.json"), load_track(demo_out / "track.npz")
    page = (demo_out / "report.html").read_text()
    table = page[page.index('<table id="keys">'):page.index("</table>", page.index('<table id="keys">'))]
    lines = dict(re.findall(r'<tr data-key="([^"]+)"><td>[^<]+</td><td class="what">([^<]*)</td>', table))
    assert list(lines) == list(keys.names)
    scores, names = np.asarray(track.blendshapes), track.blendshape_names
    rest = scores[keys.neutral_frame]
    mouth = [i for i, n in enumerate(names) if n.startswith(("jaw", "mouth", "cheek", "nose", "tongue"))]
    brows_eyes = [i for i, n in enumerate(names) if n.startswith(("brow", "eyeBlink", "eyeSquint", "eyeWide"))]
    for k, name in enumerate(keys.names):
        line = lines[name]
        word, ours = ("mouth and jaw", mouth) if keys.key_regions[k] == "lower" else ("brows and eyes", brows_eyes)
        assert line.startswith(word + ": "), line
        if keys.mirror_of[k]:
            assert line.endswith(f"({keys.mirror_of[k]} mirrored)"), line
            continue
        rise = scores[keys.frames[k]] - rest
        top = names[max(ours, key=lambda i: rise[i])]
        first = line.split(": ", 1)[1].split(",")[0].split(";")[0]
        if rise[names.index(top)] >= 0.1:  # the strongest rise comes first (a pair: both sides of it)
            assert first.startswith((top, top.replace("Right", "Left"))), (line, top)
        named = set(re.findall(r"\b([a-z]+[A-Z]\w*?)(?:\+Right)? [+-]\d", line))
        assert named and named <= {names[i] for i in ours}, line  # the region's own expressions only
    assert len(set(lines.values())) >= len(lines) // 2  # lines that tell keys apart, not one per region
