"""``keyshape run``: every stage in one go, video to an animated character and its report."""

from __future__ import annotations

from pathlib import Path

from ._options import (
    add_capture_options,
    add_correspondence_option,
    add_key_options,
    add_normalize_option,
    add_solve_options,
    add_visibility_option,
    capture_kwargs,
    describe_keys,
    mesh_choice,
    progress,
    say,
    shell_command,
    solve_kwargs,
    stage_lines,
)

DESCRIPTION = ("Track, discover keys, solve and retarget in one go. Without --rig the character is "
               "keyshape's stylised head, with target shapes proposed from the key shapes.")
EPILOG = """\
examples:
  keyshape run take.mp4                                  # the default character, into ./keyshape-take/
  keyshape run take.mp4 -o out/                          # the same, into out/
  keyshape run take.mp4 --rig avatar.glb --auto-targets -o out/   # an ARKit rig (Ready Player Me, VRM, ...)
  keyshape run take.mp4 --rig kit/sculpt.glb -o out/     # a character sculpted in the kit of `keyshape sculpt`
  keyshape run take.mp4 --rig hero.glb --map map.json -o out/     # a rig's own shapes, through a mapping
  keyshape run take.mp4 --keys actor_keys.json -o out/   # a key set shared across takes
then: open out/report.html, or `keyshape view out/`
"""
DEFAULT_OUTPUT = "keyshape-{name}"  # beside the current folder, as `keyshape demo` writes ./keyshape-demo


def add_arguments(p) -> None:
    p.epilog = EPILOG
    p.add_argument("video", type=Path, help="video file or folder of images")
    p.add_argument("--rig", type=Path, default=None,
                   help="character: OBJ folder, .glb/.gltf (kept whole, animation added), .vrm (its expressions; "
                        "the take also as animation.vrma, VRM Animation 1.0) or "
                        "USD, with "
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
    p.add_argument("--mesh", action="append", default=None, metavar="NAME",
                   help="with --auto-targets on a .glb/.gltf: the mesh(es) to propose targets on (repeatable; "
                        "default: the meshes with morph targets, else the head's mesh, else all)")
    add_normalize_option(p, when="with --auto-targets on a rig with its own blendshapes: ")
    p.add_argument("--no-refine", dest="refine", action="store_false",
                   help="with --auto-targets on an ARKit rig: skip render and compare (the character rendered "
                        "as driven, tracked again, and the jaw, lower lip, squint, outer brow and pucker targets "
                        "refined on the landmarks; one more tracking pass per target, about 9). Faster, "
                        "and those targets follow MediaPipe's scores alone")
    p.add_argument("--floor", action="store_true",
                   help="with --auto-targets on an ARKit rig: start from MediaPipe's own scores less the "
                        "character's rest reading on every target, and keep the key route or its refinement "
                        "only where render and compare shows it explains the video better (map.json's refined "
                        "steps say which). Measured, not yet the default (BENCHMARKS.md, issue 35)")
    add_capture_options(p)
    add_visibility_option(p)
    p.add_argument("-o", "--output", type=Path, default=None, metavar="OUTDIR",
                   help="output folder: track.npz, keys.json, weights.csv, animation.glb, preview.mp4, the "
                        "pictures and report.html (default ./keyshape-VIDEONAME, e.g. ./keyshape-take for "
                        "take.mp4)")
    add_key_options(p)
    add_solve_options(p)
    p.add_argument("--no-preview", action="store_true",
                   help="skip the side-by-side preview video (pictures and report are still written)")
    add_format_option(p)


def add_format_option(p) -> None:
    """``--format``: the animation also as FBX, .blend (Blender, the `blender` extra) or USD."""
    p.add_argument("--format", dest="formats", action="append", choices=("fbx", "blend", "usd"), default=[],
                   metavar="{fbx,blend,usd}",
                   help="also write the animation as animation.fbx, animation.blend (through Blender: "
                        'pip install "keyshape[blender]") or animation.usda; give it again for several. '
                        "animation.glb is always written (the report and viewer play it)")


def check(parser, args) -> None:
    """Usage errors argparse cannot see (exit code 2); fills in the default output folder."""
    if not args.auto_targets and (args.correspondence or args.normalize or args.front != "auto" or not args.refine
                                  or args.mesh or args.floor):
        parser.error("--correspondence, --front, --normalize, --no-refine, --mesh and --floor only apply with "
                     "--auto-targets")
    if is_track_file(args.video):
        parser.error(track_file_message(args.video))
    if args.output is None:
        args.output = default_output(args.video)


def default_output(video: Path) -> Path:
    """``./keyshape-<video name without suffix>`` (a folder of images: its name)."""
    name = (video.name if video.is_dir() else video.stem) or "take"
    return Path(DEFAULT_OUTPUT.format(name=name))


def is_track_file(path: Path) -> bool:
    """Whether ``path`` is a track file (``.npz``, as `keyshape track` writes) rather than a video."""
    return path.suffix.lower() == ".npz" and path.is_file()


def track_file_message(path: Path) -> str:
    """What to run on a track file, which ``run`` (a video's whole path) cannot take."""
    keys = path.with_name("keys.json")
    return (f"{path} is a track file, not a video: give run the video it was tracked from, or run "
            f"`{shell_command('keyshape', 'keys', path, '-o', keys)}` then "
            f"`{shell_command('keyshape', 'solve', path, keys, '-o', path.with_name('weights.csv'))}`")


def run(args) -> None:
    from ..app import RunOptions, run_take

    options = RunOptions(rig=args.rig, mapping=args.map, keys=args.keys, regions=args.regions,
                         n_keys=args.count, max_error=args.max_error, method=args.method,
                         mirror=args.mirror, neutral=args.neutral, auto_targets=args.auto_targets,
                         correspondence=args.correspondence, front=args.front, normalize=args.normalize,
                         meshes=None if args.mesh is None else tuple(mesh_choice(args.mesh)),
                         refine=args.refine, floor=args.floor, capture=capture_kwargs(args),
                         preview=not args.no_preview,
                         formats=tuple(args.formats),
                         **solve_kwargs(args))
    with stage_lines(args):
        summary = run_take(args.video, args.output, options, progress=progress(args))
    keys = summary.keys
    say(args, f"{args.video.name}: {summary.n_frames} frames, face in {100 * summary.detection_rate:.1f} %, "
              f"neutral frame {keys.neutral_frame}")
    say(args, f"keys: {describe_keys(keys)}")
    say(args, f"fit: RMS error {summary.error_pct:.2f} % of the inter-ocular distance; gaps: {summary.gaps}")
    say(args, f"wrote {args.output}/: {', '.join(summary.files)} in {summary.seconds:.1f} s")
    say(args, f"see it: open {shell_command(args.output / 'report.html')} or run "
              f"`{shell_command('keyshape', 'view', args.output)}`")
