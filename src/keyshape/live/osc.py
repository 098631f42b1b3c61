"""Open Sound Control 1.0 messages and bundles, encoded by hand (no dependency).

An OSC packet is a *message* — an address pattern, a type-tag string and the arguments — or a
*bundle* of them under a time tag. Every part is big-endian and padded with NULs to a multiple
of 4 bytes:

* string ``s``: UTF-8 bytes, at least one NUL, padded to 4;
* int32 ``i``, float32 ``f``: 4 bytes, two's complement / IEEE 754;
* bundle: ``"#bundle\\0"``, a 64-bit NTP time tag (``1`` means *immediately*), then each element
  as an int32 size followed by the element's bytes.

Only what the VMC protocol needs is here: strings, int32 and float32 arguments, one level of
bundles. :class:`Message` pre-encodes everything before its last float, so a frame of 60 blend
values costs 60 ``struct.pack`` calls and one ``bytes.join``.

References
----------
Wright, M. (2002). *The Open Sound Control 1.0 Specification*. CNMAT, UC Berkeley.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence

__all__ = ["osc_string", "message", "bundle", "Message", "IMMEDIATELY"]

IMMEDIATELY = 1  # the OSC time tag meaning "process on receipt"
_BUNDLE = b"#bundle\x00"


def osc_string(text: str) -> bytes:
    """``text`` as an OSC string: UTF-8, NUL-terminated, padded to a multiple of 4 bytes.

    Examples
    --------
    >>> osc_string("Head"), osc_string("abc")
    (b'Head\\x00\\x00\\x00\\x00', b'abc\\x00')
    """
    raw = text.encode("utf-8") + b"\x00"
    return raw + b"\x00" * (-len(raw) % 4)


def _tag(value) -> str:
    if isinstance(value, str):
        return "s"
    if isinstance(value, bool):
        return "T" if value else "F"
    if isinstance(value, int):
        return "i"
    return "f"


def _argument(value, tag: str) -> bytes:
    if tag == "s":
        return osc_string(value)
    if tag == "i":
        return struct.pack(">i", value)
    if tag == "f":
        return struct.pack(">f", float(value))
    return b""  # T and F carry no data


def message(address: str, *args) -> bytes:
    """One OSC message: ``str`` arguments are strings, ``int`` int32, anything else float32.

    Examples
    --------
    >>> message("/VMC/Ext/Blend/Apply")
    b'/VMC/Ext/Blend/Apply\\x00\\x00\\x00\\x00,\\x00\\x00\\x00'
    >>> message("/VMC/Ext/OK", 1).hex(" ", 4)
    '2f564d43 2f457874 2f4f4b00 2c690000 00000001'
    """
    tags = [_tag(a) for a in args]
    return osc_string(address) + osc_string("," + "".join(tags)) + b"".join(
        _argument(a, t) for a, t in zip(args, tags))


def bundle(elements: Iterable[bytes], *, timetag: int = IMMEDIATELY) -> bytes:
    """An OSC bundle of already encoded messages (or bundles).

    Examples
    --------
    >>> bundle([message("/a")]).hex(" ", 4)
    '2362756e 646c6500 00000000 00000001 00000008 2f610000 2c000000'
    """
    parts = [_BUNDLE, struct.pack(">Q", timetag)]
    for element in elements:
        parts += [struct.pack(">i", len(element)), element]
    return b"".join(parts)


class Message:
    """A message whose address and leading arguments are fixed and whose trailing floats change.

    ``Message("/VMC/Ext/Blend/Val", "jawOpen", floats=1).element(0.25)`` is the size-prefixed
    bundle element of ``/VMC/Ext/Blend/Val "jawOpen" 0.25``, from bytes encoded once.
    """

    def __init__(self, address: str, *fixed, floats: int = 0):
        tags = "".join(_tag(a) for a in fixed) + "f" * floats
        self._head = osc_string(address) + osc_string("," + tags) + b"".join(
            _argument(a, _tag(a)) for a in fixed)
        self._format = f">{floats}f"
        self._size = struct.pack(">i", len(self._head) + 4 * floats)

    def element(self, *values: float) -> bytes:
        """This message with ``values`` as its floats, prefixed by its size (a bundle element)."""
        return self._size + self._head + struct.pack(self._format, *values)

    def encode(self, values: Sequence[float] = ()) -> bytes:
        """This message with ``values`` as its floats (a packet of its own)."""
        return self._head + struct.pack(self._format, *values)
