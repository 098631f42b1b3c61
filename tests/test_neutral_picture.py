"""A neutral from a file of its own (``--neutral FILE``: a still image or a clip of the actor at rest):
the contact sheets show that file's picture, not the take's frame of the same number, and say so."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from keyshape.app import contact_sheet, write_sculpt_kit
from keyshape.containers import KeyShapes, Track
from keyshape.exceptions import InputError
from keyshape.report import separate_neutral

from conftest import dotted_take, write_video

N_FRAMES, RED = 14, (250, 20, 20)
ROBOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "robot-expressive" / "RobotExpressive.glb"


@pytest.fixture
def take(tmp_path):
    """A 14-frame video of white dots, its track and three keys whose neutral is frame 20 of
    ``rest.mp4`` (a clip longer than the take: frame 20 of the take does not exist)."""
    points, video, regions, deltas = dotted_take(tmp_path / "take.mp4", N_FRAMES)
    keys = KeyShapes(points[0], deltas, ("upper_00", "upper_01", "lower_00"), [3, 6, 9],
                     ("upper", "upper", "lower"), regions, ("take.mp4",) * 3, 20, "rest.mp4")
    return keys, Track(points, fps=25.0), video


def _red_picture(monkeypatch, keys, calls):
    """``neutral_picture`` stood in for (no tracker): a red picture with the neutral's landmarks."""
    import keyshape.report

    def picture(path, frame=0):
        calls.append((Path(path).name, frame))
        return np.full((80, 112, 3), RED, np.uint8), keys.neutral + 5.0

    monkeypatch.setattr(keyshape.report, "neutral_picture", picture)


def test_the_sculpt_sheet_shows_the_neutral_file_not_the_takes_frame(take, tmp_path, monkeypatch):
    from PIL import Image

    keys, track, video = take
    assert separate_neutral(keys) and not separate_neutral(dataclasses.replace(keys, neutral_take="take.mp4"))
    calls = []
    _red_picture(monkeypatch, keys, calls)
    sheet = np.asarray(Image.open(contact_sheet(keys, track, video, tmp_path / "keys.png", cell=120,
                                                neutral_source=tmp_path / "rest.mp4")))
    assert calls == [("rest.mp4", 20)]  # the clip's frame neutral_frame (the take has no frame 20)
    for top in (30, 184):  # each region's row starts with the neutral: the rest clip's (red) picture
        neutral, key = sheet[top:top + 120, :120].astype(int), sheet[top:top + 120, 120:240].astype(int)
        assert (np.abs(neutral - RED).sum(axis=2) < 30).mean() > 0.5
        assert (np.abs(key - RED).sum(axis=2) < 30).mean() < 0.01


def test_without_the_file_the_neutral_tile_is_its_shape_labelled_with_its_source(take, tmp_path):
    from PIL import Image

    keys, track, video = take
    plain = np.asarray(Image.open(contact_sheet(keys, track, video, tmp_path / "keys.png", cell=120)))
    neutral = plain[30:150, :120]
    assert (neutral == 40).all(axis=2).mean() > 0.8  # the dark "no picture" square with the landmarks
    assert (neutral != 40).any(axis=2).sum() > 10
    # a still image: the tile says so, and its neutral_frame is no frame of the take either
    still = dataclasses.replace(keys, neutral_take="rest.png", neutral_frame=0)
    assert np.asarray(Image.open(contact_sheet(still, track, video, tmp_path / "still.png", cell=120))).shape \
        == plain.shape


@pytest.mark.skipif(not ROBOT.is_file(), reason=f"{ROBOT} not present (shared data)")
def test_the_kit_readme_names_the_neutral_file(take, tmp_path, monkeypatch):
    keys, track, video = take
    calls = []
    _red_picture(monkeypatch, keys, calls)
    kit = write_sculpt_kit(keys, ROBOT, tmp_path / "kit", track=track, video=video,
                           neutral_source=tmp_path / "rest.mp4")
    readme = kit.readme.read_text()
    assert "The neutral is frame 20 of `rest.mp4`, a separate clip of the actor at rest" in readme
    assert "not a frame of `take.mp4`" in readme and calls == [("rest.mp4", 20)]
    still = dataclasses.replace(keys, neutral_take="rest.png", neutral_frame=0)
    kit = write_sculpt_kit(still, ROBOT, tmp_path / "kit2", track=track, video=video)
    assert "The neutral is the still image `rest.png` of the actor at rest" in kit.readme.read_text()
    own = dataclasses.replace(keys, neutral_take="take.mp4", neutral_frame=2)
    assert "The neutral frame is 2." in write_sculpt_kit(own, ROBOT, tmp_path / "kit3", track=track,
                                                          video=video).readme.read_text()
    with pytest.raises(InputError, match="the keys use frame 20"):  # a neutral of the take must be in it
        write_sculpt_kit(dataclasses.replace(keys, neutral_take="take.mp4"), ROBOT, tmp_path / "kit4",
                         track=track, video=video)


