"""``keyshape propose``: propose a character's target shapes (or a mapping onto its own) for the key shapes."""

from __future__ import annotations

from pathlib import Path

from ..exceptions import UsageError
from ._argtypes import positive
from ._options import add_correspondence_option, add_normalize_option, add_rig_options, mesh_choice, shell_command

DESCRIPTION = (
    "Propose, for every key shape, the character's version of it, so the character moves without "
    "sculpting (an artist can refine the result). Two routes: transfer (the key's landmark motion carried "
    "onto the mesh and spread smoothly; writes the character with one target per key, as .glb or an OBJ "
    "folder) and mapping (for a rig with blendshapes of its own, ARKit or any: each key as a non-negative "
    "mix of them; writes MAP.json for `keyshape retarget --map`). The output's suffix picks the route: "
    ".json -> mapping, .glb or a folder -> transfer. Landmarks are matched to the mesh by --correspondence "
    "(JSON), or found by rendering the character from the front and tracking the render (human-like heads "
    "facing +Z, MediaPipe key shapes)."
)
EPILOG = """\
correspondence file (JSON; landmark index -> vertex id, [x, y, z] point, or barycentric):
  {"landmarks": {"33": 1204, "263": 2210, "61": [0.031, -0.042, 0.087]}}
examples:
  keyshape propose out/keys.json -o head.glb                       # the built-in stylised head
  keyshape propose out/keys.json --rig face.glb -o face_targets.glb # transfer onto a human-like head
  keyshape propose out/keys.json --rig ict/ --rig-unit cm -o map.json  # mapping onto ARKit shapes
  keyshape propose keys.json --rig robot.glb --correspondence robot.json -o robot_map.json
"""


def add_arguments(p) -> None:
    p.epilog = EPILOG
    p.add_argument("keys", type=Path, help="key file from `keyshape keys` (or `run`)")
    p.add_argument("--rig", type=Path, default=None,
                   help="the character: .glb/.gltf, .obj, an OBJ rig folder or a USD rig (default: the "
                        "built-in stylised head)")
    add_correspondence_option(p)
    p.add_argument("--save-correspondence", type=Path, default=None, metavar="CORR.json",
                   help="also write the correspondence used, to check or edit it")
    add_rig_options(p, meshes="to propose targets on")
    add_normalize_option(p)
    p.add_argument("--falloff", type=positive, default=1.0,
                   help="transfer: how far motion spreads beyond the moving landmarks, in face radii (default 1)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="OUT",
                   help="MAP.json (mapping route), .glb or a folder (transfer route)")


def run(args) -> None:
    from ..io.keys_json import load_keys

    keys = load_keys(args.keys)
    route = _route(args.output)
    if route == "mapping" and args.rig is None:
        raise UsageError("a mapping needs --rig: a rig with blendshapes of its own")
    character, source = _character(args)
    colours = None
    if source is not None and args.correspondence is None:  # the character as it looks, for the render
        from ..io.gltf import read_colours

        colours = read_colours(source, meshes=mesh_choice(args.mesh))
    from ..targets import NoFaceFound, no_face_on

    try:
        if route == "mapping":
            _propose_mapping(args, keys, character, colours)
        else:
            _propose_targets(args, keys, character, source, colours)
    except NoFaceFound as error:
        if args.rig is None:
            raise
        raise no_face_on(error, args.rig, mesh_choice(args.mesh)) from None


def _route(output: Path) -> str:
    suffix = output.suffix.lower()
    if suffix == ".json":
        return "mapping"
    if suffix in (".glb", "") or output.is_dir():
        return "transfer"
    raise UsageError(f"-o {output}: expected MAP.json (mapping), a .glb or a folder (new targets)")


def _character(args):
    """(Rig, glTF source path or None); None rig for the built-in head."""
    if args.rig is None:
        return None, None
    from ..io.rig import load_rig, parse_unit

    if args.rig.suffix.lower() in (".glb", ".gltf"):
        from ..io.gltf import read_meshes

        return read_meshes(args.rig, meshes=mesh_choice(args.mesh))[0], args.rig
    return load_rig(args.rig, unit=parse_unit(args.rig_unit)), None


def _propose_mapping(args, keys, rig, colours) -> None:
    from ..targets import propose_mapping, resolve_correspondence

    corr = resolve_correspondence(args.correspondence, rig, keys.n_landmarks, front=args.front, colours=colours)
    _save_correspondence(args, corr)
    mapping = propose_mapping(keys, rig, correspondence=corr, normalize=args.normalize)
    mapping.save(args.output)
    if not args.quiet:
        then = shell_command("keyshape", "retarget", "WEIGHTS.csv", "--rig", args.rig, "--map", args.output)
        print(f"{args.output}: {mapping.n_keys} keys -> {mapping.n_targets} targets "
              f"(edit the gains, then `{then}`)")
        for key, gains in mapping.to_dict().items():
            top = sorted(gains.items(), key=lambda item: -item[1])[:4]
            shown = ", ".join(f"{t} {g:.2f}" for t, g in top) or "nothing (no target reproduces it: map by hand)"
            print(f"  {key}: {shown}")


def _propose_targets(args, keys, rig, source, colours) -> None:
    from ..targets import auto_targets

    auto = auto_targets(keys, rig, correspondence=args.correspondence, route="transfer", falloff=args.falloff,
                        front=args.front, colours=colours)
    _save_correspondence(args, auto.correspondence)
    written = _write_targets(args.output, auto.rig, source, mesh_choice(args.mesh))
    if not args.quiet:
        print(f"{written}: {auto.rig.n_targets} proposed targets named after the keys on "
              f"{args.rig or 'the built-in stylised head'} ({auto.rig.n_vertices} vertices); drive it with "
              f"`{shell_command('keyshape', 'retarget', 'WEIGHTS.csv', '--rig', written)}`")


def _write_targets(output: Path, rig, source, meshes) -> Path:
    if output.suffix.lower() == ".glb":
        from ..containers import Weights
        from ..io.gltf import write_glb, write_gltf_targets

        if source is not None:
            return write_gltf_targets(source, output, rig, meshes=meshes)
        import numpy as np

        return write_glb(output, rig, Weights(np.zeros((0, rig.n_targets)), rig.names, fps=30.0))
    from ..io.rig import save_obj_folder

    return save_obj_folder(rig, output)


def _save_correspondence(args, corr) -> None:
    if args.save_correspondence is not None:
        corr.save(args.save_correspondence)
        if not args.quiet:
            print(f"{args.save_correspondence}: {corr.n_corr} landmarks matched to the mesh")
