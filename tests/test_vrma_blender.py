"""A `.vrma` keyshape writes, imported by the VRM add-on for Blender (`bpy-vrm-format`, on PyPI's `bpy`)
onto the avatar it was made for (issue 37): every expression of the file is animated on the avatar,
its curve the weights written (at Blender's frame rate, between the file's keys), and the head bone
turns. Blender runs in its own process, as keyshape's own Blender jobs do.

The add-on (4.10) imports a VRM Animation onto VRM 1.0 avatars only ("Please set the version of VRM
to 1.0" for a 0.x armature), so the avatars here are the 1.0 ones, standard and perfect sync."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_vrma import read_vrma
from vrm_avatars import make_vrm

from keyshape.containers import Poses, Weights
from keyshape.exceptions import InputWarning
from keyshape.io import export, load_vrm

JOB = r"""
import json, os, sys
import bpy

avatar, take = sys.argv[1:3]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.preferences.addon_enable(module="io_scene_vrm")
assert bpy.ops.import_scene.vrm(filepath=avatar) == {"FINISHED"}
(armature,) = [o for o in bpy.data.objects if o.type == "ARMATURE"]
bpy.context.view_layer.objects.active = armature
assert bpy.ops.import_scene.vrma(filepath=take, armature_object_name=armature.name) == {"FINISHED"}
scene = bpy.context.scene
expressions = armature.data.vrm_addon_extension.vrm1.expressions
curves = {fc.data_path: fc for action in bpy.data.actions for fc in action.fcurves}
out = {"fps": scene.render.fps / scene.render.fps_base, "frame_start": scene.frame_start,
       "frame_end": scene.frame_end, "expressions": {}, "head": []}
for name, expression in expressions.all_name_to_expression_dict().items():
    curve = curves.get(expression.path_from_id("preview"))
    if curve is not None:
        frames = [k.co[0] for k in curve.keyframe_points]
        out["expressions"][name] = [[f, curve.evaluate(f)] for f in frames]
head = armature.pose.bones.get(armature.data.vrm_addon_extension.vrm1.humanoid.human_bones.head.node.bone_name)
for frame in range(scene.frame_start, scene.frame_end + 1):
    scene.frame_set(frame)
    out["head"].append(list(head.rotation_quaternion))
print("RESULT " + json.dumps(out), flush=True)
os._exit(0)  # bpy's own teardown at exit can crash after the work is done
"""


def _needs_addon():
    if importlib.util.find_spec("bpy") is None or importlib.util.find_spec("io_scene_vrm") is None:
        pytest.fail('needs bpy and the VRM add-on: pip install "keyshape[vrm-tests]" (setup.sh installs it)',
                    pytrace=False)


def _blender(avatar, take) -> dict:
    run = subprocess.run([sys.executable, "-X", "faulthandler", "-c", JOB, str(avatar), str(take)],
                         capture_output=True, text=True, timeout=600, check=False)
    lines = [line for line in run.stdout.splitlines() if line.startswith("RESULT ")]
    assert run.returncode == 0 and lines, (run.stdout[-2000:], run.stderr[-3000:])
    return json.loads(lines[-1].removeprefix("RESULT "))


@pytest.mark.slow
@pytest.mark.parametrize("sync", [False, True], ids=["standard", "perfect-sync"])
def test_blender_imports_the_take_animated(tmp_path, sync):
    _needs_addon()
    avatar = make_vrm(tmp_path / "avatar.vrm", "1.0", perfect_sync=sync, skeleton=True)
    vrm = load_vrm(avatar.path)
    n, fps = 30, 30.0
    t = np.arange(n) / fps
    # each expression its own phase: no two curves alike
    values = 0.5 + 0.5 * np.sin(2 * np.pi * t[:, None] + np.arange(vrm.rig.n_targets))
    yaw = np.radians(20) * np.sin(2 * np.pi * t)
    poses = Poses(Rotation.from_rotvec(np.outer(yaw, [0, 1, 0])).as_matrix(), np.zeros((n, 3)), np.ones(n))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # the look and mouthSmileLeft are left out
        take = export(Weights(values, vrm.rig.names, fps), tmp_path / "take.vrma", source=avatar.path, poses=poses)
    extension, tracks, _ = read_vrma(take)
    written = {}
    for group in ("preset", "custom"):
        for key, entry in extension["expressions"].get(group, {}).items():
            times, moved = tracks[entry["node"], "translation"]
            written[key] = (times, moved[:, 0])

    got = _blender(avatar.path, take)
    assert set(got["expressions"]) == set(written)  # every expression of the file is animated
    for name, keys in got["expressions"].items():
        frames, curve = np.array(keys).T
        times, weights = written[name]
        expected = np.interp((frames - got["frame_start"]) / got["fps"], times, weights)
        np.testing.assert_allclose(curve, expected, atol=2e-3, err_msg=name)
        assert np.ptp(curve) > 0.5, name  # animated, not a constant
    head = np.array(got["head"])
    assert np.ptp(head, axis=0).max() > 0.05  # the head bone turns with the poses
