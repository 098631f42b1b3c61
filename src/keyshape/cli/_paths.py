"""The one check of a verb's output paths, made before any work starts.

Every verb's arguments are read the same way: the ``-o``/``--output`` values (and
``--save-correspondence``, ``live --record``) are outputs, every other path argument is an input.
Before the verb runs, :func:`check_outputs` refuses

* an output that is one of the inputs, or a file a folder output would write over an input
  (``track a.mp4 -o a.mp4``, ``retarget w.csv --rig rig.glb -o rig.glb``): a usage error;
* a file output that names an existing folder (``-o out/`` for a .npz), or a folder output an
  existing file (``run -o notes.txt``, ``live --record take.mp4``): a usage error;
* a folder output that is an input folder (``run IMAGES/ -o IMAGES/``, also through a link or
  ``IMAGES/.``): a usage error, else its files join the input's;
* an output whose folder cannot be written (read-only, or a file where a folder should be): a
  data error, found now rather than after minutes of tracking.

The input files of a take folder (``report OUTDIR``, ``preview OUTDIR``, ``view OUTDIR``) are its
``take.json``, the files it lists and its video.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from ..exceptions import InputError, UsageError

__all__ = ["check_outputs", "FOLDER_OUTPUTS"]

# verb -> the files its folder output (-o) is written with; verbs not named here write a file
_RUN_FILES = ("track.npz", "keys.json", "weights.csv", "animation.glb", "take.json", "preview.mp4",
              "keyshapes.png", "weights.png", "error_vs_k.png", "report.html", "correspondence.json",
              "map.json", "animation.vrma")
FOLDER_OUTPUTS = {
    "run": _RUN_FILES,
    "demo": _RUN_FILES,
    "batch": ("summary.csv", "keys.json"),
    "sculpt": ("sculpt.glb", "keys.png", "README.md"),
    "report-k": ("error_vs_k.csv", "error_vs_k.json", "error_vs_k.png"),
    "coverage": ("coverage.png", "coverage.json"),
}
_EITHER = {"propose"}  # -o is a file (.json, .glb) or a folder (an OBJ rig)
# outputs other than -o that are folders, whatever the verb: argument -> the files written in it
_FOLDER_DESTS = {"record": ("track.npz", "keys.json", "weights.csv", "animation.glb", "take.json")}
_OUTPUT_DESTS = ("output", "save_correspondence", *_FOLDER_DESTS)
_TAKE_FOLDER_VERBS = {"report", "preview", "view"}


def check_outputs(verb: str, args) -> None:
    """Refuse outputs that would destroy an input or cannot be written (see the module)."""
    inputs = list(_inputs(verb, args))
    for flag, out, dest in _outputs(args):
        names = _FOLDER_DESTS.get(dest, FOLDER_OUTPUTS.get(verb) if dest == "output" else None)
        folder_output = names is not None or (verb in _EITHER and (out.is_dir() or not out.suffix))
        if not folder_output and out.is_dir():
            raise UsageError(f"{flag} {out}: is an existing folder; give a file name")
        if folder_output and out.exists() and not out.is_dir():
            raise UsageError(f"{flag} {out}: is an existing file; give a folder")
        if folder_output:
            for name, source in _input_folders(verb, args):
                if _same(out, source):
                    raise UsageError(f"{flag} {out}: is the input folder {name} {source}; its files would be "
                                     "written among the input's; choose another output")
        written = [out / name for name in names or ()] if folder_output else [out]
        for target in written:
            for name, source in inputs:
                if _same(target, source):
                    raise UsageError(f"{flag} {out}: would overwrite the input {name} {source}; "
                                     "choose another output")
        _check_writable(flag, out)


def _outputs(args) -> Iterator[tuple[str, Path, str]]:
    """(flag, path, argument) of every output the arguments name."""
    for dest in _OUTPUT_DESTS:
        value = getattr(args, dest, None)
        flag = "-o" if dest == "output" else "--" + dest.replace("_", "-")
        for out in value if isinstance(value, list) else [value]:
            if isinstance(out, Path):
                yield flag, out, dest


def _inputs(verb: str, args) -> Iterator[tuple[str, Path]]:
    """(argument name, path) of every input file the arguments name."""
    for dest, value in vars(args).items():
        if dest in _OUTPUT_DESTS:
            continue
        for path in value if isinstance(value, list) else [value]:
            if not isinstance(path, Path):
                continue
            name = _argument_name(dest)
            if path.is_dir() and verb in _TAKE_FOLDER_VERBS:
                yield from ((name, p) for p in _take_files(path))
            elif path.is_file():
                yield name, path


def _input_folders(verb: str, args) -> Iterator[tuple[str, Path]]:
    """(argument name, path) of every input that is a folder (an image sequence, a folder of takes, an
    OBJ rig): a folder output must not be one of them, or its files join the input's (a run's
    pictures among the frames of the next run's image sequence)."""
    for dest, value in vars(args).items():
        if dest in _OUTPUT_DESTS:
            continue
        for path in value if isinstance(value, list) else [value]:
            if isinstance(path, Path) and path.is_dir():
                yield _argument_name(dest), path


def _argument_name(dest: str) -> str:
    return dest.upper() if dest in ("video", "track", "keys", "weights", "tracks", "takes") \
        else "--" + dest.replace("_", "-")


def _take_files(folder: Path) -> list[Path]:
    """take.json, the files it lists and its video (what a take folder's reader reads)."""
    info_path = folder / "take.json"
    try:
        info = json.loads(info_path.read_text())
    except (OSError, ValueError):
        return []
    files = info.get("files") if isinstance(info, dict) else None
    listed = [folder / str(n) for n in files.values()] if isinstance(files, dict) else []
    video = [Path(info["video"])] if isinstance(info.get("video"), str) else []
    return [info_path, *(p for p in listed + video if p.is_file())]


def _same(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
        return a.resolve() == b.resolve()
    except OSError:
        return False


def _check_writable(flag: str, out: Path) -> None:
    """The nearest existing folder of ``out`` must be a folder we can create files in."""
    existing = out if out.is_dir() else out.parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise UsageError(f"{flag} {out}: {existing} is a file, not a folder")
    try:  # a real probe: os.access says yes to root on a read-only file system
        fd, probe = tempfile.mkstemp(prefix=".keyshape-probe-", dir=existing)
    except OSError as exc:
        raise InputError(f"{flag} {out}: cannot write into {existing} ({exc.strerror or exc})") from None
    os.close(fd)
    os.unlink(probe)
