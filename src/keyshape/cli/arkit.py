"""``keyshape arkit``: MediaPipe's own 52 ARKit-style scores as a Live Link Face CSV.

``keyshape track`` keeps the scores MediaPipe's blendshape model gives every frame; this verb
writes them, with the head rotation from the alignment, in the format of Epic's Live Link Face
app, so the key-shape path can be compared with what the tracker's fixed ARKit rig gives.
"""

from __future__ import annotations

from pathlib import Path

DESCRIPTION = ("Write the 52 ARKit-style scores that `keyshape track` kept, with the head rotation, "
               "as a Live Link Face CSV (Timecode, BlendShapeCount, the ARKit names in Live Link's "
               "order, head and eye rotations).")


def add_arguments(p) -> None:
    p.add_argument("track", type=Path, help="track file written by `keyshape track`")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="TAKE.csv")


def run(args) -> None:
    from ..app import arkit_scores, head_poses
    from ..io.livelink import write_livelink_csv
    from ..io.track import load_track

    track = load_track(args.track)
    scores = arkit_scores(track, source=args.track)
    write_livelink_csv(args.output, scores, poses=head_poses(track))
    if not args.quiet:
        print(f"{args.output}: {scores.n_frames} frames of {scores.n_channels} ARKit scores")
