"""Frame sources: video files (PyAV, the only decoder import) and folders of images.

``iter_frames`` yields ``(timestamp_ms, rgb)`` with rotation metadata applied, optionally for a
frame range only; ``prefetch`` decodes in a background thread so decoding overlaps tracking.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..exceptions import InputError

__all__ = ["VideoInfo", "probe", "iter_frames", "prefetch", "IMAGE_SUFFIXES", "open_stream", "decode_stream"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
FOLDER_FPS = 30.0


@dataclass(frozen=True)
class VideoInfo:
    """What a frame source says about itself (size after rotation)."""

    fps: float
    width: int
    height: int
    n_frames: int  # 0 when the container does not say
    rotation: int = 0  # degrees counter-clockwise applied to decoded frames


def _images(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError(f"{folder}: folder has no images ({', '.join(IMAGE_SUFFIXES)})")
    return files


def _open(path: Path):
    import av

    if not path.exists():
        raise InputError(f"{path}: file not found")
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, ValueError) as exc:
        raise InputError(f"{path}: not a video PyAV can open ({exc.__class__.__name__})") from None
    if not container.streams.video:
        container.close()
        raise InputError(f"{path}: has no video stream")
    return container


def _read_image(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("RGB"))
    except (OSError, UnidentifiedImageError) as exc:
        raise InputError(f"{path}: not a readable image ({exc.__class__.__name__})") from None


def _first_rotation(container) -> int:
    import av

    try:
        frame = next(container.decode(video=0))
    except (StopIteration, av.error.FFmpegError):
        return 0
    return int(round(getattr(frame, "rotation", 0) or 0)) % 360


def probe(path: str | Path, *, fps: float | None = None) -> VideoInfo:
    """Frame rate, size (after rotation) and frame count of a video file or image folder.

    ``fps`` overrides the rate (image folders default to 30 frames/s).
    """
    path = Path(path)
    if path.is_dir():
        files = _images(path)
        height, width = _read_image(files[0]).shape[:2]
        return VideoInfo(float(fps or FOLDER_FPS), width, height, len(files))
    with _open(path) as container:
        stream = container.streams.video[0]
        rate = float(fps or stream.average_rate or stream.guessed_rate or 30)
        rotation = _first_rotation(container)
        width, height = stream.width, stream.height
        if rotation in (90, 270):
            width, height = height, width
        return VideoInfo(rate, width, height, int(stream.frames or 0), rotation)


def _rotate(rgb: np.ndarray, rotation: int) -> np.ndarray:
    """Undo the display rotation: frames come out upright."""
    return np.ascontiguousarray(np.rot90(rgb, k=rotation // 90)) if rotation else rgb


def frame_pts(path: str | Path) -> np.ndarray | None:
    """Presentation times of every frame of a video file, in stream units, sorted: ``(n_frames,) int``.

    Read from the packets (nothing is decoded). None for image folders and for streams whose packets
    do not all carry a time, which cannot be sought by frame number.
    """
    path = Path(path)
    if path.is_dir():
        return None
    with _open(path) as container:
        pts = [packet.pts for packet in container.demux(container.streams.video[0]) if packet.size]
    if not pts or any(p is None for p in pts):
        return None
    return np.sort(np.array(pts, dtype=np.int64))


def _seek(container, stream, pts: np.ndarray | None, start: int) -> bool:
    """Seek to the keyframe at or before frame ``start`` (with its times ``pts``); whether it did."""
    if pts is None or start <= 0 or start >= len(pts):
        return False
    container.seek(int(pts[start]), stream=stream, backward=True, any_frame=False)
    return True  # frame numbers come from the presentation times from here on


def _decode_video(path: Path, fps: float | None, start: int = 0,
                  pts: np.ndarray | None = None) -> Iterator[tuple[int, int, np.ndarray]]:
    import av

    with _open(path) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        rate = float(fps or stream.average_rate or stream.guessed_rate or 30)
        sought = _seek(container, stream, pts, start)
        rgb24 = av.video.reformatter.VideoReformatter()  # one for all frames: to_ndarray sets one up per frame
        try:
            for decoded, frame in enumerate(container.decode(stream)):
                index = decoded
                if sought:  # after a seek, a frame's number is the rank of its time
                    index = int(np.searchsorted(pts, frame.pts)) if frame.pts is not None else -1
                    if index < start:
                        continue
                if fps is None and frame.pts is not None and frame.time_base is not None:
                    ms = int(round(float(frame.pts * frame.time_base) * 1000))
                else:
                    ms = int(round(index * 1000 / rate))
                rotation = int(round(getattr(frame, "rotation", 0) or 0)) % 360
                yield index, ms, _rotate(rgb24.reformat(frame, format="rgb24").to_ndarray(), rotation)
        except av.error.FFmpegError as exc:
            raise InputError(f"{path}: video could not be decoded ({exc.__class__.__name__})") from None


def _decode_folder(folder: Path, fps: float | None, start: int = 0) -> Iterator[tuple[int, int, np.ndarray]]:
    rate = float(fps or FOLDER_FPS)
    size = None
    for index, file in enumerate(_images(folder)):
        if index < start:  # the images before the range are not read
            continue
        rgb = _read_image(file)
        if size is not None and rgb.shape != size:
            raise InputError(f"{file}: image is {rgb.shape[1]}x{rgb.shape[0]} but the first one is "
                             f"{size[1]}x{size[0]}")
        size = rgb.shape
        yield index, int(round(index * 1000 / rate)), rgb


def iter_frames(path: str | Path, *, start: int = 0, end: int | None = None,
                fps: float | None = None, pts: np.ndarray | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(timestamp_ms, rgb)`` for frames ``start <= i < end`` of a video or image folder.

    ``rgb`` is (height, width, 3) uint8, upright (rotation metadata applied). Timestamps come
    from the stream's presentation times and are strictly increasing (MediaPipe's VIDEO mode
    requires it). ``pts``: the video's :func:`frame_pts`, to seek to the keyframe before
    ``start`` instead of decoding every frame before it.
    """
    path = Path(path)
    source = _decode_folder(path, fps, start) if path.is_dir() else _decode_video(path, fps, start, pts)
    last = -1
    for index, stamp, rgb in source:
        if end is not None and index >= end:
            break
        ms = max(stamp, last + 1)
        last = ms
        if index >= start:
            yield ms, rgb


