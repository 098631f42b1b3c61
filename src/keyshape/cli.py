"""The ``keyshape`` command: one sub-command per pipeline stage, plus ``run`` and ``demo``.

Exit codes: 0 success, 2 usage error, 1 any other error (one line; ``--debug`` for the traceback).
"""

from __future__ import annotations

import argparse
import sys
from importlib import resources
from pathlib import Path

from . import __version__
from ._defaults import DEFAULT_SMOOTHNESS, DEFAULT_UPPER
from .commands import discover
from .commands._argtypes import bound, non_negative, positive, whole
from .commands.propose import add_correspondence_option, add_normalize_option
from .exceptions import InputError, KeyshapeError

DEMO_CLIP = "data/WolfgangLanger_Pexels.mp4"

DESCRIPTION = """\
Turn a video of an actor's face into animation of any blendshape character
(Chuang & Bregler, Performance Driven Facial Animation using Blendshape Interpolation).

pipeline:  track VIDEO -> keys (real frames that span the performance)
           -> solve (non-negative weights per frame) -> retarget (drive a rig, write .glb)
"""

EPILOG = """\
examples:
  keyshape demo                                   # the whole path on the embedded clip
  keyshape run take.mp4 -o out/                   # track, keys, solve, default character
  keyshape track take.mp4 -o take.npz
  keyshape keys take.npz -o keys.json --count 10
  keyshape solve take.npz keys.json -o weights.csv
  keyshape retarget weights.csv --rig hero.glb --track take.npz -o hero.glb
"""


def _formatter(prog):
    return argparse.RawDescriptionHelpFormatter(prog, max_help_position=32)


def _count(text: str) -> int | str:
    return "auto" if text == "auto" else whole(1, 64)(text)


def add_key_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--method", choices=("spa", "hull", "spread"), default="spa",
                   help="key-shape selection: spa = successive projection on the deltas from neutral "
                        "(default); hull = convex hull of the leading principal components (paper); "
                        "spread = extreme projections on the principal components (paper)")
    p.add_argument("--count", type=_count, default=8, metavar="K",
                   help="key shapes per region (default 8), or 'auto': the fewest per region whose "
                        "RMS error is below --max-error (at most 24)")
    p.add_argument("--max-error", type=positive, default=2.0, metavar="PCT",
                   help="target of --count auto: RMS reconstruction error in %% of the "
                        "inter-ocular distance (default 2)")
    p.add_argument("--regions", default="upper-lower", metavar="SCHEME",
                   help="upper-lower (brows+eyes / mouth+jaw, default), whole, eyes "
                        "(brows / left eye / right eye / mouth), or a REGIONS.json mapping region "
                        "names to landmark indices")
    p.add_argument("--neutral", type=int, default=None, metavar="FRAME",
                   help="the neutral (resting) frame; default: chosen automatically as the frame "
                        "closest to the median aligned shape")


def add_capture_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--start", type=int, default=0, metavar="FRAME", help="first frame to track (default 0)")
    p.add_argument("--end", type=int, default=None, metavar="FRAME",
                   help="stop before this frame (default: the last frame)")
    p.add_argument("--fps", type=float, default=None,
                   help="frame rate override (image folders default to 30)")
    p.add_argument("--face", type=int, default=0, metavar="N",
                   help="which person to follow when several are visible: 0 = the largest face at "
                        "the start (default), 1 = the next largest, ...")
    p.add_argument("--one-euro", nargs="?", const="1.0,0.05", default=None, metavar="MINCUT,BETA",
                   help="causal One Euro filter on the landmarks, for live-like use (default "
                        "settings 1.0 Hz, 0.05). Offline, prefer the solve's zero-lag smoothing; "
                        "MediaPipe's video mode already smooths")


