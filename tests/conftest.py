"""Shared fixtures: the embedded real clip, its track (computed once per session), tiny videos."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"


@pytest.fixture(scope="session")
def demo_clip() -> Path:
    return Path(str(resources.files("keyshape").joinpath("data/WolfgangLanger_Pexels.mp4")))


@pytest.fixture(scope="session")
def real_track(demo_clip):
    """The real clip tracked with the real vendored MediaPipe model (no mocks)."""
    from keyshape.capture import track_video

    return track_video(demo_clip, progress=False)


def write_video(path: Path, frames: np.ndarray, fps: int = 25) -> Path:
    """Encode ``frames`` (n, height, width, 3) uint8 as an H.264 MP4 with PyAV."""
    import av

    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=fps)
        stream.width, stream.height = frames.shape[2], frames.shape[1]
        stream.pix_fmt = "yuv420p"
        for image in frames:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        out.mux(stream.encode())
    return path


@pytest.fixture
def faceless_video(tmp_path) -> Path:
    """A real H.264 file of smooth noise: decodable, with no face in it."""
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (12, 16, 3)).astype(np.uint8)
    frames = np.stack([np.kron(np.roll(base, i, axis=1), np.ones((8, 8, 1), np.uint8)) for i in range(10)])
    return write_video(tmp_path / "noise.mp4", frames)
