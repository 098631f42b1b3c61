"""``keyshape sculpt``: write the sculpt kit (character with one target per key, contact sheet, README)."""

from __future__ import annotations

from pathlib import Path

from ..exceptions import InputError
from ._options import add_rig_options, mesh_choice

DESCRIPTION = (
    "Write KIT/sculpt.glb (the character with one morph target per key shape, named after it, each "
    "starting as the neutral), KIT/keys.png (the key frames from the video with the landmarks, region "
    "highlighted) and KIT/README.md. Sculpt the targets, export a .glb, and `keyshape retarget` drives "
    "it as it is."
)
EPILOG = """\
examples:
  keyshape sculpt out/keys.json --rig hero.glb -o kit/            # video and track from out/take.json
  keyshape sculpt keys.json --rig head.obj --rig-unit cm --video take.mp4 --track track.npz -o kit/
"""


def add_arguments(p) -> None:
    p.epilog = EPILOG
    p.add_argument("keys", type=Path, help="key file from `keyshape keys` (or `run`)")
    p.add_argument("--rig", type=Path, required=True, metavar="NEUTRAL",
                   help="the character: .glb/.gltf (kept whole), .obj, an OBJ rig folder or a USD rig")
    p.add_argument("--video", type=Path, default=None,
                   help="the take's video (default: the one named in take.json beside KEYS.json)")
    p.add_argument("--track", type=Path, default=None,
                   help="the take's track (default: track.npz beside KEYS.json, else the video is tracked)")
    add_rig_options(p, meshes="to put the targets on")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="KIT/",
                   help="the kit's folder: sculpt.glb, keys.png and README.md are written into it")
    p.add_argument("--force", action="store_true",
                   help="replace a kit already in KIT/ (default: refused, its sculpt.glb may hold an artist's work)")


def run(args) -> None:
    from ..app import check_kit_folder, write_sculpt_kit
    from ..io.keys_json import load_keys
    from ..io.rig import parse_unit

    keys = load_keys(args.keys)
    video = _video(args)
    check_kit_folder(args.output, overwrite=args.force, replace="--force")  # before any tracking
    _check_rig(args.rig)
    track = _track(args, video)
    kit = write_sculpt_kit(keys, args.rig, args.output, track=track, video=video,
                           unit=parse_unit(args.rig_unit), meshes=mesh_choice(args.mesh), overwrite=args.force,
                           neutral_source=_neutral(args))
    if not args.quiet:
        print(f"{kit.folder}: {kit.glb.name} ({keys.n_keys} targets to sculpt), {kit.sheet.name}, "
              f"{kit.readme.name}")


def _check_rig(rig: Path) -> None:
    """The character must exist (a .glb must look like one) before the take is tracked."""
    if not rig.exists():
        raise InputError(f"{rig}: file not found")
    if rig.suffix.lower() in (".glb", ".gltf"):
        from ..io.gltf import check_gltf_file

        check_gltf_file(rig)


def _video(args) -> Path:
    if args.video is not None:
        return args.video
    info = args.keys.parent / "take.json"
    if info.is_file():
        from ..io.take import load_take_info

        video = load_take_info(args.keys.parent).get("video")
        if not video:
            raise InputError(f"{info}: names no video; give --video")
        return Path(video)
    raise InputError(f"give --video: the take's video (no take.json beside {args.keys})")


def _neutral(args) -> Path | None:
    """The still image or clip of the keys' neutral (``--neutral FILE`` of the run), from take.json."""
    if not (args.keys.parent / "take.json").is_file():
        return None
    from ..io.take import load_take_info

    source = load_take_info(args.keys.parent).get("neutral_source")
    return Path(source) if source else None


def _track(args, video: Path):
    from ..io.track import load_track

    if args.track is not None:
        return load_track(args.track)
    beside = args.keys.parent / "track.npz"
    if beside.is_file():
        return load_track(beside)
    from ..capture import track_video
    from ._options import progress

    return track_video(video, progress=progress(args))
