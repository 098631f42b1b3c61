"""``keyshape report``: pictures, preview and report.html (the preview beside it or embedded) for a take."""

from __future__ import annotations

from pathlib import Path

DESCRIPTION = ("Write into OUTDIR (an output folder of `keyshape run`): preview.mp4, keyshapes.png (the "
               "key-shape contact sheet), weights.png (weights over time with the fit error and the "
               "frames outside the key-shape hull), error_vs_k.png when OUTDIR/error_vs_k.json exists, "
               "and report.html, which opens without a network: it plays preview.mp4 from beside it "
               "(--embed-video: from inside it, a page to send on its own).")


def add_arguments(p) -> None:
    p.add_argument("outdir", type=Path, help="output folder of `keyshape run` (holds take.json)")
    p.add_argument("--no-preview", action="store_true", help="skip the preview video (the slow part)")
    p.add_argument("--embed-video", action="store_true",
                   help="carry preview.mp4 inside report.html (base64: about 4/3 of its size) instead of "
                        "playing it from beside the page")
    p.add_argument("--backend", choices=("auto", "gl", "numpy"), default="auto",
                   help="preview renderer: auto (default), gl or numpy")


def run(args) -> None:
    from ..report import write_take_extras
    from ._options import progress

    extras = write_take_extras(args.outdir, progress=progress(args), preview=not args.no_preview,
                               backend=args.backend, embed_video=args.embed_video)
    if not args.quiet:
        n = extras.numbers
        errors = ", ".join(f"{r} {v['rms_error']}" for r, v in n["regions"].items())
        print(f"{extras.report}: {n['frames']} frames, face in {n['detection_rate']} %, "
              f"RMS error ({n['error_unit']}) {errors}")
