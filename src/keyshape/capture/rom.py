"""The range-of-motion (ROM) script: the expressions to film once per actor.

Key shapes are real frames, so a key set can only blend what its takes showed. A short ROM take
that walks through every part of the face, each side alone too, gives the actor a key set that
carries over to new takes (``keyshape keys rom.mp4 take1.npz ...``). The order runs from the top
of the face down, each one-sided move right after its two-sided one, a rest between moves so
that every expression stands on its own frames.

"left" and "right" are the actor's own.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["RomStep", "ROM_SCRIPT", "HOLD_SECONDS", "REST_SECONDS", "rom_duration"]

HOLD_SECONDS = 2.0  # hold each expression this long
REST_SECONDS = 1.0  # back to the neutral between expressions


class RomStep(NamedTuple):
    """One expression of the script: a short name, what to do, and the face parts it covers."""

    name: str
    say: str
    covers: str


ROM_SCRIPT: tuple[RomStep, ...] = (
    RomStep("neutral", "relax: lips closed, eyes open, look into the lens (hold 3 s)", "the neutral"),
    RomStep("brows_up", "raise both eyebrows as high as they go", "brows"),
    RomStep("brow_up_left", "raise only the left eyebrow", "brows, one side"),
    RomStep("brow_up_right", "raise only the right eyebrow", "brows, one side"),
    RomStep("frown", "pull both eyebrows down and together (a hard frown)", "brows"),
    RomStep("eyes_wide", "open both eyes as wide as they go", "lids"),
    RomStep("eyes_closed", "close both eyes gently", "lids"),
    RomStep("wink_left", "close only the left eye", "lids, one side"),
    RomStep("wink_right", "close only the right eye", "lids, one side"),
    RomStep("squint", "squeeze both eyes shut hard, cheeks up", "lids, cheeks"),
    RomStep("sneer", "wrinkle the nose and lift the upper lip", "nose, upper lip"),
    RomStep("cheeks_puff", "puff both cheeks out, lips closed", "cheeks, lips"),
    RomStep("smile", "a broad smile showing the teeth", "lips, cheeks"),
    RomStep("smile_left", "smile with the left corner of the mouth only", "lips, one side"),
    RomStep("smile_right", "smile with the right corner of the mouth only", "lips, one side"),
    RomStep("mouth_corners_down", "pull both corners of the mouth down (sad)", "lips"),
    RomStep("mouth_left", "push the closed lips to the left", "lips, one side"),
    RomStep("mouth_right", "push the closed lips to the right", "lips, one side"),
    RomStep("ee", "say a long \"ee\": lips stretched wide, teeth together", "lips"),
    RomStep("oo", "say \"oo\": lips pushed forward into a small round", "lips"),
    RomStep("lips_pressed", "press the lips together and roll them in", "lips"),
    RomStep("jaw_open", "open the jaw as wide as it goes (\"ah\")", "jaw"),
    RomStep("jaw_left", "slide the jaw to the left, mouth slightly open", "jaw, one side"),
    RomStep("jaw_right", "slide the jaw to the right, mouth slightly open", "jaw, one side"),
    RomStep("neutral_again", "relax back to the neutral (hold 3 s)", "the neutral"),
)


def rom_duration(script=ROM_SCRIPT) -> float:
    """Seconds the script takes at the stated pace (the two neutrals hold 3 s)."""
    holds = sum(3.0 if step.name.startswith("neutral") else HOLD_SECONDS for step in script)
    return holds + REST_SECONDS * (len(script) - 1)
