"""What the live loop hands every output for one frame, and the outputs' small protocol."""

from __future__ import annotations

import socket
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..exceptions import InputError

__all__ = ["LiveFrame", "Output", "UdpOutput", "parse_address", "IDENTITY"]

IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])  # quaternion (x, y, z, w)


@dataclass(frozen=True, eq=False)
class LiveFrame:
    """One solved frame of a live session.

    Attributes
    ----------
    index : int
        Source frame number (every frame the source delivered counts, dropped ones too).
    time : float
        Media time of the frame, seconds (presentation time for files, since start for cameras).
    arrival : float
        ``time.perf_counter()`` when the frame arrived from the source.
    names : tuple of n_targets str
        Target names (the key names, or the rig's targets with a mapping).
    values : (n_targets,) float
        Target weights, ≥ 0 (0 everywhere is the neutral); never NaN.
    keys : (n_keys,) float
        The key weights behind ``values`` (NaN while no face has been seen).
    head : (4,) float
        Head rotation relative to the neutral, quaternion ``(x, y, z, w)`` in glTF axes (+Y up, the
        character facing +Z).
    eyes : (2, 4) float or None
        Eye rotations relative to the head, quaternions in glTF axes, the character's LEFT eye first;
        None when gaze is not known (not a MediaPipe track, no face).
    face : bool
        Whether the tracker found the face in this frame (else the last pose is held, then the neutral).
    rgb : (height, width, 3) uint8
        The camera image.
    detection : Detection or None
        The tracker's output for the followed face (landmarks, scores, head matrix), None without one.
    """

    index: int
    time: float
    arrival: float
    names: tuple[str, ...]
    values: np.ndarray
    keys: np.ndarray
    head: np.ndarray
    eyes: np.ndarray | None
    face: bool
    rgb: np.ndarray
    detection: object = None


class Output(Protocol):
    """Where live frames go: ``send`` is called once per solved frame, ``close`` once at the end."""

    def send(self, frame: LiveFrame) -> None: ...

    def close(self) -> None: ...


def parse_address(text: str, *, option: str = "address") -> tuple[str, int]:
    """``HOST:PORT`` -> ``(host, port)``.

    Examples
    --------
    >>> parse_address("127.0.0.1:39539"), parse_address("studio-pc:11111")
    (('127.0.0.1', 39539), ('studio-pc', 11111))
    """
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"{option} must be HOST:PORT with a port in 1..65535; got {text!r}")
    return host.strip("[]"), int(port)


class UdpOutput:
    """A UDP socket to one receiver: sends never block and never fail the session.

    UDP has no connection: with no receiver listening the packets are simply lost (the count of
    send errors, e.g. an ICMP "port unreachable" reported back or a broadcast address refused, is
    kept in ``errors``, the last one's reason in ``last_error``; :meth:`report` says it in a line).
    """

    kind = "UDP"

    def __init__(self, host: str, port: int):
        try:
            family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
        except socket.gaierror as exc:
            raise InputError(f"{host}:{port}: unknown host ({exc.strerror})") from None
        self.address = address
        self.socket = socket.socket(family, kind, proto)
        self.socket.setblocking(False)
        self.target = f"{host}:{port}"
        self.sent = 0
        self.errors = 0
        self.last_error: str | None = None

    def send_packet(self, packet: bytes) -> None:
        try:
            self.socket.sendto(packet, self.address)
            self.sent += 1
        except OSError as exc:  # no receiver (ICMP refused), buffer full: UDP carries on
            self.errors += 1
            self.last_error = exc.strerror or type(exc).__name__

    def report(self) -> str:
        """One line: how many packets went to the receiver and how many could not be sent."""
        text = f"{self.kind} {self.target}: {self.sent} of {self.sent + self.errors} packets sent"
        return text + (f", {self.errors} failed ({self.last_error})" if self.errors else "")

    def close(self) -> None:
        self.socket.close()
