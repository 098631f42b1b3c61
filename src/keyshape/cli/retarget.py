"""``keyshape retarget``: drive a rig with the weights and write the animation."""

from __future__ import annotations

import tempfile
from pathlib import Path

from ..exceptions import InputError, UsageError
from ._options import add_rig_options

DESCRIPTION = (
    "Apply the weights to a rig: targets named after the key shapes, or any targets through a "
    "mapping (--map). Writes each output in the format its suffix (or --format) names: .glb "
    "(a glTF rig's file kept whole, with a morph-weight animation added), .usd/.usda/.usdc/"
    ".usdz (UsdSkel; a USD rig's stage kept whole), .csv (target weights) or --format livelink "
    "(Live Link Face CSV for ARKit-named targets), .fbx or .blend (through Blender's own exporters: "
    'pip install "keyshape[blender]"; a glTF rig\'s file kept whole) or .vrma (VRM Animation 1.0 for a '
    "--rig avatar.vrm: its expressions, head and gaze). With --track, the head rotation "
    "is written too. A mirrored key (named KEY_mirror) whose target the rig lacks or holds neutral gets "
    "the mirror image of KEY's target on the symmetric mesh."
)
EPILOG = """\
mapping file (JSON, gains >= 0; a key may drive several targets):
  {"lower_03": {"jawOpen": 0.8, "mouthFunnel": 0.3}, "upper_01": {"browInnerUp_L": 1.0}}
examples:
  keyshape retarget weights.csv --rig hero.glb --track track.npz -o hero_anim.glb
  keyshape retarget weights.csv --rig ict/ --rig-unit cm --map arkit.json -o face.usda -o face.glb
  keyshape retarget weights.csv --map arkit.json --format livelink -o take_livelink.csv
  keyshape retarget weights.csv --rig robot.glb --map map.json --track track.npz -o anim.fbx -o anim.blend
  keyshape retarget weights.csv --rig avatar.vrm --track track.npz -o take.vrma
"""


def add_arguments(p) -> None:
    p.epilog = EPILOG
    p.add_argument("weights", type=Path, help="weights CSV from `keyshape solve`")
    p.add_argument("--rig", type=Path, default=None,
                   help="folder of OBJs (neutral.obj + <target>.obj), a single .obj, a .glb/.gltf with "
                        "named morph targets, a .vrm avatar (its expressions), or a USD file with UsdSkel "
                        "blend shapes; required except for CSV outputs through --map")
    p.add_argument("--map", type=Path, default=None, metavar="MAP.json",
                   help="key -> targets gains (JSON); default: each key drives the target of its name")
    p.add_argument("--track", type=Path, default=None,
                   help="track file: also animate the head rotation (and the eyes, where the rig "
                        "has eye nodes, and in Live Link Face CSV); its gaze scores drive the gaze "
                        "targets of a MAP.json with a \"gaze\" section (what run --auto-targets writes)")
    p.add_argument("--allow-extra", action="store_true",
                   help="without --map: let rig targets that no key drives stay at 0 (default: an error "
                        "listing them; ARKit gaze targets, eyeLook*, are always let through and, with "
                        "--track, turned by the irises)")
    p.add_argument("--format", choices=("glb", "usd", "csv", "livelink", "fbx", "blend", "vrma"), default=None,
                   help="output format for every -o (default: from each suffix; livelink must be asked for)")
    add_rig_options(p)
    p.add_argument("--head", default=None, metavar="NODE",
                   help="glTF node to turn with the head (default: a joint or node named like 'head' "
                        "above the face meshes)")
    p.add_argument("-o", "--output", type=Path, required=True, action="append", metavar="OUT",
                   help="output file; give -o several times for several files")


