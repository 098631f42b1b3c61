"""Argument types shared by the verbs: each returns the parsed value or raises a clear message."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

__all__ = ["bound", "weight_bound", "non_negative", "positive", "frame_rate", "whole", "regions", "tcp_port",
           "address"]


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number; got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number; got {text!r}")
    return value


def bound(text: str) -> float | None:
    """An upper bound > 0, or ``none``/``inf``/``off`` for no bound."""
    if text.lower() in ("none", "inf", "off"):
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number or 'none'; got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0 or 'none'; got {value:g}")
    return value


def weight_bound(text: str) -> float:
    """The solve's upper bound: > 0 and at most ``MAX_WEIGHT`` (5), the largest weight a weights
    file holds; ``none``/``inf``/``off`` give that ceiling, so every file ``solve`` writes can be read
    back by ``apply``, ``preview`` and ``export``."""
    from ..io.validate import MAX_WEIGHT

    value = bound(text)
    if value is None:
        return MAX_WEIGHT
    if value > MAX_WEIGHT:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_WEIGHT:g} (the largest weight a weights file holds) "
                                         f"or 'none'; got {value:g}")
    return value


def non_negative(text: str) -> float:
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0; got {value:g}")
    return value


def positive(text: str) -> float:
    value = _number(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0; got {value:g}")
    return value


def frame_rate(text: str) -> float:
    """A frame rate: > 0 and at most ``MAX_FPS`` (1000), what a track file holds (frames are timed in
    whole milliseconds)."""
    from ..io.validate import MAX_FPS

    value = positive(text)
    if value > MAX_FPS:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_FPS:g} frames a second (frames are timed in whole "
                                         f"milliseconds); got {value:g}")
    return value


def whole(low: int, high: int | None = None):
    """A whole number in ``low..high`` (``high=None``: no upper limit). The limits are kept on the
    parser (``.limits``), and the help formatter states them in ``--help``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a whole number; got {text!r}") from None
        if value < low or (high is not None and value > high):
            if high is None:
                raise argparse.ArgumentTypeError(f"must be >= {low}; got {value}")
            raise argparse.ArgumentTypeError(f"must be between {low} and {high}; got {value}")
        return value

    parse.__name__ = "whole number"  # argparse's "invalid <name> value" if ever shown
    parse.limits = (low, high)
    return parse


def regions(text: str) -> str | Path:
    """A built-in region scheme's name or an existing REGIONS.json."""
    from ..schemes import REGION_SCHEMES

    if text in REGION_SCHEMES:
        return text
    if Path(text).is_file():
        return Path(text)
    raise argparse.ArgumentTypeError(f"{text!r} is neither a scheme ({', '.join(REGION_SCHEMES)}) nor an "
                                     "existing REGIONS.json file")


def tcp_port(text: str) -> int:
    """A TCP or UDP port, 0 (any free one) to 65535.

    Examples
    --------
    >>> tcp_port("8000")
    8000
    """
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number; got {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be between 0 and 65535; got {value}")
    return value


def address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` as ``(host, port)``, the port in 1..65535 (checked before any source is opened).

    Examples
    --------
    >>> address("127.0.0.1:39539")
    ('127.0.0.1', 39539)
    """
    from ..exceptions import InputError
    from ..live import parse_address

    try:
        return parse_address(text, option="it")
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("it ")) from None
