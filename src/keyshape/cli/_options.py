"""Options and helpers shared by several verbs (kept import-light: argparse and the defaults only)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..defaults import (
    DEFAULT_METHOD,
    DEFAULT_N_KEYS,
    DEFAULT_REGIONS,
    DEFAULT_SMOOTHNESS,
    DEFAULT_UPPER,
    FRONTS,
    MAX_ERROR,
    MAX_KEYS,
)
from ..exceptions import UsageError
from ._argtypes import frame_rate, non_negative, positive, regions, weight_bound, whole


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """States the limits of every whole-number option (its type's ``limits``) in ``--help``."""

    def _get_help_string(self, action):
        text = action.help or ""
        limits = getattr(action.type, "limits", None)
        if limits is not None and "%(default)" not in text:
            low, high = limits
            text += f" [{low}..{high}]" if high is not None else f" [>= {low}]"
        return text


def formatter(prog):
    return _Formatter(prog, max_help_position=32)


COUNT_LIMIT = 64  # largest --count per region


def _count(text: str) -> int | str:
    return "auto" if text == "auto" else whole(1, COUNT_LIMIT)(text)


_count.limits = (1, COUNT_LIMIT)


def add_key_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--method", choices=("spa", "hull", "spread"), default=DEFAULT_METHOD,
                   help="key-shape selection: spa = successive projection on the deltas from neutral "
                        "(default); hull = convex hull of the leading principal components (paper); "
                        "spread = extreme projections on the principal components (paper)")
    p.add_argument("--count", type=_count, default=DEFAULT_N_KEYS, metavar="K",
                   help=f"key shapes per region (default {DEFAULT_N_KEYS}), or 'auto': the fewest per region whose "
                        f"RMS error is below --max-error (at most {MAX_KEYS})")
    p.add_argument("--max-error", type=positive, default=MAX_ERROR, metavar="PCT",
                   help=f"target of --count auto: RMS reconstruction error in %% of the "
                        f"inter-ocular distance (default {MAX_ERROR:g})")
    p.add_argument("--regions", type=regions, default=DEFAULT_REGIONS, metavar="SCHEME",
                   help="upper-lower (brows+eyes / mouth+jaw, default), whole, eyes "
                        "(brows / left eye / right eye / mouth), or a REGIONS.json mapping region "
                        "names to landmark indices")
    p.add_argument("--no-mirror", dest="mirror", action="store_false",
                   help="no mirrored keys (default: each key's left-right mirror image is added where it "
                        "reaches what the keys cannot, so a one-sided move seen on one side drives the "
                        "other side too; mirrored keys need no sculpting: their targets are mirrored)")
    p.add_argument("--neutral", type=_neutral, default=None, metavar="FRAME|FILE",
                   help="the neutral (resting) face: a frame of the (first) take, or a still image or short "
                        "clip of the same actor at rest (tracked; its median aligned shape is the neutral); "
                        "default: the least activated frame by MediaPipe's scores with the whole face in view")


def _neutral(text: str) -> int | Path:
    """``--neutral``: a frame number (>= 0) or an existing image or video file."""
    if text.isdigit():
        return int(text)
    path = Path(text)
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"must be a frame number >= 0 or an image or video file; got {text!r}")
    return path


def add_capture_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--start", type=whole(0), default=0, metavar="FRAME", help="first frame to track (default 0)")
    p.add_argument("--end", type=whole(1), default=None, metavar="FRAME",
                   help="stop before this frame (default: the last frame)")
    p.add_argument("--fps", type=frame_rate, default=None,
                   help="frame rate override (image folders default to 30); frames are then timed "
                        "at i / FPS instead of by the video's own timestamps")
    p.add_argument("--face", type=whole(0, 16), default=0, metavar="N",
                   help="which person to follow when several are visible: 0 = the largest face at "
                        "the start (default), 1 = the next largest, ...")
    p.add_argument("--one-euro", nargs="?", const="1.0,0.05", default=None, metavar="MINCUT,BETA",
                   help="causal One Euro filter on the landmarks, for live-like use (default "
                        "settings 1.0 Hz, 0.05). Offline, prefer the solve's zero-lag smoothing; "
                        "MediaPipe's video mode already smooths")
    p.add_argument("--workers", type=whole(1), default=None, metavar="N",
                   help="processes tracking overlapping segments of the video in parallel, each with "
                        "its own landmarker (default: one per core; 1 = one process)")


def add_visibility_option(p: argparse.ArgumentParser) -> None:
    """``--visibility auto|off``: whether the landmarks a hand covers count as hidden."""
    p.add_argument("--visibility", choices=("auto", "off"), default="auto",
                   help="landmarks covered by a hand: auto (default) = MediaPipe's hand landmarker finds the hands "
                        "in front of the face and the landmarks they cover count as hidden (no key from such a "
                        "frame, no part in the neutral, the fit and the solve); anything else, an expression, a "
                        "turn or the light, is never taken for an occluder; off = every landmark counts as seen")


def without_visibility(track, args):
    """``track`` with its visibility dropped under ``--visibility off`` (else as it is)."""
    if getattr(args, "visibility", "auto") == "off" and track.visibility is not None:
        import dataclasses

        return dataclasses.replace(track, visibility=None)
    return track


