"""The add-on's panel, operators and settings.

* **Take**: a keyshape take folder (``keyshape run`` output: ``weights.csv``, ``take.json``)
  onto the selected objects' shape keys, by name (the sculpt kit's targets) or through a mapping
  file (``map.json``: ``{key: {target: gain}}``); the panel previews which shape key each key drives.
* **Video**: ``keyshape run VIDEO --rig CHARACTER.glb`` on the selected character (exported to a
  temporary glTF with its shape keys), then the take it wrote is brought in as above.
* **Sculpt kit**: ``keyshape sculpt``'s ``sculpt.glb`` opened ready to sculpt: the face mesh active
  in Sculpt Mode, its first key's shape key active and shown alone, ``keys.png`` and the README loaded.
"""

from __future__ import annotations

import shlex
import shutil
import subprocess
import tempfile
from pathlib import Path

import bpy
from bpy.props import BoolProperty, PointerProperty, StringProperty

from . import anim, gltf, take

_PREVIEW_ROWS = 12
_cache: dict = {}


# --------------------------------------------------------------------------- settings


class KeyshapePreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    command: StringProperty(name="keyshape command", default="keyshape", subtype="FILE_PATH",
                            description="The keyshape program (`pip install keyshape`); a name on the PATH or a path")

    def draw(self, context):
        self.layout.prop(self, "command")


class KeyshapeSettings(bpy.types.PropertyGroup):
    folder: StringProperty(name="Take", subtype="DIR_PATH", description="Output folder of `keyshape run`")
    mapping: StringProperty(name="Map", subtype="FILE_PATH",
                            description="Mapping file {key: {target: gain}}; empty: map.json in the take "
                                        "folder if there is one, else shape keys named after the keys")
    video: StringProperty(name="Video", subtype="FILE_PATH", description="Video of the actor's face")
    output: StringProperty(name="Output", subtype="DIR_PATH",
                           description="Folder for the run's outputs (empty: beside the video)")
    auto_targets: BoolProperty(name="Auto targets", default=False,
                               description="keyshape run --auto-targets: propose a key -> shape key mapping")
    options: StringProperty(name="Options", description="More `keyshape run` options, e.g. --end 300 --count 6 "
                                                         "or --keys KEYS.json (a key set shared across takes)")
    kit: StringProperty(name="Sculpt kit", subtype="FILE_PATH", description="sculpt.glb of `keyshape sculpt`")


def _command() -> str:
    prefs = bpy.context.preferences.addons.get(__package__)
    return prefs.preferences.command if prefs else "keyshape"


# --------------------------------------------------------------------------- take -> shape keys


def targets_of(context) -> list:
    """The selected meshes with shape keys; else those below the active object."""
    chosen = anim.shape_key_meshes(context.selected_objects)
    if not chosen and context.active_object is not None:
        chosen = anim.shape_key_meshes([context.active_object, *context.active_object.children_recursive])
    return chosen


def mapping_for(folder: str, mapping: str, loaded: take.Take, shape_keys) -> take.TargetMap:
    """The mapping file given, else the take's ``map.json``, else by name."""
    path = Path(bpy.path.abspath(mapping)) if mapping else Path(folder) / "map.json"
    if path.is_file():
        return take.read_map(path)
    if mapping:
        raise ValueError(f"{path}: mapping file not found")
    return take.by_name(loaded, shape_keys)


def import_take(context, folder: str, mapping: str = "") -> tuple[int, int, list]:
    """Key the take in ``folder`` on the selected character; (n_frames, n_curves, what it lacks).

    The shape keys the mapping drives, from ``weights.csv``; the take's ``animation.glb`` (when it is
    there) gives the rest: the shape keys it animates that the mapping does not drive (the gaze's
    ``eyeLook*``) and the turns of its head and eye nodes, keyed on the bones or objects of those
    names in the selected character (its armature and everything below it). ``n_curves`` counts the
    shape keys and nodes keyed; what it lacks names the targets and nodes of the take it has not.
    """
    folder = bpy.path.abspath(folder)
    meshes = targets_of(context)
    if not meshes:
        raise ValueError("select the character (a mesh with shape keys)")
    loaded = take.read_take(folder)
    names = {b.name for m in meshes for b in m.data.shape_keys.key_blocks[1:]}
    chosen = mapping_for(folder, mapping, loaded, names)
    if not chosen.gains:
        raise ValueError(f"no shape key is named after a key of the take ({', '.join(loaded.names[:6])}, ...); "
                         "give a mapping file")
    scene = context.scene
    anim.set_frame_rate(scene, loaded.fps, loaded.n_frames, scene.frame_start)
    weights = take.target_weights(loaded, chosen)
    performance = _take_animation(folder, loaded)
    extra = {t: w for t, w in performance.weights.items() if t not in weights and t in names}
    missing = anim.key_shape_keys(meshes, {**weights, **extra}, start=scene.frame_start)
    objects = _character(meshes)
    turns, lacking = [], []
    for node_name, rotations in performance.turns.items():
        node = anim.find_node(objects, node_name)
        if node is None:
            lacking.append(node_name)
        else:
            turns.append((node, rotations))
    if turns:
        # Blender's glTF importer gives an object the node's rotation (x, y, z, w) as (w, x, -z, y)
        rests = {n: (q[3], q[0], -q[2], q[1]) for n, q in performance.rests.items()}
        anim.pose_at_rest([node for node, _ in turns], rests)
        anim.turn(turns, start=scene.frame_start)
    return loaded.n_frames, len(weights) + len(extra) - len(missing) + len(turns), missing + lacking


