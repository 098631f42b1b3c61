"""Unreal's Live Link Face UDP packets: what the Live Link Face iPhone app streams to Unreal.

Unreal's Apple ARKit Face Support plugin receives them (Live Link source "LiveLinkFace", port
11111 by default), so MetaHuman and other ARKit-named rigs in Unreal follow a webcam as they
follow the app. Layout of packet version 6, every number big-endian (Unreal's network byte
order serialiser)::

    uint8    version            6
    int32    n, n bytes          device id (UTF-8, no terminator)
    int32    n, n bytes          subject name (the Live Link subject Unreal shows)
    int32    frame number        \\
    float32  sub-frame           |  FQualifiedFrameTime: the frame's time at the frame rate below
    int32    rate numerator      |
    int32    rate denominator   /
    uint8    count              61
    61 × float32                 the values, in Unreal's EARFaceBlendShape order (PACKET_NAMES)

The 61 values are the 52 ARKit coefficients in ``[0, 1]`` and 9 rotations in radians (head yaw,
pitch, roll; left eye yaw, pitch, roll; right eye), the same names and angle conventions as the
Live Link Face CSV (:mod:`keyshape.io.livelink`). The packet order is *not* the CSV's column
order: ``EARFaceBlendShape`` lists ``JawLeft`` before ``JawRight`` and ``MouthLeft`` before
``MouthRight``, the CSV the other way round; values are placed by name.

Verified against the public descriptions of the format: the enum ``EARFaceBlendShape`` in
Unreal's ``AugmentedReality`` module (61 entries, values 0..60), the publisher and listener of
``AppleARKitLiveLinkSource.cpp`` (version byte, device id, subject name, frame time, count,
floats through ``FNboSerializeToBuffer``), and the version-6 decoder of the LLV tool
(think-biq/LLV, ``gesicht.py``: int32-length-prefixed strings, int32 + float32 + int32 + int32
frame time).
"""

from __future__ import annotations

import socket
import struct
from fractions import Fraction
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from ..exceptions import InputError, RigError
from ..io.livelink import LIVELINK_NAMES, ROTATION_NAMES, head_angles, livelink_columns
from .frame import LiveFrame, UdpOutput

__all__ = ["PACKET_NAMES", "PACKET_VERSION", "LIVELINK_PORT", "LiveLinkPacket", "encode_packet",
           "decode_packet", "LiveLinkSender", "frame_rate"]

PACKET_VERSION = 6
LIVELINK_PORT = 11111
# Unreal's EARFaceBlendShape, values 0..60
PACKET_NAMES = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft",
    "EyeSquintLeft", "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight",
    "EyeLookOutRight", "EyeLookUpRight", "EyeSquintRight", "EyeWideRight", "JawForward",
    "JawLeft", "JawRight", "JawOpen", "MouthClose", "MouthFunnel", "MouthPucker", "MouthLeft",
    "MouthRight", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft", "MouthFrownRight",
    "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft", "MouthStretchRight",
    "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper", "MouthPressLeft",
    "MouthPressRight", "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft",
    "MouthUpperUpRight", "BrowDownLeft", "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft",
    "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft", "CheekSquintRight", "NoseSneerLeft",
    "NoseSneerRight", "TongueOut", *ROTATION_NAMES,
)
assert sorted(PACKET_NAMES) == sorted(LIVELINK_NAMES + ROTATION_NAMES)  # the same 61 names
_N = len(PACKET_NAMES)


class LiveLinkPacket(NamedTuple):
    """A decoded packet: ``values (61,)`` in :data:`PACKET_NAMES` order; ``rate`` as (numerator, denominator)."""

    version: int
    device_id: str
    subject: str
    frame: int
    subframe: float
    rate: tuple[int, int]
    values: np.ndarray

    def as_dict(self) -> dict[str, float]:
        return dict(zip(PACKET_NAMES, self.values.tolist()))


def _string(text: str) -> bytes:
    raw = text.encode("utf-8")
    return struct.pack(">i", len(raw)) + raw


def frame_rate(fps: float) -> tuple[int, int]:
    """``fps`` as Unreal's FFrameRate ``(numerator, denominator)``.

    Examples
    --------
    >>> frame_rate(30.0), frame_rate(30000 / 1001)
    ((30, 1), (30000, 1001))
    """
    rate = Fraction(float(fps)).limit_denominator(1001)
    return rate.numerator, rate.denominator


