from pathlib import Path

import numpy as np
import pytest

from keyshape.capture import probe, track_video
from keyshape.exceptions import InputError, NoFaceError


def test_real_clip_is_tracked(real_track):
    assert real_track.points.shape == (472, 478, 3)
    assert real_track.valid.mean() >= 0.95
    assert real_track.fps == pytest.approx(23.976, rel=1e-3)
    assert real_track.image_size == (640, 360)
    assert real_track.blendshapes.shape == (472, 52)
    assert "jawOpen" in real_track.blendshape_names
    assert real_track.head_matrix.shape == (472, 4, 4)
    # landmarks in pixels: the face centre is inside the picture, the face a sensible size
    valid = real_track.points[real_track.valid]
    centre = valid[..., :2].mean(axis=1)
    assert (centre > 0).all() and (centre < (640, 360)).all()
    width = np.ptp(valid[..., 0], axis=1)
    assert (width > 50).all() and (width < 640).all()


def test_real_clip_moves(real_track):
    """The clip is expressive: the actor smiles and blinks, and the lips part."""
    for name in ("mouthSmileLeft", "eyeBlinkLeft"):
        score = real_track.blendshapes[:, real_track.blendshape_names.index(name)]
        assert np.nanmax(score) - np.nanmin(score) > 0.5, name
    gap = np.linalg.norm(real_track.points[:, 13, :2] - real_track.points[:, 14, :2], axis=1)
    assert np.nanmax(gap) > 3 * np.nanmin(gap) + 1


def test_video_without_face(faceless_video):
    with pytest.raises(NoFaceError, match=r"noise\.mp4: no face found in any of its 10 frames"):
        track_video(faceless_video, progress=False)


def test_missing_and_non_video_files(tmp_path):
    with pytest.raises(InputError, match=r"nope\.mp4: file not found"):
        probe(tmp_path / "nope.mp4")
    fake = tmp_path / "fake.mp4"
    fake.write_text("this is not a video\n" * 20)
    with pytest.raises(InputError, match=r"fake\.mp4: not a video"):
        track_video(fake, progress=False)


def test_sigterm_while_the_landmarker_is_made_closes_it_then_terminates(monkeypatch):
    """MediaPipe makes the landmarker on a thread of its own while the caller waits: SIGTERM
    landing in that wait used to leave it made but never closed (its graph went on running and
    logging after the command's last line, and could keep the process from exiting)."""
    import signal

    from mediapipe.tasks.python import vision

    from keyshape.capture.mediapipe import MediaPipeTracker
    from keyshape.cli._main import _terminate_as_interrupt
    from keyshape.exceptions import Terminated

    made, closed = [], []
    create = vision.FaceLandmarker.create_from_options

    def create_then_sigterm(options):
        landmarker = create(options)
        made.append(landmarker)
        close = landmarker.close
        landmarker.close = lambda: (closed.append(landmarker), close())
        signal.raise_signal(signal.SIGTERM)  # as if it came while MediaPipe was still at work
        return landmarker

    monkeypatch.setattr(vision.FaceLandmarker, "create_from_options", staticmethod(create_then_sigterm))
    try:
        with _terminate_as_interrupt(), pytest.raises(Terminated), MediaPipeTracker():
            pytest.fail("the tracker was handed out after SIGTERM")
        assert closed == made != []
    finally:
        for landmarker in set(made) - set(closed):
            landmarker.close()


def test_an_interrupted_removal_of_the_spools_still_removes_them(demo_clip, tmp_path, monkeypatch):
    """SIGTERM (or Ctrl-C) landing while the tracker removes its spool folder: the removal is finished."""
    import shutil

    from keyshape.capture import track_to_file
    from keyshape.exceptions import Terminated

    rmtree = shutil.rmtree
    interrupted = []

    def rmtree_interrupted(path, *args, **kwargs):
        if "keyshape-track-" in str(path) and not interrupted:
            interrupted.append(path)
            next(p for p in Path(path).rglob("*") if p.is_file()).unlink()  # part of it is gone
            raise Terminated()
        return rmtree(path, *args, **kwargs)

    monkeypatch.setattr(shutil, "rmtree", rmtree_interrupted)
    with pytest.raises(Terminated):
        track_to_file(demo_clip, tmp_path / "t.npz", start=24, end=28, progress=False)
    assert interrupted and sorted(p.name for p in tmp_path.iterdir()) == ["t.npz"]
