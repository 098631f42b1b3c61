"""Stage 6, files: readers and writers for the files artists and engines open, one module per format.

* :mod:`~keyshape.io.track` (``.npz`` tracks), :mod:`~keyshape.io.keys_json`,
  :mod:`~keyshape.io.weights_csv`, :mod:`~keyshape.io.take` (``take.json`` of a run folder);
* :mod:`~keyshape.io.rig` — characters: OBJ folders, glTF, VRM and USD rigs (:func:`load_rig`, :func:`load_vrm`);
* :mod:`~keyshape.io.gltf` (with private ``_gltf_read``, ``_gltf_nodes``, ``_gltf_edit``,
  ``_gltf_anim``), :mod:`~keyshape.io.usd` (``_usd_read``; ``pxr`` imported only in ``_pxr``),
  :mod:`~keyshape.io.livelink` (Live Link Face CSV);
* :func:`export` — an animation written in the format its suffix names;
* :mod:`~keyshape.io.atomic` — every file is written atomically (no half-written output survives).
"""

from ._export import Format, export, format_of
from .atomic import atomic_path
from .keys_json import load_keys, save_keys
from .rig import RIG_SUFFIXES, load_rig, load_vrm, parse_unit, read_obj, save_obj_folder
from .take import load_take_info, save_take_info
from .track import TrackFile, load_track, open_track, save_track
from .weights_csv import load_weights_csv, save_weights_csv

__all__ = ["load_track", "save_track", "open_track", "TrackFile", "load_keys", "save_keys", "load_weights_csv",
           "save_weights_csv",
           "load_take_info", "save_take_info", "load_rig", "load_vrm", "parse_unit", "read_obj", "save_obj_folder",
           "RIG_SUFFIXES", "export", "Format", "format_of", "atomic_path"]
