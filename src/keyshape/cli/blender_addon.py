"""``keyshape blender-addon``: write keyshape's Blender add-on as an installable zip."""

from __future__ import annotations

from pathlib import Path

DESCRIPTION = (
    "Write keyshape's Blender add-on (Blender 4.2 and later) as an installable zip: a panel in the 3D "
    "Viewport's sidebar that imports a keyshape take folder onto the selected character's shape keys "
    "(by name or through a map.json, with a preview of the mapping), runs `keyshape run` on a video for "
    "the selected character and brings the result in, and opens a sculpt kit ready to sculpt. "
    "Install it in Blender: Edit > Preferences > Add-ons > Install from Disk. The add-on is GPL-3.0-or-later "
    "(it imports Blender's bpy); keyshape itself stays MIT and runs as a separate program."
)
EPILOG = """\
examples:
  keyshape blender-addon -o dist/          # writes dist/keyshape_blender-<version>.zip
"""


def add_arguments(p) -> None:
    p.epilog = EPILOG
    # dest "folder": -o names a folder here, not a file (the command line's output-file checks skip it)
    p.add_argument("-o", "--output", dest="folder", type=Path, default=Path("."), metavar="DIR",
                   help="folder to write the zip into (default: the current folder)")


def run(args) -> None:
    from ..io.blender import write_addon

    path = write_addon(args.folder)
    if not args.quiet:
        print(f"wrote {path}: in Blender, Edit > Preferences > Add-ons > Install from Disk, then "
              "3D Viewport > Sidebar (N) > keyshape")