def add_solve_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--smooth", type=non_negative, default=DEFAULT_SMOOTHNESS, metavar="LAMBDA",
                   help=f"temporal smoothness, solved over the whole take with no lag (default "
                        f"{DEFAULT_SMOOTHNESS}; 0 = the paper's per-frame NNLS). Short gaps without a "
                        f"face are bridged, longer ones (> 0.5 s) hold the neutral")
    p.add_argument("--max", type=bound, default=DEFAULT_UPPER, metavar="U",
                   help=f"upper bound of every weight (default {DEFAULT_UPPER:g}; 'none' lifts it)")
    p.add_argument("--convex", action="store_true",
                   help="also require the weights of each region to sum to at most 1")


def solve_kwargs(args) -> dict:
    return {"smoothness": args.smooth, "upper": args.max, "convex": args.convex}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="keyshape", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=_formatter)
    parser.add_argument("--version", action="version", version=f"keyshape {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", help="show the full traceback on errors")
    common.add_argument("-q", "--quiet", action="store_true", help="no progress bars or summaries")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)

    p = sub.add_parser("track", parents=[common], formatter_class=_formatter,
                       help="track the face in a video (MediaPipe, 478 landmarks)",
                       description="Track the face in every frame of VIDEO with MediaPipe's "
                                   "FaceLandmarker (vendored model). Writes points (pixels), fps, "
                                   "the 52 ARKit-style scores and the head matrix to TRACK.npz; "
                                   "frames without a face are NaN.")
    p.add_argument("video", type=Path, help="video file (anything PyAV opens; rotation metadata "
                                            "is honoured) or a folder of images")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="TRACK.npz")
    add_capture_options(p)

    p = sub.add_parser("keys", parents=[common], formatter_class=_formatter,
                       help="discover key shapes (real frames) per region",
                       description="Choose K real frames per face region that span the performance "
                                   "(the key shapes an artist will sculpt on the character). With more "
                                   "than 2048 frames in all (long or many takes), each region's keys are "
                                   "searched among 2048 of them (the extremes and evenly spaced frames), "
                                   "so memory stays bounded; --count auto still measures every frame.")
    p.add_argument("tracks", type=Path, nargs="+", metavar="TRACK",
                   help="track file(s) (.npz with points and fps, or a landmark CSV frame,x0,y0[,z0],"
                        "x1,... from another tool); several takes of one actor give one key set")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="KEYS.json")
    add_key_options(p)

    p = sub.add_parser("solve", parents=[common], formatter_class=_formatter,
                       help="non-negative weights of every frame on the key shapes",
                       description="Write every frame as neutral + a non-negative blend of the key "
                                   "shapes' deltas, per region (exact batched NNLS).")
    p.add_argument("track", type=Path, help="track file (.npz)")
    p.add_argument("keys", type=Path, help="key file from `keyshape keys`")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="WEIGHTS.csv")
    add_solve_options(p)

    modules = discover()
    extra = ([m for m in modules if m.VERB in STAGE_VERBS], [m for m in modules if m.VERB not in STAGE_VERBS])
    for module in extra[0]:
        _add_module(sub, common, module)

    p = sub.add_parser("run", parents=[common], formatter_class=_formatter,
                       help="all stages: video -> track, keys, weights, animated .glb",
                       description="Track, discover keys, solve and retarget in one go. Without "
                                   "--rig the character is keyshape's stylised head, with target "
                                   "shapes proposed from the key shapes.")
    p.add_argument("video", type=Path, help="video file or folder of images")
    p.add_argument("--rig", type=Path, default=None,
                   help="character: OBJ folder, .glb/.gltf (kept whole, animation added) or USD, with "
                        "targets named after the keys (e.g. from `keyshape sculpt`) or --map")
    p.add_argument("--map", type=Path, default=None, metavar="MAP.json",
                   help="key -> rig target gains (JSON), for rigs with their own shape set")
    p.add_argument("--keys", type=Path, default=None, metavar="KEYS.json",
                   help="reuse this key set (e.g. shared across takes) instead of discovering one")
    p.add_argument("--auto-targets", action="store_true",
                   help="no sculpting: propose the rig's target shapes from the key shapes (or, for "
                        "a rig with its own blendshapes, a key -> shape mapping); see "
                        "docs/auto-targets.md. Also writes the correspondence used (and, for such a rig, "
                        "map.json) to OUTDIR, to edit and pass back")
    add_correspondence_option(p, when="with --auto-targets: ")
    add_normalize_option(p, when="with --auto-targets on a rig with its own blendshapes: ")
    add_capture_options(p)
    p.add_argument("-o", "--output", type=Path, required=True, metavar="OUTDIR")
    add_key_options(p)
    add_solve_options(p)
    p.add_argument("--no-preview", action="store_true",
                   help="skip the side-by-side preview video (pictures and report are still written)")

    p = sub.add_parser("demo", parents=[common], formatter_class=_formatter,
                       help="run the whole path on the embedded real clip",
                       description="Run the whole pipeline on the embedded clip "
                                   "(WolfgangLanger_Pexels.mp4, 472 frames) onto the default "
                                   "character.")
    p.add_argument("-o", "--output", type=Path, default=Path("keyshape-demo"), metavar="OUTDIR",
                   help="output folder (default ./keyshape-demo)")

    for module in extra[1]:
        _add_module(sub, common, module)
    return parser


