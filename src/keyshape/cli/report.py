"""``keyshape report``: pictures, preview and a self-contained report.html for a take."""

from __future__ import annotations

from pathlib import Path

DESCRIPTION = ("Write into OUTDIR (an output folder of `keyshape run`): preview.mp4, keyshapes.png (the "
               "key-shape contact sheet), weights.png (weights over time with the fit error and the "
               "frames outside the key-shape hull), error_vs_k.png when OUTDIR/error_vs_k.json exists, "
               "and report.html, which opens without a network.")


def add_arguments(p) -> None:
    p.add_argument("outdir", type=Path, help="output folder of `keyshape run` (holds take.json)")
    p.add_argument("--no-preview", action="store_true", help="skip the preview video (the slow part)")
    p.add_argument("--backend", choices=("auto", "gl", "numpy"), default="auto",
                   help="preview renderer: auto (default), gl or numpy")


def run(args) -> None:
    from ..report import write_take_extras
    from ._options import progress

    extras = write_take_extras(args.outdir, progress=progress(args), preview=not args.no_preview,
                               backend=args.backend)
    if not args.quiet:
        n = extras.numbers
        errors = ", ".join(f"{r} {v['rms_error']}" for r, v in n["regions"].items())
        print(f"{extras.report}: {n['frames']} frames, face in {n['detection_rate']} %, "
              f"RMS error ({n['error_unit']}) {errors}")
