"""Live frame sources: a camera, a video file played as a camera would deliver it, or a stream.

Each source decodes in a background thread (PyAV releases the GIL while decoding) and posts
every frame into a :class:`Mailbox` that holds only the newest one. The live loop takes the
newest frame when it is ready for the next; a frame replaced before the loop took it is
*dropped* and counted. So a loop that falls behind skips frames instead of queueing them up:
the lag never grows.

* **camera** — ``0`` (or any number), ``/dev/video0``: PyAV's ``v4l2`` input on Linux,
  ``avfoundation`` on macOS; ``video=NAME`` is DirectShow on Windows. The camera paces itself.
* **file** — any video PyAV can open, delivered at its own frame rate: frame ``i`` arrives at
  ``start + pts_i``, as a camera would deliver it, however fast the machine could decode it.
* **stream** — a URL PyAV opens (``rtsp://``, ``udp://``, ``http://``, ...), delivered as it comes.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..capture.video import decode_stream, iter_frames, open_stream, probe
from ..exceptions import InputError

__all__ = ["SourceFrame", "Mailbox", "FrameSource", "open_source", "camera_input", "pin_thread"]

MAX_DRIFT = 1.0  # seconds a stream may run ahead of or behind its own clock before it is re-anchored


@dataclass(frozen=True, eq=False)
class SourceFrame:
    """One frame as the source delivered it: ``index`` counts every frame the source produced,
    ``time`` is its media time (s), ``arrival`` the ``time.perf_counter()`` of its delivery."""

    index: int
    time: float
    arrival: float
    rgb: np.ndarray


class Mailbox:
    """A one-frame slot between the source thread and the loop; an unread frame replaced is a drop."""

    def __init__(self):
        self._ready = threading.Condition()
        self._frame: SourceFrame | None = None
        self.closed = False
        self.error: str | None = None  # why the source stopped, when it failed
        self.delivered = 0
        self.dropped = 0

    def put(self, frame: SourceFrame) -> None:
        with self._ready:
            if self._frame is not None:
                self.dropped += 1
            self._frame = frame
            self.delivered += 1
            self._ready.notify()

    def close(self, error: str | None = None) -> None:
        with self._ready:
            self.closed = True
            self.error = error
            self._ready.notify()

    @property
    def pending(self) -> int:
        """1 while a frame waits to be taken, else 0."""
        return int(self._frame is not None)

    def get(self, timeout: float = 0.1) -> SourceFrame | None:
        """The newest frame, waiting up to ``timeout`` s; None if none came (see ``closed``)."""
        with self._ready:
            if self._frame is None and not self.closed:
                self._ready.wait(timeout)
            frame, self._frame = self._frame, None
            return frame


def camera_input(spec: str) -> tuple[str, str] | None:
    """``(device, PyAV format)`` when ``spec`` names a camera, else None.

    Examples
    --------
    >>> camera_input("/dev/video2"), camera_input("clip.mp4")
    (('/dev/video2', 'v4l2'), None)
    """
    if spec.startswith("/dev/video"):
        return spec, "v4l2"
    if spec.startswith("video="):
        return spec, "dshow"
    if spec.isdigit():
        if sys.platform == "darwin":
            return spec, "avfoundation"
        if sys.platform.startswith("linux"):
            return f"/dev/video{spec}", "v4l2"
        raise InputError(f"camera {spec}: on Windows name the camera as video=NAME (DirectShow)")
    return None


class FrameSource:
    """A started source posts frames into ``mailbox`` until it ends, fails or is stopped.

    Attributes
    ----------
    kind : "camera", "file" or "stream"
    name : str
    fps : float (the stated rate; cameras may deliver at another)
    size : (width, height)
    mailbox : Mailbox
    """

    def __init__(self, spec: str, *, size: tuple[int, int] | None = None, fps: float | None = None,
                 input_format: str | None = None):
        """``size`` and ``fps`` are asked of a camera; ``fps`` plays a file at that rate instead of its own."""
        self.spec = str(spec)
        self.mailbox = Mailbox()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._options = {}
        if size:
            self._options["video_size"] = f"{size[0]}x{size[1]}"
        if fps:
            self._options["framerate"] = f"{fps:g}"
        camera = camera_input(self.spec) if input_format is None else (self.spec, input_format)
        path = Path(self.spec)
        if camera is not None:
            self.kind, (self.device, self.format) = "camera", camera
        elif "://" in self.spec:
            self.kind, self.device, self.format = "stream", self.spec, None
        elif path.is_file():
            self.kind, self.device, self.format = "file", self.spec, None
        else:
            raise InputError(f"{self.spec}: not a camera (0, /dev/video0), a video file or a stream URL")
        self.name = path.name if self.kind == "file" else self.spec
        self._rate = fps if self.kind == "file" else None  # a file played at another rate
        self.fps, self.size = self._probe(fps)

    def _probe(self, fps: float | None) -> tuple[float, tuple[int, int]]:
        if self.kind == "file":
            info = probe(self.device, fps=fps)
            return info.fps, (info.width, info.height)
        self._container, rate, size = open_stream(self.device, format=self.format, options=self._options,
                                                  what=self.kind)
        return float(fps or rate or 30), size

    def start(self, *, cpu: int | None = None) -> Mailbox:
        """Start delivering frames (in a thread, on core ``cpu`` if given); returns the mailbox."""
        target = self._play_file if self.kind == "file" else self._read_live
        self._thread = threading.Thread(target=self._guarded, args=(target, cpu), daemon=True,
                                        name=f"keyshape-live-{self.kind}")
        self._thread.start()
        return self.mailbox

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        container = getattr(self, "_container", None)
        if container is not None:
            container.close()
            self._container = None

    def _guarded(self, target, cpu: int | None = None) -> None:
        if cpu is not None:
            pin_thread(cpu)
        try:
            target()
        except Exception as exc:  # noqa: BLE001 - the loop reports it as the reason the source stopped
            self.mailbox.close(f"{self.name}: the {self.kind} stopped delivering frames "
                               f"({exc.__class__.__name__}: {exc})")

    def _play_file(self) -> None:
        """Deliver the file's frames at their presentation times, from the moment it starts."""
        origin = None
        for index, (ms, rgb) in enumerate(iter_frames(self.device, fps=self._rate)):
            if self._stop.is_set():
                break
            origin = self._hold(origin, ms / 1000, drift=None)
            if origin is None:
                break
            self.mailbox.put(SourceFrame(index, ms / 1000, time.perf_counter(), rgb))
        self.mailbox.close()

    def _read_live(self) -> None:
        """Deliver a camera's or stream's frames as they are decoded; a stream's are held to their
        presentation times (a URL of a stored file, or a server that sends faster than real time,
        would otherwise be decoded flat out, starving the loop of the interpreter)."""
        start = origin = None
        for index, (media, rgb) in enumerate(decode_stream(self._container)):
            if self._stop.is_set():
                break
            if self.kind == "stream" and media is not None:
                origin = self._hold(origin, media)
                if origin is None:
                    break
            arrival = time.perf_counter()
            start = arrival if start is None else start
            self.mailbox.put(SourceFrame(index, arrival - start if media is None else media, arrival, rgb))
        if not self._stop.is_set() and self.kind == "camera":
            raise OSError("end of the camera's stream (unplugged?)")
        self.mailbox.close()

    def _hold(self, origin: float | None, media: float, *, drift: float | None = MAX_DRIFT) -> float | None:
        """Wait until ``media`` seconds (a frame's presentation time) after ``origin`` on
        ``time.perf_counter``'s clock; returns the origin, set at the first frame (``origin`` None)
        and, with ``drift``, set again when the source's clock jumps or stalls by more than that;
        None when stopped while waiting."""
        now = time.perf_counter()
        wait = 0.0 if origin is None else origin + media - now
        if origin is None or (drift is not None and not -drift <= wait <= drift):
            return now - media
        if wait > 0 and self._stop.wait(wait):
            return None
        return origin


def pin_thread(cpu: int) -> set[int] | None:
    """Run the calling thread on core ``cpu`` only (Linux); returns its previous cores (None: not possible)."""
    import os

    if not hasattr(os, "sched_setaffinity") or cpu not in os.sched_getaffinity(0):
        return None
    previous = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {cpu})  # on Linux, 0 is the calling thread
    return previous


def open_source(spec: str, **options) -> FrameSource:
    """The source ``spec`` names (see the module docstring); not started yet."""
    return FrameSource(spec, **options)
