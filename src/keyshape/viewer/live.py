"""``keyshape live --view``: the viewer page, live — the camera and the character side by side.

The page is the same as ``keyshape view``'s; ``/api/take`` says ``"live": true`` and the page then
opens a WebSocket on ``/live`` (RFC 6455, server to page only) instead of playing a video:

* a text message per solved frame: ``{"frame", "time", "face", "names", "weights", "head"}``
  (weights in ``names`` order, the head rotation as a glTF-axis quaternion ``[x, y, z, w]``; for
  keyshape's own head the key weights and the gaze targets' weights from the eye rotations);
* a binary message with the camera image as JPEG, at most :data:`IMAGE_RATE` times a second
  and at most 640 pixels wide (the weights go every frame; the pictures only as fast as they help).

Each page has its own sending thread that always sends the newest frame, so a slow page skips
frames and never slows the live loop down. Loopback only, as ``keyshape view``.

References
----------
RFC 6455, *The WebSocket Protocol*, sections 1.3 (opening handshake) and 5.2 (base framing).
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import shutil
import struct
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from ..containers import Rig, Weights
from .server import Take, ViewerServer, _Handler

__all__ = ["LiveView", "IMAGE_RATE", "websocket_accept", "gaze_from_eyes"]

IMAGE_RATE = 15.0  # camera pictures per second, at most
_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"  # RFC 6455, section 1.3


def websocket_accept(key: str) -> str:
    """The ``Sec-WebSocket-Accept`` answer to a client's ``Sec-WebSocket-Key``.

    Examples
    --------
    >>> websocket_accept("dGhlIHNhbXBsZSBub25jZQ==")  # RFC 6455's own example
    's3pPLMBiTxaQ9kYGzzhZRbK+xOo='
    """
    return base64.b64encode(hashlib.sha1((key + _GUID).encode()).digest()).decode()


def _ws_frame(opcode: int, payload: bytes) -> bytes:
    """One unmasked, final WebSocket frame (server to client)."""
    n = len(payload)
    if n < 126:
        head = struct.pack(">BB", 0x80 | opcode, n)
    elif n < 1 << 16:
        head = struct.pack(">BBH", 0x80 | opcode, 126, n)
    else:
        head = struct.pack(">BBQ", 0x80 | opcode, 127, n)
    return head + payload


def gaze_from_eyes(eyes) -> np.ndarray:
    """The stylised head's gaze-target weights ``(8,)`` (:data:`keyshape.targets.GAZE_NAMES`) of a live
    frame's eye rotations ``eyes (2, 4)`` (glTF-axis quaternions, LEFT eye first; None: straight ahead).

    Each eye's rest direction (+Z in glTF axes) turned by its rotation gives yaw and pitch in
    degrees, as :class:`keyshape.capture.Gaze` measures them, for :func:`keyshape.targets.gaze_weights`.
    """
    from scipy.spatial.transform import Rotation

    from ..targets import gaze_weights

    if eyes is None or not np.isfinite(eyes).all():
        return np.zeros(8)
    ahead = Rotation.from_quat(np.asarray(eyes, float)[::-1]).apply([0.0, 0.0, 1.0])  # (right, left) x (x, y, z)
    yaw = np.degrees(np.arctan2(ahead[:, 0], ahead[:, 2]))
    pitch = np.degrees(np.arcsin(np.clip(ahead[:, 1], -1.0, 1.0)))
    return gaze_weights(yaw[None], pitch[None])[0]


class LiveView:
    """An :class:`~keyshape.live.frame.Output` serving the live page on ``url``.

    Parameters
    ----------
    rig : Rig
        The character drawn (written once as a .glb for the page).
    fps : float
    port : int (0: any free port)
    key_names : tuple of str, optional
        When the character is keyshape's own head (targets named after the keys), the names of
        ``frame.keys``: the page is then driven by the key weights, the head drawn in its colours
        and, when the rig has them (:func:`keyshape.targets.with_gaze_targets`), its eyes turned by
        ``frame.eyes`` through the gaze targets.
    name : str, shown as the take's name
    """

    def __init__(self, rig: Rig, *, fps: float, port: int = 0, key_names=None, name: str = "live",
                 host: str = "127.0.0.1"):
        from ..io.gltf import write_glb
        from ..targets import GAZE_NAMES, stylised_head

        self._folder = Path(tempfile.mkdtemp(prefix="keyshape-live-view-"))
        glb = self._folder / "character.glb"
        builtin = key_names is not None and rig.n_vertices == stylised_head().rig.n_vertices
        write_glb(glb, rig, Weights(np.zeros((1, len(rig.names))), rig.names, fps),
                  colours=stylised_head().colours if builtin else None)
        self._gaze = tuple(GAZE_NAMES) if builtin and set(GAZE_NAMES) <= set(rig.names) else ()
        take = Take(self._folder, float(fps), 1, files={glb.name: glb}, animation=glb.name)
        self.name, self.key_names = name, tuple(key_names) if key_names is not None else None
        self._changed = threading.Condition()
        self._frame, self._seq, self.closed = None, 0, False
        self._jpeg = (0, b"")
        self.server = _LiveServer(take, (host, port), self)
        self._thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.2},
                                        daemon=True, name="keyshape-live-view")
        self._thread.start()

    @property
    def url(self) -> str:
        return self.server.url

    def send(self, frame) -> None:
        with self._changed:
            self._frame, self._seq = frame, self._seq + 1
            self._changed.notify_all()

    def close(self) -> None:
        with self._changed:
            self.closed = True
            self._changed.notify_all()
        self.server.shutdown()
        self.server.server_close()
        self._thread.join(timeout=5)
        shutil.rmtree(self._folder, ignore_errors=True)

    def newest(self, seen: int, timeout: float = 1.0):
        """``(frame, seq)``: the newest frame once it is newer than ``seen`` (None after ``timeout``)."""
        with self._changed:
            if self._seq == seen and not self.closed:
                self._changed.wait(timeout)
            return (self._frame, self._seq) if self._seq != seen else (None, seen)

    def message(self, frame) -> bytes:
        """The page's JSON for one frame."""
        if self.key_names is not None:
            names, values = self.key_names, np.nan_to_num(frame.keys, nan=0.0)
            if self._gaze:
                names, values = (*names, *self._gaze), np.concatenate([values, gaze_from_eyes(frame.eyes)])
        else:
            names, values = frame.names, frame.values
        return json.dumps({"frame": int(frame.index), "time": round(float(frame.time), 4), "face": bool(frame.face),
                           "names": list(names), "weights": np.round(values, 4).tolist(),
                           "head": np.round(frame.head, 5).tolist()}).encode()

    def jpeg(self, frame, seq: int) -> bytes:
        """The camera image of ``frame`` as JPEG (encoded once, whichever page asks first)."""
        if self._jpeg[0] == seq:
            return self._jpeg[1]
        from PIL import Image

        image = Image.fromarray(frame.rgb)
        if image.width > 640:
            image = image.resize((640, round(image.height * 640 / image.width)))
        buffer = io.BytesIO()
        image.save(buffer, format="JPEG", quality=75)
        self._jpeg = (seq, buffer.getvalue())
        return self._jpeg[1]