STAGE_VERBS = ("retarget",)  # listed with the stages, before run and demo


def _add_module(sub, common, module) -> None:
    p = sub.add_parser(module.VERB, parents=[common], formatter_class=_formatter,
                       help=module.HELP, description=getattr(module, "DESCRIPTION", module.HELP))
    module.add_arguments(p)
    p.set_defaults(handler=module.run)


def _progress(args) -> bool:
    """Progress bars only for a person watching a terminal."""
    return not args.quiet and sys.stderr.isatty()


def _say(args, text: str) -> None:
    if not args.quiet:
        print(text, flush=True)


def cmd_track(args) -> None:
    from .capture import track_to_file

    summary = track_to_file(args.video, args.output, progress=_progress(args), **capture_kwargs(args))
    n, found = summary["n_frames"], summary["n_faces"]
    _say(args, f"{args.output}: {n} frames, face in {found} ({100 * found / n:.1f} %), "
               f"{summary['fps']:g} fps")


def capture_kwargs(args) -> dict:
    return {"start": args.start, "end": args.end, "fps": args.fps, "face": args.face,
            "one_euro": _one_euro(args.one_euro)}


def _one_euro(text: str | None) -> dict | None:
    if text is None:
        return None
    try:
        min_cutoff, beta = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--one-euro expects MINCUT,BETA such as 1.0,0.05; got {text!r}") from None
    if min_cutoff <= 0 or beta < 0:
        raise InputError(f"--one-euro needs MINCUT > 0 and BETA >= 0; got {text!r}")
    return {"min_cutoff": min_cutoff, "beta": beta}


def cmd_keys(args) -> None:
    from .io.keys_json import save_keys
    from .io.track import load_track
    from .pipeline import discover_keys, fit_errors

    tracks = [load_track(path) for path in args.tracks]
    keys = discover_keys(tracks, regions=args.regions, n_keys=args.count, method=args.method,
                         neutral=args.neutral, take=[path.name for path in args.tracks],
                         max_error=args.max_error)
    save_keys(keys, args.output)
    _say(args, f"{args.output}: neutral frame {keys.neutral_frame}; " + _describe_keys(keys))
    if not args.quiet:
        errors, unit = fit_errors(tracks, keys)
        _say(args, "fit: " + "; ".join(f"{r}: K = {len(keys.keys_of(r))}, RMS error {e:.2f} {unit}"
                                       for r, e in errors.items()))


