"""keyshape for Blender: bring a keyshape take onto a character's shape keys, run keyshape on a
video, open a sculpt kit ready to sculpt.

Panel: *3D Viewport > Sidebar (N) > keyshape*. Written by ``keyshape blender-addon -o DIR`` as an
installable zip (*Edit > Preferences > Add-ons > Install from Disk*).

Licence: GPL-3.0-or-later. The add-on runs inside Blender and imports ``bpy`` (GPL), so it is
offered under the GPL; keyshape itself (MIT) is not linked to it: the add-on reads keyshape's files
and runs the ``keyshape`` command as a separate program.
"""

bl_info = {
    "name": "keyshape",
    "author": "keyshape",
    "version": (0, 1, 0),
    "blender": (4, 2, 0),
    "location": "3D Viewport > Sidebar > keyshape",
    "description": "Performance-driven facial animation: a video's key-shape weights onto shape keys",
    "category": "Animation",
    "support": "COMMUNITY",
}


def register():
    from . import ui

    ui.register()


def unregister():
    from . import ui

    ui.unregister()