def _take_animation(folder: str, loaded: take.Take) -> gltf.Animation:
    """The take's ``animation.glb`` (``take.json``'s name for it) on the take's frames; empty without one."""
    path = Path(folder) / take.take_files(folder).get("animation", "animation.glb")
    if not path.is_file():
        return gltf.Animation()
    return gltf.read_animation(path, loaded.fps, loaded.n_frames)


def _character(meshes) -> list:
    """Every object of the characters the meshes belong to: their topmost parents and all below them."""
    roots = set()
    for mesh in meshes:
        root = mesh
        while root.parent is not None:
            root = root.parent
        roots.add(root)
    return [o for root in roots for o in (root, *root.children_recursive)]


def preview(context, folder: str, mapping: str) -> list:
    """``(target, keys, found)`` rows for the panel (cached per folder, map and selection)."""
    meshes = targets_of(context)
    names = frozenset(b.name for m in meshes for b in m.data.shape_keys.key_blocks[1:])
    paths = [Path(bpy.path.abspath(folder)) / "weights.csv", Path(bpy.path.abspath(mapping))]
    stamp = (folder, mapping, names, *[p.stat().st_mtime if p.is_file() else 0 for p in paths])
    if _cache.get("stamp") != stamp:
        try:
            loaded = take.read_take(bpy.path.abspath(folder))
            rows = mapping_for(bpy.path.abspath(folder), mapping, loaded, names).rows()
            _cache["rows"] = [(t, keys, t in names) for t, keys in rows] or [("no shape key matches a key", "", False)]
        except (OSError, ValueError, KeyError) as exc:
            _cache["rows"] = [(str(exc), "", False)]
        _cache["stamp"] = stamp
    return _cache["rows"]