def add_solve_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--smooth", type=non_negative, default=DEFAULT_SMOOTHNESS, metavar="LAMBDA",
                   help=f"temporal smoothness, solved over the whole take with no lag (default "
                        f"{DEFAULT_SMOOTHNESS}; 0 = the paper's per-frame NNLS). Short gaps without a "
                        f"face are bridged, longer ones (> 0.5 s) hold the neutral")
    p.add_argument("--max", type=weight_bound, default=DEFAULT_UPPER, metavar="U",
                   help=f"upper bound of every weight, at most 5 (default {DEFAULT_UPPER:g}; 'none' lifts it to 5, "
                        f"the largest weight a weights file holds; the paper's NNLS has no bound, and a real "
                        f"take does not come near it)")
    p.add_argument("--convex", action="store_true",
                   help="also require the weights of each region to sum to at most 1")


def add_correspondence_option(p, when: str = "") -> None:
    """``--correspondence CORR.json`` and ``--front AXIS`` (``propose`` and ``run --auto-targets``; ``when``
    prefixes the help)."""
    p.add_argument("--correspondence", type=Path, default=None, metavar="CORR.json",
                   help=f"{when}landmark -> mesh point file (default: found automatically)")
    p.add_argument("--front", choices=FRONTS, default="auto", metavar="AXIS",
                   help=f"{when}the axis the character's face looks along, for the automatic correspondence: "
                        "+z (glTF), -y (Z-up exports), ...; default auto: tried in turn until MediaPipe finds "
                        "the face")


def add_normalize_option(p, when: str = "mapping: ") -> None:
    """``--normalize`` (``propose`` and ``run --auto-targets``; ``when`` prefixes the help)."""
    p.add_argument("--normalize", action="store_true",
                   help=f"{when}scale each target's gains so the key driving it most drives it fully "
                        "(stylised rigs whose targets exaggerate; default: the actor's amplitude)")


def add_rig_options(p, *, meshes: str | None = None) -> None:
    """``--rig-unit`` and, when ``meshes`` says what the meshes are chosen for, ``--mesh``."""
    p.add_argument("--rig-unit", default="m", metavar="UNIT",
                   help="length unit of OBJ characters: m (default), cm, mm, in, ft or metres per unit")
    if meshes:
        p.add_argument("--mesh", action="append", default=None, metavar="NAME",
                       help=f"glTF mesh(es) {meshes} (repeatable; default: the meshes with morph targets, "
                            "else the head's mesh, else all)")


def mesh_choice(names: list[str] | None) -> list[int | str] | None:
    """``--mesh`` values: mesh indices where they are digits, names otherwise (None: the default)."""
    if names is None:
        return None
    return [int(n) if n.isdigit() else n for n in names]


def solve_kwargs(args) -> dict:
    return {"smoothness": args.smooth, "upper": args.max, "convex": args.convex}


def capture_kwargs(args) -> dict:
    return {"start": args.start, "end": args.end, "fps": args.fps, "face": args.face,
            "one_euro": _one_euro(args.one_euro), "workers": args.workers,
            "visibility": getattr(args, "visibility", "auto")}


def _one_euro(text: str | None) -> dict | None:
    if text is None:
        return None
    try:
        min_cutoff, beta = (float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"--one-euro expects MINCUT,BETA such as 1.0,0.05; got {text!r}") from None
    if min_cutoff <= 0 or beta < 0:
        raise UsageError(f"--one-euro needs MINCUT > 0 and BETA >= 0; got {text!r}")
    return {"min_cutoff": min_cutoff, "beta": beta}


def progress(args) -> bool:
    """Progress bars only for a person watching a terminal."""
    return not args.quiet and sys.stderr.isatty()


def stage_lines(args):
    """A context in which each stage a run starts is one line (``keyshape: tracking take.mp4``) when
    stderr is not a terminal (a log, a CI job: no progress bars there) and not ``--quiet``. The lines
    go to stdout with the run's summary, so an error stays the one line on stderr."""
    import contextlib
    import logging

    if args.quiet or sys.stderr.isatty():
        return contextlib.nullcontext()
    from ..app import STAGE_LOGGER

    @contextlib.contextmanager
    def attached():
        logger = logging.getLogger(STAGE_LOGGER)
        handler = logging.StreamHandler(sys.stdout)
        handler.setFormatter(logging.Formatter("keyshape: %(message)s"))
        previous = logger.level
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
        try:
            yield
        finally:
            logger.removeHandler(handler)
            logger.setLevel(previous)

    return attached()


def say(args, text: str) -> None:
    if not args.quiet:
        print(text, flush=True)


def describe_keys(keys) -> str:
    """``upper: frames 3, 17, ...; lower: ...`` (``take:frame`` when the keys come from several takes)."""
    several = len(set(keys.takes)) > 1
    where = [f"{t}:{f}" if several else str(f) for t, f in zip(keys.takes, keys.frames)]
    parts = [f"{r}: frames {', '.join(where[k] for k in keys.keys_of(r) if not keys.mirror_of[k])}"
             for r in keys.regions]
    mirrored = [keys.mirror_of[k] for k in range(keys.n_keys) if keys.mirror_of[k]]
    if mirrored:
        parts.append(f"mirrored: {', '.join(mirrored)}")
    return "; ".join(parts)


def check_frame_range(parser, args) -> None:
    """``--start`` before ``--end`` (a usage error, exit code 2, before any work)."""
    end = getattr(args, "end", None)
    if end is not None and end <= args.start:
        parser.error(f"--end must be after --start; got --start {args.start} --end {end}")


def shell_command(*words) -> str:
    """A command line to print for the user to paste: every word shell-quoted
    (``keyshape view 'uni dir/out'``)."""
    import shlex

    return " ".join(shlex.quote(str(w)) for w in words)
