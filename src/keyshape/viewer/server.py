"""Serve the viewer page and one take's files on the loopback interface (stdlib ``http.server``).

Routes, all ``GET`` or ``HEAD``:

==========================  =====================================================================
``/``                       the page, ``static/index.html``
``/static/<name>``          the page's files (``viewer.js``, ``viewer.css``)
``/api/take``               what the page needs to know, as JSON (see :meth:`Take.as_json`)
``/media/video``            the source video named in ``take.json``
``/media/<file>``           a file of the take listed in ``take.json`` (``animation.glb``, ...)
==========================  =====================================================================

Files are sent with ``Accept-Ranges: bytes`` and single byte ranges are honoured
(``206``), so the page's ``<video>`` can seek. Nothing outside the static folder, the
take's listed files and its video is ever served; on a loopback address, only requests
that name a loopback host (``127.0.0.1``, ``localhost``) are answered.

References
----------
RFC 9110, *HTTP Semantics*, sections 14.1.2 (byte ranges) and 15.3.7 (206 Partial Content).
"""

from __future__ import annotations

import json
import mimetypes
import re
from dataclasses import dataclass, field
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from urllib.parse import unquote, urlsplit

from ..exceptions import InputError
from ..io.take import load_take_info

__all__ = ["Take", "load_take", "make_server", "ViewerServer", "parse_range"]

STATIC = Path(str(resources.files("keyshape.viewer").joinpath("static")))
_MIME = {".glb": "model/gltf-binary", ".gltf": "model/gltf+json", ".js": "text/javascript",
         ".css": "text/css", ".html": "text/html; charset=utf-8", ".json": "application/json",
         ".csv": "text/csv", ".npz": "application/octet-stream", ".mp4": "video/mp4",
         ".m4v": "video/mp4", ".mov": "video/quicktime", ".webm": "video/webm",
         ".mkv": "video/x-matroska", ".ogv": "video/ogg"}
_CHUNK = 1 << 16
_LOOPBACK = ("127.0.0.1", "localhost", "::1")


@dataclass(frozen=True)
class Take:
    """One output folder of ``keyshape run`` as the viewer serves it.

    Attributes
    ----------
    folder : Path
    fps : float
    n_frames : int
    neutral_frame : int or None
    video : Path or None
        The source video; None when ``take.json`` names none or the file is gone.
    files : dict of str to Path
        The take's files that exist, by file name (``animation.glb``, ``weights.csv``, ...).
    key_frames : dict of str to int
        Source frame of each key shape of this take, by key name (from ``keys.json``).
    key_regions : dict of str to str
        The region of every key shape of ``keys.json`` (``upper``, ``lower``, ...), by key name.
    animation : str
        File name of the animated ``.glb`` among ``files``.
    video_times : tuple of float
        The time in the source video of every frame (the track's ``time``: a take tracked from
        ``--start`` or with a variable frame rate is not ``frame / fps``); empty without a track.
    key_descriptions : dict of str to str
        A readable line per key shape (its region word and nearest ARKit expressions, see
        :func:`keyshape.report.describe_keys`), by key name; empty without keys.json or a track.
    """

    folder: Path
    fps: float
    n_frames: int
    neutral_frame: int | None = None
    video: Path | None = None
    files: dict[str, Path] = field(default_factory=dict)
    key_frames: dict[str, int] = field(default_factory=dict)
    key_regions: dict[str, str] = field(default_factory=dict)
    animation: str = "animation.glb"
    video_times: tuple[float, ...] = ()
    key_descriptions: dict[str, str] = field(default_factory=dict)

    def as_json(self) -> dict:
        """The page's view of the take: numbers, URLs of the files, key frames."""
        return {"name": self.folder.name, "fps": self.fps, "n_frames": self.n_frames,
                "neutral_frame": self.neutral_frame,
                "video": "/media/video" if self.video else None,
                "video_name": self.video.name if self.video else None,
                "animation": f"/media/{self.animation}",
                "files": {name: f"/media/{name}" for name in self.files},
                "key_frames": self.key_frames, "key_regions": self.key_regions,
                "key_descriptions": self.key_descriptions,
                "video_times": list(self.video_times) if len(self.video_times) == self.n_frames else None}