class KEYSHAPE_OT_import_take(bpy.types.Operator):
    """Key a keyshape take (weights.csv) on the selected character's shape keys"""

    bl_idname = "keyshape.import_take"
    bl_label = "Import take"
    bl_options = {"REGISTER", "UNDO"}  # noqa: RUF012 - Blender reads a set here

    directory: StringProperty(name="Take", subtype="DIR_PATH", description="Default: the panel's take folder")
    mapping: StringProperty(name="Map", subtype="FILE_PATH", description="Default: the panel's map")

    def execute(self, context):
        settings = context.scene.keyshape
        try:
            n_frames, n_keys, missing = import_take(context, self.directory or settings.folder,
                                                    self.mapping or settings.mapping)
        except (OSError, ValueError, KeyError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if missing:
            self.report({"WARNING"}, f"the selection has no shape keys or bones {missing}")
        self.report({"INFO"}, f"keyshape: {n_keys} shape keys and bones keyed over {n_frames} frames")
        return {"FINISHED"}


# --------------------------------------------------------------------------- video -> take


class KEYSHAPE_OT_run_video(bpy.types.Operator):
    """Run `keyshape run` on the video for the selected character and bring the take in"""

    bl_idname = "keyshape.run_video"
    bl_label = "Run keyshape"
    bl_options = {"REGISTER", "UNDO"}  # noqa: RUF012 - Blender reads a set here

    def execute(self, context):
        settings = context.scene.keyshape
        video = Path(bpy.path.abspath(settings.video))
        if not video.is_file():
            self.report({"ERROR"}, f"{video}: no such video")
            return {"CANCELLED"}
        if not targets_of(context):
            self.report({"ERROR"}, "select the character (a mesh with shape keys)")
            return {"CANCELLED"}
        out = Path(bpy.path.abspath(settings.output)) if settings.output else video.with_name(f"{video.stem}_keyshape")
        try:
            self._run(context, video, out, settings)
            n_frames, n_keys, _ = import_take(context, str(out), settings.mapping)
        except (OSError, ValueError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        settings.folder = str(out)
        self.report({"INFO"}, f"keyshape: {video.name} -> {n_keys} shape keys over {n_frames} frames ({out})")
        return {"FINISHED"}

    @staticmethod
    def _run(context, video: Path, out: Path, settings) -> None:
        work = Path(tempfile.mkdtemp(prefix="keyshape-"))
        try:
            rig = work / "character.glb"
            bpy.ops.export_scene.gltf(filepath=str(rig), export_format="GLB", use_selection=True,
                                      export_morph=True, export_animations=False, export_skins=True)
            command = [_command(), "run", str(video), "--rig", str(rig), "-o", str(out), "-q", "--no-preview"]
            if settings.mapping:
                command += ["--map", bpy.path.abspath(settings.mapping)]
            elif settings.auto_targets:
                command += ["--auto-targets"]
            command += shlex.split(settings.options)
            done = subprocess.run(command, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                raise RuntimeError((done.stderr.strip().splitlines() or ["keyshape run failed"])[-1])
        finally:
            shutil.rmtree(work, ignore_errors=True)


# --------------------------------------------------------------------------- the sculpt kit


def open_sculpt_kit(context, path: str):
    """Import ``sculpt.glb`` (or the kit folder's) and make it ready to sculpt; returns the face mesh."""
    path = Path(bpy.path.abspath(path))
    if path.is_dir():
        path = path / "sculpt.glb"
    if not path.is_file():
        raise ValueError(f"{path}: no sculpt kit here (`keyshape sculpt` writes sculpt.glb)")
    if context.object is not None and context.object.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    before = set(bpy.data.objects)
    bpy.ops.import_scene.gltf(filepath=str(path))
    meshes = anim.shape_key_meshes([o for o in bpy.data.objects if o not in before])
    if not meshes:
        raise ValueError(f"{path}: has no mesh with shape keys")
    face = max(meshes, key=lambda o: len(o.data.vertices))
    for other in context.selected_objects:
        other.select_set(False)
    face.select_set(True)
    context.view_layer.objects.active = face
    face.active_shape_key_index = 1
    face.show_only_shape_key = True  # the active key alone, at full strength: what the artist sculpts
    face.use_shape_key_edit_mode = True
    sheet, readme = path.parent / "keys.png", path.parent / "README.md"
    if sheet.is_file():  # the key frames, for the Image Editor
        bpy.data.images.load(str(sheet), check_existing=True)
    if readme.is_file() and readme.name not in bpy.data.texts:  # what to do, in the Text Editor
        bpy.data.texts.load(str(readme))
    bpy.ops.object.mode_set(mode="SCULPT")
    return face


class KEYSHAPE_OT_open_sculpt_kit(bpy.types.Operator):
    """Open a keyshape sculpt kit ready to sculpt: one shape key per key shape"""

    bl_idname = "keyshape.open_sculpt_kit"
    bl_label = "Open sculpt kit"
    bl_options = {"REGISTER", "UNDO"}  # noqa: RUF012 - Blender reads a set here

    filepath: StringProperty(name="Sculpt kit", subtype="FILE_PATH", description="Default: the panel's kit")

    def execute(self, context):
        try:
            face = open_sculpt_kit(context, self.filepath or context.scene.keyshape.kit)
        except (OSError, ValueError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        keys = face.data.shape_keys.key_blocks
        self.report({"INFO"}, f"keyshape: {len(keys) - 1} shape keys on {face.name}; sculpting {keys[1].name} "
                              "(pick another in Object Data > Shape Keys); keys.png shows the frames")
        return {"FINISHED"}


# --------------------------------------------------------------------------- the panel


class KEYSHAPE_PT_panel(bpy.types.Panel):
    bl_label = "keyshape"
    bl_idname = "KEYSHAPE_PT_panel"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "keyshape"

    def draw(self, context):
        settings = context.scene.keyshape
        box = self.layout.box()
        box.label(text="Take onto shape keys", icon="SHAPEKEY_DATA")
        box.prop(settings, "folder")
        box.prop(settings, "mapping")
        if settings.folder:
            rows = preview(context, settings.folder, settings.mapping)
            column = box.column(align=True)
            for target, keys, found in rows[:_PREVIEW_ROWS]:
                column.label(text=f"{target}  <-  {keys}" if keys else target, icon="CHECKMARK" if found else "ERROR")
            if len(rows) > _PREVIEW_ROWS:
                column.label(text=f"... and {len(rows) - _PREVIEW_ROWS} more")
        box.operator(KEYSHAPE_OT_import_take.bl_idname)
        box = self.layout.box()
        box.label(text="Video to the selected character", icon="FILE_MOVIE")
        box.prop(settings, "video")
        box.prop(settings, "output")
        box.prop(settings, "auto_targets")
        box.prop(settings, "options")
        box.operator(KEYSHAPE_OT_run_video.bl_idname)
        box = self.layout.box()
        box.label(text="Sculpt kit", icon="SCULPTMODE_HLT")
        box.prop(settings, "kit")
        box.operator(KEYSHAPE_OT_open_sculpt_kit.bl_idname)


CLASSES = (KeyshapePreferences, KeyshapeSettings, KEYSHAPE_OT_import_take, KEYSHAPE_OT_run_video,
           KEYSHAPE_OT_open_sculpt_kit, KEYSHAPE_PT_panel)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.keyshape = PointerProperty(type=KeyshapeSettings)


def unregister():
    del bpy.types.Scene.keyshape
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
