"""``keyshape view``: a local web page playing the source video and the animated character in sync."""

from __future__ import annotations

import errno
from pathlib import Path

from ..exceptions import InputError
from ._argtypes import tcp_port

DESCRIPTION = """\
Serve a local page (on 127.0.0.1 only) for an output folder of `keyshape run` or
`keyshape demo`: the source video and the animated .glb play side by side, in sync,
with play/pause, frame-accurate scrubbing (arrow keys step one frame) and the weight
of every morph target. Everything the page needs ships with keyshape: no network is
used. Ctrl-C stops the server."""
DEFAULT_PORT = 8765


def add_arguments(p) -> None:
    p.add_argument("folder", type=Path, metavar="OUTDIR",
                   help="output folder of `keyshape run` / `keyshape demo` (with take.json)")
    p.add_argument("--port", type=tcp_port, default=None, metavar="N",
                   help=f"TCP port (default {DEFAULT_PORT}, or any free one if that is taken)")
    p.add_argument("--no-browser", action="store_true",
                   help="only print the address; do not open a browser")


def run(args) -> None:
    from ..viewer.server import make_server

    server = _bind(make_server, args.folder, args.port)
    with server:
        take = server.take
        if not args.quiet:
            video = take.video.name if take.video else "no video found (animation only)"
            print(f"{take.folder.name}: {take.n_frames} frames at {take.fps:g} fps, {video}")
            print(f"viewer at {server.url}  (Ctrl-C to stop)", flush=True)
        if not args.no_browser and _has_display():
            import webbrowser

            webbrowser.open(server.url)
        try:
            server.serve_forever(poll_interval=0.2)
        except KeyboardInterrupt:
            if not args.quiet:
                print("viewer stopped")


def _has_display() -> bool:
    """Whether a graphical browser can open: without a display, Python's ``webbrowser`` would
    run a text browser (lynx, w3m) in this terminal, on top of the server's messages."""
    import os
    import sys

    return (sys.platform in ("darwin", "win32") or "BROWSER" in os.environ
            or any(os.environ.get(name) for name in ("DISPLAY", "WAYLAND_DISPLAY")))


def _bind(make_server, folder: Path, port: int | None):
    """The server on ``port``; without one, the default port or else any free port."""
    try:
        return make_server(folder, port=DEFAULT_PORT if port is None else port)
    except OSError as exc:
        if exc.errno != errno.EADDRINUSE:
            raise
        if port is not None:
            raise InputError(f"port {port} is already in use on 127.0.0.1; choose another with "
                             f"--port (or 0 for any free port)") from None
        return make_server(folder, port=0)
