"""``take.json``: what ``keyshape run`` wrote for one take, for the report and the viewer.

``{"format": "keyshape-take", "version": 1, "video": "/abs/path/take.mp4", "fps": 23.976,
"n_frames": 472, "image_size": [640, 360], "neutral_frame": 12, "files": {"track": "track.npz",
"keys": "keys.json", "weights": "weights.csv", "animation": "animation.glb"}}``, and
``"neutral_source": "/abs/path/rest.png"`` when the neutral comes from a file (``--neutral FILE``),
and ``"written": ["animation.glb", ..., "take.json"]``, every file the run put in its folder: the
one record of what keyshape wrote there, so a later run in the same folder removes what it does
not write again and nothing else (:func:`written_by`).
"""

from __future__ import annotations

import json
from pathlib import Path

from ..containers import KeyShapes, Track
from ..exceptions import InputError, InputWarning
from .atomic import atomic_path, check_switched
from .validate import check_take_info

__all__ = ["save_take_info", "load_take_info", "take_video", "record_written", "written_by", "TAKE_FILES"]

TAKE_FILES = {"track": "track.npz", "keys": "keys.json", "weights": "weights.csv",
              "animation": "animation.glb"}


def save_take_info(path: str | Path, *, video: Path, track: Track, keys: KeyShapes,
                   files: dict[str, str] | None = None, neutral: Path | None = None) -> Path:
    """Write the take description beside the outputs, atomically.

    ``neutral``: the still image or clip of the actor at rest the keys' neutral comes from
    (``--neutral FILE``), kept as ``"neutral_source"`` so the contact sheets can show it.
    """
    info = {"format": "keyshape-take", "version": 1, "video": str(Path(video).resolve()),
            "fps": track.fps, "n_frames": track.n_frames,
            "image_size": list(track.image_size) if track.image_size else None,
            "neutral_frame": int(keys.neutral_frame), "files": files or dict(TAKE_FILES)}
    if neutral is not None:
        info["neutral_source"] = str(Path(neutral).resolve())
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(info, indent=1) + "\n")
    return Path(path)


def load_take_info(folder: str | Path) -> dict:
    """Read ``take.json`` from an output folder of ``keyshape run``."""
    path = Path(folder) / "take.json"
    check_switched(folder)  # a run's switch cut short: a mix of two takes, take.json or not
    if not path.is_file():
        raise InputError(f"{folder}: no take.json here; is it an output folder of `keyshape run`?")
    try:
        info = json.loads(path.read_text(encoding="utf-8-sig"))  # a BOM is no JSON error
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc.__class__.__name__}: {exc})") from None
    check_take_info(path, info)
    return info


def record_written(path: str | Path, names) -> None:
    """Add ``"written"``, the sorted file names ``names`` (``take.json`` among them), to the take
    description at ``path``, atomically: the record :func:`written_by` reads back."""
    path = Path(path)
    info = json.loads(path.read_text())
    info["written"] = sorted({*map(str, names), path.name})
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(info, indent=1) + "\n")


def written_by(folder: str | Path) -> frozenset[str]:
    """The names of the files an earlier run wrote in ``folder``, as its ``take.json`` records them
    (``"written"``; for a description from before that record, the files it names); empty when
    there is no readable description. Only plain names count: nothing outside ``folder``.

    Examples
    --------
    >>> written_by("no/such/folder")
    frozenset()
    """
    try:
        info = json.loads((Path(folder) / "take.json").read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return frozenset()
    if not isinstance(info, dict) or info.get("format") != "keyshape-take":
        return frozenset()
    files = info.get("files")
    names = info.get("written", list(files.values()) if isinstance(files, dict) else [])
    if not isinstance(names, list):
        return frozenset()
    return frozenset(n for n in names if isinstance(n, str) and n and n == Path(n).name and n not in (".", ".."))


def take_video(folder: str | Path, info: dict) -> Path | None:
    """The take's source video, or None, with an :class:`~keyshape.exceptions.InputWarning`
    when ``take.json`` names a video that is gone (the pictures then lack the actor)."""
    import warnings

    if not info.get("video"):
        return None
    video = Path(info["video"])
    if video.is_file():
        return video
    warnings.warn(f"{Path(folder) / 'take.json'}: its video {str(video)!r} is not found: the landmarks are "
                  "drawn without the actor", InputWarning, stacklevel=2)
    return None
