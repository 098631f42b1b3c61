"""``keyshape rom``: show the range-of-motion script."""

from __future__ import annotations

DESCRIPTION = ("Print the range-of-motion (ROM) script: about twenty expressions, in order, that together cover "
               "brows, lids (each eye alone too), cheeks, nose, lips (one-sided moves too) and jaw. Film the "
               "actor doing them once, in the lighting and framing of the real takes, then build the actor's "
               "key set from it and the takes: `keyshape keys rom.mp4 take1.npz ... -o keys.json`. A key set "
               "that has seen the whole range carries over to new takes; `keyshape coverage` checks a new take.")


def add_arguments(p) -> None:
    p.add_argument("--json", action="store_true", help="print the script as JSON (for a prompter or a script)")


def run(args) -> None:
    import json

    from ..capture.rom import HOLD_SECONDS, REST_SECONDS, ROM_SCRIPT, rom_duration

    if args.json:
        print(json.dumps({"hold_seconds": HOLD_SECONDS, "rest_seconds": REST_SECONDS,
                          "steps": [step._asdict() for step in ROM_SCRIPT]}, indent=1))
        return
    print(f"Range of motion: {len(ROM_SCRIPT)} expressions, about {rom_duration():.0f} s. Hold each for "
          f"{HOLD_SECONDS:g} s, relax for {REST_SECONDS:g} s between them; left and right are the actor's own.")
    width = max(len(step.name) for step in ROM_SCRIPT)
    for i, step in enumerate(ROM_SCRIPT, 1):
        print(f"{i:3d}. {step.name:<{width}}  {step.say}   [{step.covers}]")
    print("then: keyshape keys rom.mp4 take1.npz ... -o keys.json")
