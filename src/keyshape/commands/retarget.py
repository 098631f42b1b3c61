"""``keyshape retarget``: drive a rig with the weights and write the animation."""

from __future__ import annotations

from pathlib import Path

from ..exceptions import InputError

VERB = "retarget"
HELP = "drive a rig with the weights and write a binary glTF"
DESCRIPTION = ("Apply the weights to a rig whose targets are named after the key shapes; write the "
               "rig with a morph-weight animation (and the head rotation with --track).")


def add_arguments(p) -> None:
    p.add_argument("weights", type=Path, help="weights CSV from `keyshape solve`")
    p.add_argument("--rig", type=Path, required=True,
                   help="folder of OBJs (neutral.obj + <key name>.obj) or a .glb/.gltf with "
                        "morph targets named after the keys")
    p.add_argument("--track", type=Path, default=None,
                   help="track file: also animate the head rotation")
    p.add_argument("--allow-extra", action="store_true",
                   help="let rig targets that no key drives stay at 0 (default: an error listing them)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="ANIM.glb")


def run(args) -> None:
    from ..io.gltf import write_glb
    from ..io.track import load_track
    from ..io.weights_csv import load_weights_csv
    from ..pipeline import head_poses
    from ..retarget import Mapping, retarget
    from ..rig import load_rig

    weights = load_weights_csv(args.weights)
    rig = load_rig(args.rig)
    poses = None
    if args.track is not None:
        track = load_track(args.track)
        if track.n_frames != weights.n_frames:
            raise InputError(f"{args.track}: has {track.n_frames} frames but {args.weights} has "
                             f"{weights.n_frames}")
        poses = head_poses(track)
    anim = retarget(weights, Mapping.by_name(weights.names, rig.names, allow_extra=args.allow_extra))
    write_glb(args.output, rig, anim, poses=poses)
    if not args.quiet:
        print(f"{args.output}: {rig.n_targets} targets animated over {anim.n_frames} frames")