def load_take(folder: str | Path) -> Take:
    """Read ``take.json`` (and the key frames from ``keys.json``) of an output folder.

    Raises
    ------
    InputError
        If the folder has no valid ``take.json`` or no animation file, or if its frame
        rate or frame count is not positive.
    """
    folder = Path(folder).resolve()
    info = load_take_info(folder)
    fps, n_frames = info.get("fps"), info.get("n_frames")
    if not isinstance(fps, (int, float)) or not fps > 0:
        raise InputError(f"{folder / 'take.json'}: fps must be a positive number; got {fps!r}")
    if not isinstance(n_frames, int) or n_frames < 1:
        raise InputError(f"{folder / 'take.json'}: n_frames must be a positive integer; got {n_frames!r}")
    listed = info.get("files") or {}
    files = {Path(name).name: folder / Path(name).name for name in listed.values()
             if (folder / Path(name).name).is_file()}
    animation = Path(listed.get("animation", "animation.glb")).name
    if animation not in files:
        raise InputError(f"{folder}: no {animation} here to show; run `keyshape run` again")
    from ..io.gltf import check_gltf_file

    check_gltf_file(files[animation])
    video = Path(info["video"]) if info.get("video") else None
    keys_name = Path(listed.get("keys", "keys.json")).name
    track_name = Path(listed.get("track", "track.npz")).name
    track = _track(files.get(track_name))
    frames, regions = _keys(files.get(keys_name), video)
    times = () if track is None else tuple(round(float(t), 6) for t in track.time)
    described = _descriptions(files.get(keys_name), track, (video.name if video else "", track_name),
                              files.get(Path(listed.get("weights", "weights.csv")).name))
    return Take(folder, float(fps), n_frames, info.get("neutral_frame"),
                video if video is not None and video.is_file() else None, files,
                frames, regions, animation, times, described)


def _track(path: Path | None):
    """The take's track (checked as every reader checks it); None without one."""
    if path is None:
        return None
    from ..io.track import load_track

    return load_track(path)


def _descriptions(path: Path | None, track, take: tuple[str, str], weights: Path | None) -> dict[str, str]:
    """``{key: readable line}`` from ``keys.json`` and the take's track (and ``weights.csv``, for the
    keys of another take); empty without the keys or the track."""
    if path is None or track is None:
        return {}
    from ..io.keys_json import load_keys
    from ..io.weights_csv import load_weights_csv
    from ..report import describe_keys

    try:
        keys = load_keys(path)
        solved = load_weights_csv(weights) if weights is not None else None
    except InputError:
        return {}  # the key file is a nicety here, as in _keys
    if keys.n_landmarks != track.n_landmarks:
        return {}
    return dict(zip(keys.names, describe_keys(keys, track, take=take, weights=solved)))


def _keys(path: Path | None, video: Path | None) -> tuple[dict[str, int], dict[str, str]]:
    """``({key: source frame}, {key: region})``: the frames of the keys taken from this take's video,
    the regions of every key of ``keys.json``."""
    if path is None:
        return {}, {}
    try:
        regions = json.loads(path.read_text()).get("regions", {})
        keys = [(region, key) for region, entry in regions.items() for key in entry.get("keys", [])]
        frames = {str(key["name"]): int(key["frame"]) for _, key in keys
                  if video is None or key.get("take") in (None, video.name)}
        return frames, {str(key["name"]): str(region) for region, key in keys}
    except (ValueError, TypeError, KeyError, AttributeError):
        return {}, {}  # the key file is a nicety here: the page works without it


# --------------------------------------------------------------------------- byte ranges

_RANGE = re.compile(r"bytes=(\d*)-(\d*)")


class RangeNotSatisfiable(Exception):
    """A ``Range`` header whose only range lies outside the file."""


def parse_range(header: str | None, size: int) -> tuple[int, int] | None:
    """The inclusive byte range ``(first, last)`` a ``Range`` header asks for.

    None means "send the whole file": no header, a malformed one, or several ranges
    (which a server may ignore, RFC 9110 14.2).

    Raises
    ------
    RangeNotSatisfiable
        If the range starts past the end of the file, or is an empty suffix.

    Examples
    --------
    >>> parse_range("bytes=0-99", 1000), parse_range("bytes=900-", 1000)
    ((0, 99), (900, 999))
    >>> parse_range("bytes=-100", 1000), parse_range("bytes=10-5000", 1000)
    ((900, 999), (10, 999))
    >>> parse_range(None, 1000) is None and parse_range("bytes=0-1,5-9", 1000) is None
    True
    """
    match = _RANGE.fullmatch(header.strip()) if header else None
    if match is None or match.group(1) == match.group(2) == "":
        return None
    first, last = match.group(1), match.group(2)
    if first == "":  # suffix: the last N bytes
        if int(last) == 0 or size == 0:
            raise RangeNotSatisfiable(header)
        return max(size - int(last), 0), size - 1
    first, last = int(first), (int(last) if last else size - 1)
    if first >= size:
        raise RangeNotSatisfiable(header)
    if last < first:
        return None
    return first, min(last, size - 1)