def test_the_report_sheet_shows_the_neutral_picture(take, tmp_path):
    from PIL import Image

    from keyshape.report import plots

    keys, track, _ = take
    images = {f: np.zeros((80, 112, 3), np.uint8) for f in (3, 6, 9)}
    red = np.full((80, 112, 3), RED, np.uint8), keys.neutral + 5.0
    with_picture = np.asarray(Image.open(plots.contact_sheet(keys, track, images, tmp_path / "a.png", take="take.mp4",
                                                             neutral=red)).convert("RGB")).astype(int)
    without = np.asarray(Image.open(plots.contact_sheet(keys, track, images, tmp_path / "b.png",
                                                        take="take.mp4")).convert("RGB")).astype(int)
    reddish = lambda image: (np.abs(image - RED).sum(axis=2) < 60).sum()  # noqa: E731
    assert reddish(with_picture) > 500 and reddish(without) == 0


def test_take_json_keeps_the_neutral_source(take, tmp_path):
    from keyshape.io.take import load_take_info, save_take_info

    keys, track, video = take
    save_take_info(tmp_path / "take.json", video=video, track=track, keys=keys, neutral=tmp_path / "rest.mp4")
    assert load_take_info(tmp_path)["neutral_source"] == str((tmp_path / "rest.mp4").resolve())
    info = json.loads((tmp_path / "take.json").read_text())
    (tmp_path / "take.json").write_text(json.dumps({**info, "neutral_source": 3}))
    with pytest.raises(InputError, match="neutral_source"):
        load_take_info(tmp_path)


def test_run_records_the_neutral_file_only_when_the_keys_come_from_it(tmp_path):
    from keyshape.app import RunOptions
    from keyshape.app._run import _neutral_file

    keys = KeyShapes(np.zeros((2, 2)), np.ones((1, 2, 2)), ("a",), [4], ("lower",), {"lower": [0, 1]},
                     ("take.mp4",), 0, "rest.png")
    assert _neutral_file(RunOptions(neutral=tmp_path / "rest.png"), keys) == tmp_path / "rest.png"
    assert _neutral_file(RunOptions(neutral=tmp_path / "other.png"), keys) is None  # keys reused from elsewhere
    assert _neutral_file(RunOptions(neutral=3), keys) is None


@pytest.mark.slow
def test_neutral_picture_of_a_still_and_of_a_clip(demo_clip, tmp_path):
    """The real tracker on a still image and on a short clip cut from the embedded clip."""
    from PIL import Image

    from keyshape.capture.video import iter_frames
    from keyshape.report import neutral_picture

    frames = [rgb for _, rgb in iter_frames(demo_clip, start=225, end=231)]
    Image.fromarray(frames[4]).save(tmp_path / "rest.png")
    clip = write_video(tmp_path / "rest.mp4", np.stack(frames), fps=25)
    rgb, points = neutral_picture(tmp_path / "rest.png")
    assert np.array_equal(rgb, frames[4]) and points.shape == (478, 2) and np.isfinite(points).all()
    rgb3, points3 = neutral_picture(clip, 3)
    assert rgb3.shape == frames[3].shape and np.abs(rgb3.astype(int) - frames[3]).mean() < 8  # H.264
    assert np.abs(rgb3.astype(int) - frames[0]).mean() > np.abs(rgb3.astype(int) - frames[3]).mean()
    assert np.isfinite(points3).all() and neutral_picture(tmp_path / "gone.png") is None
    assert neutral_picture(clip, 50) is None


def test_the_report_of_a_take_with_a_neutral_file_shows_its_picture(tmp_path, monkeypatch):
    """``take.json``'s ``neutral_source``: ``keyshape report`` asks for that file's frame, not the take's."""
    import keyshape.report._take as report_take
    from keyshape.io.keys_json import load_keys, save_keys
    from keyshape.io.take import load_take_info, save_take_info
    from keyshape.io.track import load_track
    from keyshape.report import write_take_extras

    from test_render import make_take_folder

    folder = make_take_folder(tmp_path / "take")
    keys, track = load_keys(folder / "keys.json"), load_track(folder / "track.npz")
    video = Path(load_take_info(folder)["video"])
    rest = dataclasses.replace(keys, neutral_take="rest.png", neutral_frame=0, takes=("",) * keys.n_keys)
    save_keys(rest, folder / "keys.json")
    save_take_info(folder / "take.json", video=video, track=track, keys=rest, neutral=tmp_path / "rest.png")
    calls = []

    def picture(path, frame=0):
        calls.append((Path(path).name, frame))
        return np.full((480, 640, 3), RED, np.uint8), track.points[0, :, :2]

    monkeypatch.setattr(report_take, "neutral_picture", picture)
    extras = write_take_extras(folder, progress=False, preview=False)
    assert calls == [("rest.png", 0)]
    from PIL import Image

    sheet = np.asarray(Image.open(extras.pictures["keyshapes"]).convert("RGB")).astype(int)
    assert (np.abs(sheet - RED).sum(axis=2) < 60).sum() > 500
