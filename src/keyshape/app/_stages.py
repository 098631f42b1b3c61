"""One line per stage of a long run, for a log rather than a terminal.

:func:`stage` sends what a run starts now ("tracking take.mp4", "solving the weights", ...) to the
``keyshape.stages`` logger at INFO level. Nothing shows unless a handler is attached: the command
line attaches one when stderr is not a terminal (where no progress bar is drawn), so a two-minute
run written to a log or a CI job says what it is doing; a library user may attach their own.
"""

from __future__ import annotations

import logging

__all__ = ["stage", "STAGE_LOGGER"]

STAGE_LOGGER = "keyshape.stages"


def stage(text: str) -> None:
    """Log the start of a stage (``text``: what it does, e.g. ``"tracking take.mp4"``)."""
    logging.getLogger(STAGE_LOGGER).info(text)