class _LiveServer(ViewerServer):
    def __init__(self, take: Take, address, view: LiveView):
        self.view = view
        super().__init__(take, address)
        self.RequestHandlerClass = _LiveHandler


class _LiveHandler(_Handler):
    server: _LiveServer

    def _respond(self, *, body: bool) -> None:
        path = self.path.split("?")[0]
        if path == "/live" and self._host_allowed():
            return self._websocket()
        if path == "/api/take" and self._host_allowed():
            view = self.server.view
            info = {**self.server.take.as_json(), "name": view.name, "live": True, "socket": "/live"}
            return self._send_bytes(json.dumps(info).encode(), "application/json", body)
        return super()._respond(body=body)

    def _websocket(self) -> None:
        key = self.headers.get("Sec-WebSocket-Key")
        if not key or self.headers.get("Upgrade", "").lower() != "websocket":
            return self._send_bytes(b"a WebSocket is expected here\n", "text/plain", True, 400)
        self.send_response(101, "Switching Protocols")
        self.send_header("Upgrade", "websocket")
        self.send_header("Connection", "Upgrade")
        self.send_header("Sec-WebSocket-Accept", websocket_accept(key))
        self.end_headers()
        self.wfile.flush()
        self.close_connection = True
        self._stream(self.server.view)

    def _stream(self, view: LiveView) -> None:
        seen, pictured = 0, 0.0
        try:
            while not view.closed:
                frame, seen = view.newest(seen)
                if frame is None:
                    continue
                self.wfile.write(_ws_frame(0x1, view.message(frame)))
                now = time.monotonic()
                if now - pictured >= 1.0 / IMAGE_RATE:
                    self.wfile.write(_ws_frame(0x2, view.jpeg(frame, seen)))
                    pictured = now
                self.wfile.flush()
            self.wfile.write(_ws_frame(0x8, struct.pack(">H", 1001)))  # going away
        except OSError:
            return  # the page went away
