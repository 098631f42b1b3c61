"""The VMC protocol (OSC over UDP): a live frame as VSeeFace, VNyan, Warudo or EVMC4U receive it.

One bundle per frame, in this order::

    /VMC/Ext/OK 1                                     the avatar is "loaded"
    /VMC/Ext/T <time>                                 seconds (the frame's media time)
    /VMC/Ext/Blend/Val <name> <value>                 every target, value in [0, 1]
    /VMC/Ext/Blend/Apply                              apply the values above at once
    /VMC/Ext/Bone/Pos "Head" px py pz qx qy qz qw     head rotation relative to the neutral
    /VMC/Ext/Bone/Pos "LeftEye" ... / "RightEye" ...  eye rotations, when gaze is known

Bones are in Unity's axes, as the protocol defines them (left-handed, +Y up, the avatar facing
+Z): a glTF rotation ``(x, y, z, w)`` becomes ``(x, −y, −z, w)`` (the mirror ``x → −x`` that
UniGLTF applies to glTF files). Positions are sent as 0: receivers take the bone offsets from
their own avatar. VMC "Marionettes" (VSeeFace, VNyan, Warudo) listen on port 39539 by default;
"Performers" take assistant data on 39540.

References
----------
Virtual Motion Capture Protocol specification, https://protocol.vmc.info/english (OSC over UDP;
``/VMC/Ext/Blend/Val``, ``/VMC/Ext/Blend/Apply``, ``/VMC/Ext/Bone/Pos``, ``/VMC/Ext/T``, ``/VMC/Ext/OK``).
"""

from __future__ import annotations

import numpy as np

from .frame import LiveFrame, UdpOutput
from .osc import Message, bundle, message

__all__ = ["VmcSender", "vmc_bundle", "unity_quaternion", "VMC_PORT"]

VMC_PORT = 39539
_MIRROR_X = np.array([1.0, -1.0, -1.0, 1.0])


def unity_quaternion(q_gltf: np.ndarray) -> np.ndarray:
    """``(..., 4)`` glTF-axis quaternions ``(x, y, z, w)`` in Unity's axes (``x → −x`` mirror).

    Examples
    --------
    >>> unity_quaternion(np.array([0.0, 0.6, 0.0, 0.8])).tolist()  # a yaw turns the other way
    [0.0, -0.6, -0.0, 0.8]
    """
    return np.asarray(q_gltf, dtype=float) * _MIRROR_X


class _Encoder:
    """The bundle of one frame, from messages encoded once per session."""

    def __init__(self, names):
        self.names = tuple(names)
        self.blend = [Message("/VMC/Ext/Blend/Val", str(n), floats=1) for n in self.names]
        self.time = Message("/VMC/Ext/T", floats=1)
        self.bones = {bone: Message("/VMC/Ext/Bone/Pos", bone, floats=7)
                      for bone in ("Head", "LeftEye", "RightEye")}
        self.fixed_head = [message("/VMC/Ext/OK", 1)]
        self.apply = message("/VMC/Ext/Blend/Apply")

    def encode(self, frame: LiveFrame) -> bytes:
        values = np.clip(np.asarray(frame.values, dtype=float), 0.0, 1.0)
        elements = [*self.fixed_head, self.time.encode([frame.time])]
        elements += [m.encode([v]) for m, v in zip(self.blend, values.tolist())]
        elements.append(self.apply)
        elements.append(self.bones["Head"].encode([0.0, 0.0, 0.0, *unity_quaternion(frame.head).tolist()]))
        if frame.eyes is not None:
            for bone, q in zip(("LeftEye", "RightEye"), unity_quaternion(frame.eyes)):
                elements.append(self.bones[bone].encode([0.0, 0.0, 0.0, *q.tolist()]))
        return bundle(elements)


def vmc_bundle(frame: LiveFrame) -> bytes:
    """The VMC bundle of one frame (see the module docstring)."""
    return _Encoder(frame.names).encode(frame)


class VmcSender(UdpOutput):
    """Send every frame to a VMC receiver at ``host:port`` (an :class:`~keyshape.live.frame.Output`)."""

    kind = "VMC"

    def __init__(self, host: str, port: int = VMC_PORT, *, names=()):
        super().__init__(host, port)
        self._encoder = _Encoder(names)

    def send(self, frame: LiveFrame) -> None:
        if frame.names != self._encoder.names:
            self._encoder = _Encoder(frame.names)
        self.send_packet(self._encoder.encode(frame))