def encode_packet(values: np.ndarray, *, time: float, rate: tuple[int, int], subject: str = "keyshape",
                  device_id: str = "keyshape") -> bytes:
    """One Live Link Face packet (version 6).

    Parameters
    ----------
    values : (61,) float
        In :data:`PACKET_NAMES` order.
    time : float
        Seconds; written as frame number and sub-frame at ``rate``.
    rate : (int, int)
        Frame rate numerator and denominator (:func:`frame_rate`).

    Examples
    --------
    >>> packet = encode_packet(np.zeros(61), time=1.5, rate=(30, 1), subject="s", device_id="d")
    >>> len(packet), decode_packet(packet).frame
    (272, 45)
    """
    values = np.asarray(values, dtype=float)
    if values.shape != (_N,):
        raise InputError(f"values must have shape ({_N},); got {values.shape}")
    frame, subframe = _frame_time(float(time) * rate[0] / rate[1])
    head = struct.pack(">B", PACKET_VERSION) + _string(device_id) + _string(subject)
    timing = struct.pack(">ifiiB", frame, subframe, rate[0], rate[1], _N)
    return head + timing + struct.pack(f">{_N}f", *values.tolist())


def _frame_time(position: float) -> tuple[int, float]:
    """Frame number and sub-frame of ``position`` frames; within 0.02 of a whole frame (media times
    come in whole milliseconds, 0.012 frames at 24 fps) it is that frame, sub-frame 0."""
    nearest = round(position)
    if abs(position - nearest) < 0.02:
        return int(nearest), 0.0
    frame = int(np.floor(position))
    return frame, position - frame


def decode_packet(data: bytes) -> LiveLinkPacket:
    """Read a version-6 packet back (for tests and tools); raises InputError on a malformed one."""
    try:
        (version,) = struct.unpack_from(">B", data, 0)
        offset, texts = 1, []
        for _ in range(2):
            (length,) = struct.unpack_from(">i", data, offset)
            texts.append(data[offset + 4: offset + 4 + length].decode("utf-8"))
            offset += 4 + length
        frame, subframe, numerator, denominator, count = struct.unpack_from(">ifiiB", data, offset)
        offset += 17
        values = np.array(struct.unpack_from(f">{count}f", data, offset))
    except (struct.error, UnicodeDecodeError) as exc:
        raise InputError(f"not a Live Link Face packet ({exc})") from None
    if offset + 4 * count != len(data):
        raise InputError(f"Live Link Face packet of {len(data)} bytes has {len(data) - offset - 4 * count} extra")
    return LiveLinkPacket(version, texts[0], texts[1], frame, subframe, (numerator, denominator), values)


def _angles(quaternion: np.ndarray) -> np.ndarray:
    return head_angles(Rotation.from_quat(quaternion).as_matrix()[None])[0]


class LiveLinkSender(UdpOutput):
    """Send every frame to Unreal's Live Link (an :class:`~keyshape.live.frame.Output`).

    ``names`` are the targets the frames carry; the ARKit-named ones (any spelling
    :func:`keyshape.io.livelink.livelink_columns` accepts) fill the 52 coefficients, the others are
    left out; coefficients no target provides are 0.

    Raises
    ------
    RigError
        If no name is an ARKit coefficient.
    """

    kind = "Live Link"

    def __init__(self, host: str, port: int = LIVELINK_PORT, *, names, fps: float,
                 subject: str = "keyshape", device_id: str | None = None):
        sources, _ = livelink_columns(names)
        if not sources:
            raise RigError(f"--livelink needs ARKit-named targets (jawOpen, eyeBlinkLeft, ...); these are "
                           f"{list(names)[:8]}...: drive an ARKit rig with --rig RIG --auto-targets or --map MAP.json")
        super().__init__(host, port)
        self.names = tuple(names)
        self._columns = [(PACKET_NAMES.index(name), idx) for name, idx in sources.items()]
        self.rate = frame_rate(fps)
        self.subject = subject
        self.device_id = device_id or f"keyshape-{socket.gethostname()}"

    def values(self, frame: LiveFrame) -> np.ndarray:
        """(61,) float in :data:`PACKET_NAMES` order for ``frame``."""
        out = np.zeros(_N)
        weights = np.asarray(frame.values, dtype=float)
        for slot, idx in self._columns:
            out[slot] = weights[idx].mean()
        np.clip(out[:52], 0.0, 1.0, out=out[:52])
        out[52:55] = _angles(frame.head)
        if frame.eyes is not None:
            out[55:58], out[58:61] = _angles(frame.eyes[0]), _angles(frame.eyes[1])
        return out

    def send(self, frame: LiveFrame) -> None:
        self.send_packet(encode_packet(self.values(frame), time=frame.time, rate=self.rate,
                                       subject=self.subject, device_id=self.device_id))