def run(args) -> None:
    from ..io import Format, export, format_of
    from ..io.weights_csv import load_weights_csv
    from ..targets import retarget

    formats = [format_of(out, args.format) for out in args.output]
    if Format.VRMA in formats and (args.rig is None or args.rig.suffix.lower() != ".vrm"):
        out = args.output[formats.index(Format.VRMA)]
        raise UsageError(f"{out}: a .vrma animates a VRM avatar: give it with --rig avatar.vrm")
    if {Format.FBX, Format.BLEND} & set(formats):
        from ..io.blender import check_blender

        check_blender()  # before any output is written
    weights = load_weights_csv(args.weights)
    rig = _rig(args, formats, Format)
    made = []
    if rig is not None and args.map is None:  # mirrored keys' targets, made from their sources'
        from ..targets import complete_mirrors, mirror_sources

        rig, made = complete_mirrors(rig, mirror_sources(weights.names))
    gaze_only = _free_gaze_targets(args, weights, rig)
    mapping = _mapping(args, weights, rig, allow_gaze=bool(gaze_only))
    anim = retarget(weights, mapping)
    poses, gaze, scores = _poses(args, weights)
    if gaze_only and gaze is not None:  # e.g. a take's own animation.glb: its eyes follow the irises
        from ..app import drive_gaze_targets

        anim = drive_gaze_targets(anim, gaze, taken=weights.names)
    if mapping.gaze and scores is not None:  # MAP.json's gaze targets follow the track's gaze scores
        from ..targets import drive_gaze

        anim = drive_gaze(anim, mapping, *scores)
    eyes = gaze.rotations() if gaze is not None else None
    source = args.rig if rig is not None and args.rig.is_file() and args.rig.suffix.lower() != ".obj" else None
    with tempfile.TemporaryDirectory(prefix="keyshape-retarget-") as scratch:
        if made and source is not None and source.suffix.lower() in (".glb", ".gltf"):
            from ..io.gltf import write_gltf_targets

            source = write_gltf_targets(source, Path(scratch) / "character.glb", rig)
        for out, chosen in zip(args.output, formats):
            export(anim, out, rig=rig, poses=poses, format=chosen, source=source, head=args.head,
                   eyes=eyes)
            if not args.quiet:
                print(_summary(out, chosen, anim, Format))
    if made and not args.quiet:
        print(f"mirrored targets made from their sources: {', '.join(made)}")
    if gaze_only and gaze is None and not args.quiet:
        print(f"gaze targets no key drives stay at rest ({', '.join(gaze_only)}): give --track to turn "
              "them with the irises")
    if mapping.gaze and scores is None and not args.quiet:
        print(f"{args.map}: its gaze targets follow the tracker's gaze scores; without --track (with scores) "
              f"they stay at rest ({', '.join(t for t, _, _ in mapping.gaze)})")


def _rig(args, formats, Format):
    from ..io.rig import load_rig, parse_unit

    if args.rig is not None:
        return load_rig(args.rig, unit=parse_unit(args.rig_unit))
    if args.map is None or any(f not in (Format.CSV, Format.LIVELINK) for f in formats):
        raise UsageError("--rig is required (only CSV and Live Link outputs through --map can do without)")
    return None


def _mapping(args, weights, rig, *, allow_gaze: bool):
    from ..targets import Mapping

    if args.map is not None:
        return Mapping.from_file(args.map, targets=None if rig is None else rig.names)
    return Mapping.by_name(weights.names, rig.names, allow_extra=args.allow_extra or allow_gaze)


def _free_gaze_targets(args, weights, rig) -> list[str]:
    """Without --map: the rig's ARKit gaze targets (``eyeLookInLeft`` ...) that no key drives, when
    every target no key drives is one (the gaze comes from the irises, not from key shapes)."""
    if args.map is not None or rig is None:
        return []
    from ..targets import GAZE_NAMES

    extra = [t for t in rig.names if t not in weights.names]
    return extra if extra and set(extra) <= set(GAZE_NAMES) else []


def _poses(args, weights):
    """(head poses, gaze, (scores, score names) or None) from --track, or (None, None, None)."""
    if args.track is None:
        return None, None, None
    from ..app import head_and_gaze
    from ..io.track import load_track

    track = load_track(args.track)
    if track.n_frames != weights.n_frames:
        raise InputError(f"{args.track}: has {track.n_frames} frames but {args.weights} has {weights.n_frames}")
    differ = (track.frame_index != weights.frame_index).nonzero()[0]
    if differ.size:
        i = int(differ[0])
        raise InputError(f"{args.weights}: row {i} is frame {weights.frame_index[i]} but row {i} of {args.track} "
                         f"is frame {track.frame_index[i]}: give the track the weights were solved from")
    scores = (track.blendshapes, track.blendshape_names) if track.blendshapes is not None else None
    return (*head_and_gaze(track), scores)


def _summary(out, chosen, anim, Format) -> str:
    text = f"{out}: {anim.n_channels} targets animated over {anim.n_frames} frames ({chosen.value})"
    if chosen is Format.LIVELINK:
        from ..io.livelink import livelink_columns

        sources, unused = livelink_columns(anim.names)
        text += f"; {len(sources)} of 52 ARKit coefficients"
        if unused:
            text += f"; not ARKit, left out: {unused}"
    return text
