"""``keyshape solve``: the non-negative weights of every frame on the key shapes."""

from __future__ import annotations

from pathlib import Path

from ._options import add_solve_options, add_visibility_option, say, solve_kwargs

DESCRIPTION = ("Write every frame as neutral + a non-negative blend of the key shapes' deltas, per region "
               "(exact batched NNLS).")


def add_arguments(p) -> None:
    p.add_argument("track", type=Path, help="track file (.npz)")
    p.add_argument("keys", type=Path, help="key file from `keyshape keys`")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="WEIGHTS.csv")
    add_solve_options(p)
    add_visibility_option(p)


def run(args) -> None:
    from ..app import solve_track_file
    from ..io import load_keys, save_weights_csv

    keys = load_keys(args.keys)
    solved = solve_track_file(args.track, keys, visibility=args.visibility,
                              **solve_kwargs(args))  # streamed: no take-sized copies
    save_weights_csv(solved.weights, args.output)
    say(args, f"{args.output}: {solved.weights.n_frames} frames x {solved.weights.n_channels} keys; {solved.gaps}")
