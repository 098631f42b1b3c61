"""FBX and ``.blend`` out, through Blender's own exporters; the Blender add-on.

keyshape does not link Blender (``bpy`` is GPL-3 and large, an optional extra:
``pip install "keyshape[blender]"``). :func:`write_blender` writes the character as glTF with
keyshape's glTF writers, hands it and the per-frame arrays to a Blender process
(:mod:`keyshape.io._blender_job`, run by :func:`blender_command`), which imports the glTF, keys
the animation and saves with Blender's own FBX exporter or as a ``.blend``:

* shape keys named by the targets keyed once per frame (LINEAR), at the take's frame rate
  (``scene.render.fps / fps_base``): in a ``.blend`` the take's frame 0 is Blender frame 1 (its
  first frame); in FBX frame ``i`` is at ``i / fps`` seconds, as in keyshape's glTF and USD (Blender's
  FBX importer shows it at frame ``i + 1``), and the weights are blend-shape channels running
  0–100 (``DeformPercent``);
* the head rotation on the head bone or object (the one :func:`keyshape.io.gltf.animate_gltf`
  turns), the eye rotations on the eye bones or objects where the character has them;
* units and axes as each format's importers expect: Blender's scene in metres, +Z up (what its
  glTF importer makes of glTF's +Y up); FBX through Blender's exporter with
  ``axis_up="Y"``, ``axis_forward="-Z"`` and the unit scale applied (``UnitScaleFactor`` 1: one
  unit is 1 cm, the geometry scaled by 100, as Maya, Unity and Unreal expect; Blender reads it back
  in metres).

The add-on (``blender_addon/``, a package-data folder) is written as an installable zip by
:func:`write_addon`; its ``anim`` module is also what the job keys curves with.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
import warnings
import zipfile
from pathlib import Path

import numpy as np

from ..containers import Poses, Rig, Weights
from ..exceptions import InputError, KeyshapeError, MissingDependencyError
from .atomic import atomic_path

__all__ = ["BLENDER_SUFFIXES", "write_blender", "blender_command", "check_blender", "write_addon", "ADDON_NAME"]

BLENDER_SUFFIXES = {".fbx": "fbx", ".blend": "blend"}
ADDON_NAME = "keyshape_blender"  # the add-on's module name inside Blender
_HERE = Path(__file__).resolve().parent
_ADDON = _HERE / "blender_addon"
_JOB = _HERE / "_blender_job.py"
_START = {"fbx": 0, "blend": 1}  # Blender frame of the take's frame 0: FBX time 0; a .blend's first frame
_TIMEOUT = 3600  # s: a Blender job that runs an hour is stuck


def blender_command(script: str | Path) -> list[str]:
    """The command that runs ``script`` with Blender's ``bpy`` (its arguments follow).

    In order: ``$KEYSHAPE_BPY_PYTHON`` (a Python with ``bpy``, or a ``blender`` binary), this
    Python when ``bpy`` is installed in it, ``blender`` on the PATH.

    Raises
    ------
    MissingDependencyError
        None of them: the message says ``pip install "keyshape[blender]"``.
    """
    chosen = os.environ.get("KEYSHAPE_BPY_PYTHON")
    if not chosen and importlib.util.find_spec("bpy") is not None:
        chosen = sys.executable
    chosen = chosen or shutil.which("blender")
    if not chosen:
        raise MissingDependencyError("bpy (Blender as a Python module, for FBX and .blend)", extra="blender")
    if Path(chosen).name.lower().startswith("blender"):
        return [chosen, "--background", "--factory-startup", "--python-exit-code", "1", "--python", str(script), "--"]
    return [chosen, str(script)]


def check_blender() -> None:
    """Raise :class:`MissingDependencyError` now if there is no Blender to run (before a long run)."""
    blender_command(_JOB)


def write_blender(path, animation: Weights, *, rig: Rig | None = None, source=None,
                  poses: Poses | None = None, head: str | None = None, eyes=None) -> Path:
    """Write ``animation`` as FBX (``.fbx``) or a Blender file (``.blend``), atomically.

    Parameters
    ----------
    path : str or Path
        Ends in ``.fbx`` or ``.blend``; never one of the inputs.
    animation : Weights
        Target weights ``(n_frames, n_targets)`` named by the character's targets (for ``rig``
        without ``source``: exactly ``rig.names`` in order). NaN is written as 0.
    rig : Rig, optional, keyword-only
        The character, when there is no glTF ``source`` to keep.
    source : str or Path, optional, keyword-only
        The character's ``.glb``/``.gltf``: kept whole (materials, skinning, other meshes), but for
        its own animation clips: the output carries the take alone.
    poses : Poses, optional, keyword-only
        Head poses (image convention): the head's rotation.
    head : str, optional, keyword-only
        The node of ``source`` to turn (default: found by name, as :func:`~keyshape.io.gltf.animate_gltf`).
    eyes : (n_frames, 2, 3, 3) float, optional, keyword-only
        Eye rotations relative to the head (left first), on ``source``'s eye nodes where it has them.

    Returns
    -------
    Path

    Raises
    ------
    MissingDependencyError
        No Blender to run (see :func:`blender_command`).
    InputError, RigError
        Bad suffix, ``path`` is the source, names the character lacks, frame counts that differ.
    """
    from ._gltf_anim import check_eyes, check_poses

    path = Path(path)
    chosen = BLENDER_SUFFIXES.get(path.suffix.lower())
    if chosen is None:
        raise InputError(f"{path}: FBX and Blender files end in .fbx or .blend")
    if source is not None and path.resolve() == Path(source).resolve():
        raise InputError(f"{path}: is the character's own file; write the animation to another file")
    check_poses(poses, animation)
    check_eyes(eyes, animation)
    command = blender_command(_JOB)
    with tempfile.TemporaryDirectory(prefix="keyshape-blender-") as folder:
        work = Path(folder)
        head_name, eye_names = _scene(work / "scene.glb", animation, rig, source, head, eyes is not None)
        if poses is not None and head_name is None:
            warnings.warn(f"{str(source)!r}: no head node found (no joint or node named like 'head' above the "
                          "face meshes): the head rotation is not written; name the node to turn", UserWarning,
                          stacklevel=2)
        arrays = _arrays(animation, poses if head_name else None, eyes if eye_names else None)
        np.savez(work / "job.npz", **arrays)
        with atomic_path(path) as tmp:
            job = {"scene": "scene.glb", "arrays": "job.npz", "output": str(tmp), "format": chosen,
                   "fps": float(animation.fps), "start": _START[chosen], "names": list(animation.names),
                   "head": head_name if "head" in arrays else None, "eyes": eye_names if "eyes" in arrays else None}
            (work / "job.json").write_text(json.dumps(job, indent=1), encoding="utf-8")
            _run(command + [str(work / "job.json")], path)
    return path


def _scene(path: Path, animation: Weights, rig, source, head, with_eyes) -> tuple[str | None, list | None]:
    """Write the character without animation to ``path`` (glTF); its head node and eye node names."""
    from ._gltf_edit import morph_nodes
    from ._gltf_nodes import find_eyes, find_head
    from ._gltf_read import load_document, morph_meshes
    from .gltf import animate_gltf, write_glb

    still = Weights(np.zeros((0, animation.n_channels)), animation.names, animation.fps)
    if source is None or Path(source).suffix.lower() not in (".glb", ".gltf"):
        if rig is None:
            raise InputError("writing FBX or .blend needs the rig (or its glTF file)")
        write_glb(path, rig, still)
        return "face", None  # write_glb's one node, turned with the head
    animate_gltf(source, still, path)  # checks the names, packs the buffers
    _drop_clips(path)
    document, _ = load_document(path, editable=False)
    index = find_head(document, morph_nodes(document, morph_meshes(document, path)), name=head)
    eyes = find_eyes(document, index) if with_eyes and index is not None else None
    return (None if index is None else document.nodes[index].name,
            None if eyes is None else [document.nodes[e].name for e in eyes])


def _drop_clips(path: Path) -> None:
    """Remove the file's own animations: Blender then imports the character in its rest pose (the
    nodes' rest transforms, which keyshape's head turns are relative to) with nothing else playing."""
    from . import _gltf_edit as edit
    from ._gltf_read import load_document
    from .gltf import _save

    document, buffers = load_document(path)
    if document.animations:
        blob = edit.pack(document, buffers, path)
        document.animations = []
        blob.finish()
        edit.prune(document)
        _save(path, document)


def _arrays(animation: Weights, poses, eyes) -> dict:
    from ..schemes import head_rotations, hold_valid, rotations_to_gltf

    arrays = {"weights": np.nan_to_num(animation.values, nan=0.0)}
    if poses is not None:
        arrays["head"] = head_rotations(poses, hold=True)
    if eyes is not None:
        eyes = np.asarray(eyes, dtype=float)
        arrays["eyes"] = np.stack([rotations_to_gltf(hold_valid(eyes[:, s])) for s in (0, 1)], axis=1)
    return arrays


def _run(command: list[str], path: Path) -> None:
    env = dict(os.environ, PYTHONNOUSERSITE="1")
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=_TIMEOUT, env=env, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise KeyshapeError(f"{path}: Blender did not run ({exc})") from None
    if done.returncode != 0:
        lines = [ln for ln in (done.stderr + done.stdout).splitlines() if ln.strip()]
        said = next((ln for ln in reversed(lines) if ln.startswith("keyshape:")), lines[-1] if lines else "")
        raise KeyshapeError(f"{path}: Blender failed (exit code {done.returncode}): {said.strip()}")


# --------------------------------------------------------------------------- the add-on


def write_addon(folder) -> Path:
    """Write the add-on as an installable zip into ``folder``; returns the zip's path.

    Blender: *Edit > Preferences > Add-ons > Install from Disk* (4.2 and later install it as an
    extension; it carries ``blender_manifest.toml`` and ``bl_info`` both).
    """
    from .. import __version__

    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{folder}: exists and is not a folder")
    path = folder / f"{ADDON_NAME}-{__version__}.zip"
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as archive:
        for file in sorted(_ADDON.rglob("*")):
            if file.is_file() and "__pycache__" not in file.parts and file.suffix in (".py", ".toml", ".md", ".txt"):
                archive.write(file, f"{ADDON_NAME}/{file.relative_to(_ADDON).as_posix()}")
    return path
