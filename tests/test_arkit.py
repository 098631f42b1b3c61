import numpy as np

from keyshape.cli import main
from keyshape.io.livelink import read_livelink_csv
from keyshape.io.track import save_track


def test_mediapipe_scores_as_live_link(real_track, tmp_path):
    track_path = save_track(real_track, tmp_path / "t.npz")
    out = tmp_path / "take.csv"
    assert main(["arkit", str(track_path), "-o", str(out), "-q"]) == 0
    take = read_livelink_csv(out, fps=real_track.fps)
    names = list(real_track.blendshape_names)
    got = dict(zip(take.weights.names, take.weights.values.T))
    assert take.weights.n_frames == real_track.n_frames
    assert np.abs(take.rotations[:, :3]).max() > 0.01  # the head turns in this clip
    for arkit, live in [("jawOpen", "JawOpen"), ("eyeBlinkLeft", "EyeBlinkLeft"),
                        ("mouthSmileRight", "MouthSmileRight")]:
        np.testing.assert_allclose(got[live], real_track.blendshapes[:, names.index(arkit)], atol=1e-4)
    assert np.abs(got["TongueOut"]).max() == 0  # MediaPipe has no tongue score


def test_track_without_scores_is_a_clear_error(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, points=np.zeros((3, 478, 3)), fps=30.0)
    assert main(["arkit", str(path), "-o", str(tmp_path / "x.csv"), "-q"]) == 1
    assert not (tmp_path / "x.csv").exists()
