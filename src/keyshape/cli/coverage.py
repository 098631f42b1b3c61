"""``keyshape coverage``: how well an existing key set reaches a new take."""

from __future__ import annotations

from pathlib import Path

from ..defaults import MAX_ERROR
from ._argtypes import positive
from ._options import say

DESCRIPTION = ("Measure how well a key set (already sculpted, say) reaches a new take of the same actor: per "
               "region, each frame's RMS error of its best blend of the keys over time, the frames out of reach "
               "(error above --max-error) and the take's error against keys added from it (what "
               "`keyshape keys --extend` would add). Writes DIR/coverage.png and DIR/coverage.json.")


def add_arguments(p) -> None:
    p.add_argument("track", type=Path, metavar="TAKE.npz", help="the new take's track file")
    p.add_argument("--keys", type=Path, required=True, metavar="KEYS.json", help="the key set (from `keyshape keys`)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="DIR", help="folder for the picture and numbers")
    p.add_argument("--max-error", type=positive, default=MAX_ERROR, metavar="PCT",
                   help=f"the error target, RMS in %% of the inter-ocular distance (default {MAX_ERROR:g})")


def run(args) -> None:
    import json

    from ..app import coverage
    from ..io import load_keys, load_track
    from ..io.atomic import staged_folder
    from ..report.plots import coverage as coverage_plot

    track = load_track(args.track)
    keys = load_keys(args.keys)
    found = coverage(keys, track, max_error=args.max_error)
    times = track.times
    summary = {"format": "keyshape-coverage", "version": 1, "take": args.track.name, "keys": args.keys.name,
               "max_error": found.max_error, "unit": "% inter-ocular", "regions": found.summary(),
               "frames_out_of_reach": {r: found.out_of_reach(r).tolist() for r in found.errors}}
    with staged_folder(args.output, owned=lambda name: name in ("coverage.png", "coverage.json")) as stage:
        coverage_plot(found.errors, found.max_error, found.added, times, stage / "coverage.png")
        (stage / "coverage.json").write_text(json.dumps(summary, indent=1) + "\n")
    for region, row in summary["regions"].items():
        adds = row["keys_to_add"]
        adds = f"more than {len(row['error_vs_added_keys']) - 1}" if adds is None else str(adds)
        say(args, f"{region}: RMS error {row['rms_error']:.2f} %, {row['frames_out_of_reach']} frames out of reach "
                  f"({100 * row['share_out_of_reach']:.1f} %); --extend would add {adds} key(s)")
    say(args, f"{args.output}/coverage.png, coverage.json")
