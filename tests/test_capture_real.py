"""Capture on real footage: faces that leave and enter, no face, two people, rotation, ranges."""

from __future__ import annotations

import numpy as np
import pytest

from keyshape.capture import track_video
from keyshape.capture.filters import gap_report
from keyshape.cli import main
from keyshape.exceptions import NoFaceError
from keyshape.io.weights_csv import load_weights_csv

from conftest import read_frames, write_video


@pytest.mark.parametrize("clip", ["face_noface.mov", "noface_face.mov"])
def test_face_leaving_and_entering(clips, tmp_path, clip):
    out = tmp_path / "out"
    assert main(["run", str(clips / clip), "-o", str(out), "-q", "--count", "4"]) == 0
    from keyshape.io.track import load_track

    track = load_track(out / "track.npz")
    valid = track.valid
    assert 0.1 < valid.mean() < 0.95, valid.mean()  # both faces and gaps
    # NaN frames where the face is absent: the second half of face_noface, the first of noface_face
    absent, present = (slice(80, 160), slice(0, 60)) if clip == "face_noface.mov" else \
        (slice(0, 85), slice(110, 165))
    assert not valid[absent].any() and valid[present].all()
    assert np.isnan(track.points[absent]).all()
    report = gap_report(valid)
    assert report.longest >= 80 and report.held
    weights = load_weights_csv(out / "weights.csv")
    assert weights.n_frames == track.n_frames
    assert np.isfinite(weights.values[valid]).all()
    assert (out / "animation.glb").stat().st_size > 1000


def test_no_face_at_all(clips):
    with pytest.raises(NoFaceError, match=r"no_face\.mp4: no face found"):
        track_video(clips / "no_face.mp4", progress=False)


def test_two_people_keep_one_identity(clips, demo_clip, tmp_path):
    left = read_frames(clips / "single_face.mp4", 72)
    right = read_frames(demo_clip, 72)
    assert left.shape == right.shape
    both = write_video(tmp_path / "two.mp4", np.concatenate([left, right], axis=2), fps=24)
    track = track_video(both, progress=False)
    centres = track.points[track.valid, :, 0].mean(axis=1)
    assert track.valid.mean() > 0.9
    on_left = centres < 640
    assert on_left.all() or (~on_left).all(), "jumped between people"
    other = track_video(both, face=1, progress=False)
    centres_other = other.points[other.valid, :, 0].mean(axis=1)
    assert other.valid.mean() > 0.9
    assert ((centres_other < 640) != on_left[0]).all(), "--face 1 must follow the other person"


def test_rotation_metadata_is_honoured(demo_clip, real_track, tmp_path):
    import av

    frames = read_frames(demo_clip, 24)
    stored = np.ascontiguousarray(np.rot90(frames, k=-1, axes=(1, 2)))  # stored turned clockwise
    path = tmp_path / "rotated.mp4"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=24)
        stream.width, stream.height = stored.shape[2], stored.shape[1]
        stream.pix_fmt = "yuv420p"
        stream.set_display_rotation(90)  # display: turn back counter-clockwise
        for image in stored:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        out.mux(stream.encode())
    track = track_video(path, progress=False)
    assert track.image_size == (640, 360)
    err = np.linalg.norm(track.points[:, :, :2] - real_track.points[:24, :, :2], axis=2)
    assert np.nanmedian(err) < 4.0


def test_frame_range_and_image_folder(demo_clip, real_track, tmp_path):
    part = track_video(demo_clip, start=100, end=130, progress=False)
    assert part.n_frames == 30
    err = np.linalg.norm(part.points[5:, :, :2] - real_track.points[105:130, :, :2], axis=2)
    assert np.nanmedian(err) < 4.0
    from PIL import Image

    folder = tmp_path / "frames"
    folder.mkdir()
    for i, rgb in enumerate(read_frames(demo_clip, 12)):
        Image.fromarray(rgb).save(folder / f"{i:04d}.png")
    images = track_video(folder, fps=24, progress=False)
    assert images.n_frames == 12 and images.fps == 24 and images.valid.all()


def test_one_euro_option_smooths_the_landmarks(demo_clip, real_track):
    filtered = track_video(demo_clip, end=100, one_euro={"min_cutoff": 1.0, "beta": 0.05}, progress=False)
    jitter = lambda p: np.abs(np.diff(p[:, :, :2], 2, axis=0)).mean()  # noqa: E731
    assert jitter(filtered.points) < 0.8 * jitter(real_track.points[:100])
    drift = np.linalg.norm(filtered.points[:, :, :2] - real_track.points[:100, :, :2], axis=2)
    assert np.median(drift) < 3.0  # smoothing, not moving the face