def _describe_keys(keys) -> str:
    several = len(set(keys.takes)) > 1
    where = [f"{t}:{f}" if several else str(f) for t, f in zip(keys.takes, keys.frames)]
    parts = [f"{r}: frames {', '.join(where[k] for k in keys.keys_of(r))}" for r in keys.regions]
    return "; ".join(parts)


def cmd_solve(args) -> None:
    from .io.keys_json import load_keys
    from .io.track import load_track
    from .io.weights_csv import save_weights_csv
    from .pipeline import solve_take

    track = load_track(args.track)
    keys = load_keys(args.keys)
    solved = solve_take(track, keys, **solve_kwargs(args))
    save_weights_csv(solved.weights, args.output)
    _say(args, f"{args.output}: {solved.weights.n_frames} frames x {solved.weights.n_channels} keys; "
               f"{solved.gaps}")


def _run(args, video: Path) -> None:
    from .workflow import RunOptions, run_take

    options = RunOptions(rig=args.rig, mapping=args.map, keys=args.keys, regions=args.regions,
                         n_keys=args.count, max_error=args.max_error, method=args.method,
                         neutral=args.neutral, auto_targets=args.auto_targets,
                         correspondence=args.correspondence, normalize=args.normalize,
                         capture=capture_kwargs(args), preview=not args.no_preview,
                         **solve_kwargs(args))
    summary = run_take(video, args.output, options, progress=_progress(args))
    keys = summary.keys
    _say(args, f"{video.name}: {summary.n_frames} frames, face in {100 * summary.detection_rate:.1f} %, "
               f"neutral frame {keys.neutral_frame}")
    _say(args, f"keys: {_describe_keys(keys)}")
    _say(args, f"fit: RMS error {summary.error_pct:.2f} % of the inter-ocular distance; gaps: {summary.gaps}")
    _say(args, f"wrote {args.output}/: {', '.join(summary.files)} in {summary.seconds:.1f} s")
    _say(args, f"see it: open {args.output / 'report.html'} or run `keyshape view {args.output}`")


def cmd_run(args) -> None:
    _run(args, args.video)


def cmd_demo(args) -> None:
    args.rig, args.regions, args.count, args.method, args.neutral = None, "upper-lower", 8, "spa", None
    args.map, args.keys, args.max_error, args.auto_targets = None, None, 2.0, False
    args.correspondence, args.normalize = None, False
    args.start, args.end, args.fps, args.face, args.no_preview = 0, None, None, 0, False
    args.one_euro, args.smooth, args.max, args.convex = None, DEFAULT_SMOOTHNESS, DEFAULT_UPPER, False
    clip = Path(str(resources.files("keyshape").joinpath(DEMO_CLIP)))
    _run(args, clip)


COMMANDS = {"track": cmd_track, "keys": cmd_keys, "solve": cmd_solve,
            "run": cmd_run, "demo": cmd_demo}


def _blas_threads():
    """One BLAS thread unless the user chose: keyshape's linear algebra is many small K x K
    products, which threads slow down (measured 1.5-3x on 2 cores); set OPENBLAS_NUM_THREADS
    or OMP_NUM_THREADS to override."""
    import contextlib
    import os

    if any(v in os.environ for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")):
        return contextlib.nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``keyshape``; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.verb == "run" and not args.auto_targets and (args.correspondence or args.normalize):
        parser.error("--correspondence and --normalize only apply with --auto-targets")
    try:
        handler = getattr(args, "handler", None) or COMMANDS[args.verb]
        with _blas_threads():
            handler(args)
    except KeyboardInterrupt:
        print("keyshape: interrupted", file=sys.stderr)
        return 130
    except KeyshapeError as exc:
        if args.debug:
            raise
        print(f"keyshape: error: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # one clear line for anything unexpected too
        if args.debug:
            raise
        print(f"keyshape: error: {exc.__class__.__name__}: {exc} (run with --debug for details)",
              file=sys.stderr)
        return 1
    return 0