# --------------------------------------------------------------------------- the server


class ViewerServer(ThreadingHTTPServer):
    """An HTTP server for one take; ``url`` is the page's address."""

    daemon_threads = True

    def __init__(self, take: Take, address: tuple[str, int]):
        self.take = take
        super().__init__(address, _Handler)

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{host}:{port}/"

    def handle_error(self, request, client_address) -> None:
        import sys

        if not isinstance(sys.exc_info()[1], ConnectionError):  # a browser cancelling a range
            super().handle_error(request, client_address)


def make_server(folder: str | Path, *, port: int = 0, host: str = "127.0.0.1") -> ViewerServer:
    """A server (not yet started) for the output folder ``folder``.

    Parameters
    ----------
    folder : str or Path
        Output folder of ``keyshape run`` or ``keyshape demo`` (with ``take.json``).
    port : int
        TCP port; 0 lets the system choose a free one (see ``server.url``).
    host : str
        Interface to listen on; the loopback one by default, so nothing leaves the machine.

    Returns
    -------
    ViewerServer
        Call ``serve_forever()`` (in a thread, if need be) and ``shutdown()``; use as a
        context manager to close the socket.

    Raises
    ------
    InputError
        If the folder is not a take (see :func:`load_take`).
    OSError
        If the port cannot be bound.
    """
    return ViewerServer(load_take(folder), (host, port))


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server: ViewerServer

    def do_GET(self) -> None:  # http.server's naming
        self._respond(body=True)

    def do_HEAD(self) -> None:
        self._respond(body=False)

    def log_message(self, format, *args) -> None:  # http.server's signature
        pass  # the command prints the URL; per-request lines would drown it

    def _respond(self, *, body: bool) -> None:
        if not self._host_allowed():
            return self._send_bytes(b"forbidden host\n", "text/plain", body, HTTPStatus.FORBIDDEN)
        path = unquote(urlsplit(self.path).path)
        take = self.server.take
        if path == "/api/take":
            return self._send_bytes(json.dumps(take.as_json()).encode(), "application/json", body)
        target = self._route(path, take)
        if target is None:
            return self._send_bytes(b"not found\n", "text/plain", body, HTTPStatus.NOT_FOUND)
        self._send_file(target, body)

    def _host_allowed(self) -> bool:
        """On loopback, only requests addressed to a loopback name: a page elsewhere that
        re-points its own name at 127.0.0.1 (DNS rebinding) cannot read the take."""
        if self.server.server_address[0] not in _LOOPBACK:
            return True
        host = urlsplit(f"//{self.headers.get('Host', '')}").hostname
        return host in _LOOPBACK

    @staticmethod
    def _route(path: str, take: Take) -> Path | None:
        if path in ("/", "/index.html"):
            return STATIC / "index.html"
        if path.startswith("/static/"):
            name = path.removeprefix("/static/")
            target = STATIC / name
            return target if "/" not in name and name and target.is_file() else None
        if path == "/media/video":
            return take.video
        if path.startswith("/media/"):
            return take.files.get(path.removeprefix("/media/"))
        return None

    def _send_bytes(self, data: bytes, mime: str, body: bool, status=HTTPStatus.OK) -> None:
        self.send_response(status)
        self.send_header("Content-Type", mime)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if body:
            self.wfile.write(data)

    def _send_file(self, path: Path, body: bool) -> None:
        size = path.stat().st_size
        try:
            span = parse_range(self.headers.get("Range"), size)
        except RangeNotSatisfiable:
            self.send_response(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
            self.send_header("Content-Range", f"bytes */{size}")
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        first, last = span if span is not None else (0, size - 1)
        self.send_response(HTTPStatus.PARTIAL_CONTENT if span is not None else HTTPStatus.OK)
        self.send_header("Content-Type", _MIME.get(path.suffix.lower())
                         or mimetypes.guess_type(path.name)[0] or "application/octet-stream")
        self.send_header("Content-Length", str(last - first + 1))
        self.send_header("Accept-Ranges", "bytes")
        self.send_header("Cache-Control", "no-cache")
        if span is not None:
            self.send_header("Content-Range", f"bytes {first}-{last}/{size}")
        self.end_headers()
        if body:
            self._copy(path, first, last - first + 1)

    def _copy(self, path: Path, offset: int, length: int) -> None:
        with open(path, "rb") as fh:
            fh.seek(offset)
            while length > 0:
                chunk = fh.read(min(_CHUNK, length))
                if not chunk:
                    break
                self.wfile.write(chunk)
                length -= len(chunk)

