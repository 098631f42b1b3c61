"""``keyshape keys``: discover key shapes (real frames) per region, from one take or several."""

from __future__ import annotations

from pathlib import Path

from ._options import add_key_options, describe_keys, say

DESCRIPTION = ("Choose K real frames per face region that span the performance (the key shapes an artist "
               "will sculpt on the character). With more than 2048 frames in all (long or many takes), each "
               "region's keys are searched among 2048 of them (the extremes and evenly spaced frames), so "
               "memory stays bounded; --count auto still measures every frame.")


def add_arguments(p) -> None:
    p.add_argument("tracks", type=Path, nargs="+", metavar="TRACK",
                   help="track file(s) (.npz with points and fps, or a landmark CSV frame,x0,y0[,z0],"
                        "x1,... from another tool); several takes of one actor give one key set")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="KEYS.json")
    add_key_options(p)


def run(args) -> None:
    from ..app import discover_keys, fit_errors
    from ..io import load_track, save_keys

    tracks = [load_track(path) for path in args.tracks]
    keys = discover_keys(tracks, regions=args.regions, n_keys=args.count, method=args.method,
                         neutral=args.neutral, take=[path.name for path in args.tracks],
                         max_error=args.max_error)
    save_keys(keys, args.output)
    say(args, f"{args.output}: neutral frame {keys.neutral_frame}; " + describe_keys(keys))
    if not args.quiet:
        errors, unit = fit_errors(tracks, keys)
        say(args, "fit: " + "; ".join(f"{r}: K = {len(keys.keys_of(r))}, RMS error {e:.2f} {unit}"
                                      for r, e in errors.items()))
