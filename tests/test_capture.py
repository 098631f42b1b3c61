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
