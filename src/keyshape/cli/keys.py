"""``keyshape keys``: discover key shapes (real frames) per region, from one take or several;
or extend a sculpted key set to new takes (``--extend``)."""

from __future__ import annotations

from pathlib import Path

from ._options import add_key_options, add_visibility_option, describe_keys, progress, say, without_visibility

DESCRIPTION = ("Choose K real frames per face region that span the performance (the key shapes an artist "
               "will sculpt on the character), plus the mirror image of each key where it reaches what the "
               "keys cannot. Give a range-of-motion take (see `keyshape rom`) and the actor's takes together "
               "for one key set that covers them all; videos are tracked first. With --extend KEYS.json, keep "
               "that key set whole and add the fewest frames of the takes that bring them within --max-error: "
               "the artist sculpts only the new keys. With more than 2048 frames in all, each region's keys are "
               "searched among 2048 of them (the extremes and evenly spaced frames), so memory stays bounded.")

def add_arguments(p) -> None:
    p.add_argument("tracks", type=Path, nargs="+", metavar="TAKE",
                   help="track file(s) (.npz with points and fps, or a landmark CSV frame,x0,y0[,z0],x1,... "
                        "from another tool) or videos (tracked with MediaPipe first, e.g. rom.mp4); several "
                        "takes of one actor give one key set")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="KEYS.json")
    p.add_argument("--extend", type=Path, default=None, metavar="KEYS.json",
                   help="extend this key set instead of choosing a new one: every key stays (name, shape, "
                        "frame); the fewest frames of the takes that bring each region's RMS error below "
                        "--max-error are added (at most 24 per region), named after the region's last key")
    add_key_options(p)
    add_visibility_option(p)


def _load(path: Path, args):
    from ..app import VIDEO_SUFFIXES
    from ..io import load_track

    if path.suffix.lower() in VIDEO_SUFFIXES:
        from ..capture import track_video

        say(args, f"{path.name}: tracking")
        return track_video(path, progress=progress(args), visibility=args.visibility)
    return without_visibility(load_track(path), args)


def run(args) -> None:
    from ..app import discover_keys, extend_keys, fit_errors
    from ..io import load_keys, save_keys

    old = load_keys(args.extend) if args.extend is not None else None
    tracks = [_load(path, args) for path in args.tracks]
    names = [path.name for path in args.tracks]
    if old is None:
        keys = discover_keys(tracks, regions=args.regions, n_keys=args.count, method=args.method,
                             neutral=args.neutral, take=names, max_error=args.max_error, mirror=args.mirror)
    else:
        keys = extend_keys(old, tracks, take=names, max_error=args.max_error, mirror=args.mirror)
    save_keys(keys, args.output)
    if old is None:
        say(args, f"{args.output}: neutral frame {keys.neutral_frame}; " + describe_keys(keys))
    else:
        added = [n for n in keys.names if n not in old.names]
        sculpt = [n for n in added if not keys.mirror_of[keys.names.index(n)]]
        say(args, f"{args.output}: {old.n_keys} keys kept, {len(added)} added"
                  + (f" (to sculpt: {', '.join(sculpt)})" if sculpt else " (nothing new to sculpt)"))
    if not args.quiet:
        errors, unit = fit_errors(tracks, keys)
        say(args, "fit: " + "; ".join(f"{r}: K = {len(keys.keys_of(r))}, RMS error {e:.2f} {unit}"
                                      for r, e in errors.items()))
