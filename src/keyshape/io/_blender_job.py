"""The script keyshape runs in Blender (``bpy``) to write FBX and ``.blend`` files.

Run as ``python _blender_job.py JOB.json`` with a Python that has ``bpy`` (or as
``blender --background --python _blender_job.py -- JOB.json``); never imported by keyshape
itself but for its docstring: ``bpy`` is imported only inside :func:`main`, in that process.
:mod:`keyshape.io.blender` writes the job: the scene as a glTF file, the per-frame arrays as
``.npz`` and a JSON description:

``{"scene": "scene.glb", "arrays": "job.npz", "output": "anim.fbx", "format": "fbx",
"fps": 30.0, "start": 1, "names": [...], "head": "Head", "eyes": ["EyeL", "EyeR"] or null}``

with ``weights (n_frames, n_targets)``, ``head (n_frames, 3, 3)`` and ``eyes (n_frames, 2, 3, 3)``
(glTF world axes) in the arrays. The animation itself is keyed by the add-on's ``anim`` module
(``blender_addon/anim.py`` beside this file), the one place keyshape keys Blender curves.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

FBX_OPTIONS = {  # Blender's FBX exporter: every frame baked, nothing simplified away
    "use_selection": False, "object_types": {"ARMATURE", "MESH", "EMPTY", "OTHER"}, "add_leaf_bones": False,
    "bake_anim": True, "bake_anim_use_all_bones": True, "bake_anim_use_nla_strips": False,
    "bake_anim_use_all_actions": False, "bake_anim_force_startend_keying": True, "bake_anim_step": 1.0,
    "bake_anim_simplify_factor": 0.0, "axis_forward": "-Z", "axis_up": "Y", "apply_unit_scale": True,
    "apply_scale_options": "FBX_SCALE_NONE", "use_mesh_modifiers": False, "mesh_smooth_type": "FACE",
    "path_mode": "COPY", "embed_textures": True,
}


def main(argv: list[str]) -> int:
    import bpy
    import numpy as np

    job_path = Path(argv[-1])
    job = json.loads(job_path.read_text(encoding="utf-8"))
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from blender_addon import anim

    arrays = np.load(job_path.parent / job["arrays"])
    weights = arrays["weights"]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    anim.set_frame_rate(scene, job["fps"], len(weights), job["start"])
    bpy.ops.import_scene.gltf(filepath=str(job_path.parent / job["scene"]))
    objects = list(scene.objects)
    anim.silence(objects)
    missing = anim.key_shape_keys(anim.shape_key_meshes(objects), dict(zip(job["names"], weights.T)),
                                  start=job["start"])
    if missing:
        raise SystemExit(f"keyshape: no mesh in the scene has the shape keys {missing}")
    turns = [(job["head"], arrays.get("head"))]
    for side, eye in enumerate(job.get("eyes") or ()):
        turns.append((eye, arrays["eyes"][:, side]))
    nodes = []
    for node_name, rotations in turns:
        if node_name and rotations is not None:
            node = anim.find_node(objects, node_name)
            if node is None:
                raise SystemExit(f"keyshape: Blender imported no object or bone named {node_name!r}")
            nodes.append((node, rotations))
    anim.turn(nodes, start=job["start"])
    scene.frame_set(job["start"])
    _write(bpy, job["format"], job["output"])
    return 0


def _write(bpy, format: str, output: str) -> None:
    if format == "fbx":
        bpy.ops.export_scene.fbx(filepath=output, **FBX_OPTIONS)
        return
    bpy.context.preferences.filepaths.save_version = 0  # no .blend1 backup beside the output
    if bpy.data.images:
        bpy.ops.file.pack_all()
    bpy.ops.wm.save_as_mainfile(filepath=output, check_existing=False, compress=True)


if __name__ == "__main__":
    sys.exit(main(sys.argv))
