"""Argument types shared by the verbs: each returns the parsed value or raises a clear message."""

from __future__ import annotations

import argparse

__all__ = ["bound", "non_negative", "positive", "whole"]


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number; got {text!r}") from None


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


def whole(low: int, high: int):
    """A whole number in ``low..high``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a whole number; got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be between {low} and {high}; got {value}")
        return value

    return parse