_DONE = object()


def prefetch(frames: Iterable, *, depth: int = 8) -> Iterator:
    """Run ``frames`` in a background thread, ``depth`` items ahead; errors are re-raised here.

    Decoding (PyAV releases the GIL) then overlaps with the consumer's work on the other core.
    """
    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def produce():
        try:
            for item in frames:
                if stop.is_set():
                    return
                items.put(item)
            items.put(_DONE)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer thread, which re-raises it
            items.put(exc)

    worker = threading.Thread(target=produce, daemon=True, name="keyshape-decode")
    worker.start()
    try:
        while (item := items.get()) is not _DONE:
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        while worker.is_alive():
            try:
                items.get_nowait()
            except queue.Empty:
                worker.join(timeout=0.05)


def open_stream(source: str, *, format: str | None = None, options: dict | None = None,
                what: str = "stream", timeout: float = 10.0):
    """A camera or stream opened for live decoding (``keyshape live``).

    Parameters
    ----------
    source : device (``/dev/video0``, ``0`` with avfoundation, ``video=NAME``) or URL
    format : FFmpeg input format (``v4l2``, ``avfoundation``, ``dshow``, ``lavfi``, ...) or None
    options : input options such as ``{"video_size": "640x360", "framerate": "30"}``
    what : what ``source`` is, for the error message

    Returns
    -------
    (container, fps, (width, height)) : fps is 0 when the input does not say
    """
    import av

    try:
        container = av.open(source, format=format, options=options or None, timeout=timeout)
    except (av.error.FFmpegError, OSError, ValueError) as exc:
        raise InputError(f"{source}: cannot open this {what} ({exc})") from None
    if not container.streams.video:
        container.close()
        raise InputError(f"{source}: this {what} has no video")
    stream = container.streams.video[0]
    return container, float(stream.average_rate or stream.guessed_rate or 0), (stream.width, stream.height)


def decode_stream(container) -> Iterator[tuple[float | None, np.ndarray]]:
    """``(media seconds or None, rgb)`` of every frame of an :func:`open_stream` container, as decoded."""
    for frame in container.decode(container.streams.video[0]):
        yield (float(frame.time) if frame.time is not None else None), frame.to_ndarray(format="rgb24")
