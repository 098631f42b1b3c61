"""``keyshape preview``: the side-by-side preview video of a ``keyshape run`` output folder."""

from __future__ import annotations

from pathlib import Path

from ._argtypes import whole

DESCRIPTION = ("Render an H.264 MP4: the source video with the tracked landmarks (one colour per region) "
               "beside the character driven by the weights and head rotation of animation.glb, over a "
               "strip of the current key weights. One output frame per track frame, at the track's "
               "frame rate. Renders with OpenGL (moderngl on EGL) or, without it, a slow numpy "
               "rasteriser.")


def add_arguments(p) -> None:
    p.add_argument("outdir", type=Path, help="output folder of `keyshape run` (holds take.json)")
    p.add_argument("-o", "--output", type=Path, default=None, metavar="PREVIEW.mp4",
                   help="default: OUTDIR/preview.mp4")
    p.add_argument("--height", type=whole(64, 4096), default=None, metavar="PX",
                   help="height of the picture row in pixels (default: the video's, kept within 360-720)")
    p.add_argument("--backend", choices=("auto", "gl", "numpy"), default="auto",
                   help="renderer: auto (OpenGL, numpy if unavailable; default), gl or numpy")


def run(args) -> None:
    from ..report import write_take_preview
    from ._options import progress

    path = write_take_preview(args.outdir, args.output, progress=progress(args), backend=args.backend,
                              height=args.height)
    if not args.quiet:
        print(f"{path}: preview written")
