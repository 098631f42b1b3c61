"""Video decoding with PyAV: the only module that imports ``av`` for reading."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..exceptions import InputError

__all__ = ["VideoInfo", "probe", "iter_frames"]


@dataclass(frozen=True)
class VideoInfo:
    """What a video stream says about itself."""

    fps: float
    width: int
    height: int
    n_frames: int  # 0 when the container does not say


def _open(path: Path):
    import av

    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, ValueError) as exc:
        raise InputError(f"{path}: not a video PyAV can open ({exc.__class__.__name__})") from None
    if not container.streams.video:
        container.close()
        raise InputError(f"{path}: has no video stream")
    return container


def probe(path: str | Path) -> VideoInfo:
    """Frame rate, size and frame count of the first video stream of ``path``."""
    path = Path(path)
    with _open(path) as container:
        stream = container.streams.video[0]
        rate = stream.average_rate or stream.guessed_rate or 30
        return VideoInfo(float(rate), stream.width, stream.height, int(stream.frames or 0))


def iter_frames(path: str | Path) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(timestamp_ms, rgb)`` for every frame; ``rgb`` is (height, width, 3) uint8.

    Timestamps come from the stream's presentation times and are made strictly
    increasing (MediaPipe's VIDEO mode requires it).
    """
    import av

    path = Path(path)
    with _open(path) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        rate = float(stream.average_rate or stream.guessed_rate or 30)
        last = -1
        try:
            for index, frame in enumerate(container.decode(stream)):
                if frame.pts is not None and frame.time_base is not None:
                    ms = int(round(float(frame.pts * frame.time_base) * 1000))
                else:
                    ms = int(round(index * 1000 / rate))
                ms = max(ms, last + 1)
                last = ms
                yield ms, frame.to_ndarray(format="rgb24")
        except av.error.FFmpegError as exc:
            raise InputError(f"{path}: video could not be decoded ({exc.__class__.__name__})") from None
