"""A keyshape take folder read without keyshape: ``weights.csv``, ``take.json`` and a mapping file.

Pure Python (no ``bpy``, no numpy), so Blender's own interpreter reads a take without keyshape
installed. The formats are keyshape's (``keyshape.io.weights_csv``, ``keyshape.io.take``,
``keyshape.targets`` mapping files); a mapping gives target weights as ``c + M · w_key`` per
frame, clipped below at 0 when there is an offset, as ``keyshape retarget`` does.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

MAP_FORMAT = "keyshape-map"


@dataclass(frozen=True)
class Take:
    """Key weights of a take: ``values[frame][key]`` (NaN where there was no face)."""

    names: tuple
    values: tuple
    fps: float

    @property
    def n_frames(self) -> int:
        return len(self.values)


@dataclass(frozen=True)
class TargetMap:
    """``gains[target] = {key: gain}`` and ``offset[target]``: how keys drive the shape keys."""

    gains: dict
    offset: dict

    def rows(self) -> list:
        """``(target, "key×gain + ...")`` rows for the mapping preview."""
        rows = []
        for target, keys in self.gains.items():
            terms = " + ".join(key if gain == 1 else f"{key}×{gain:g}" for key, gain in keys.items())
            rows.append((target, f"{self.offset[target]:g} + {terms}" if self.offset.get(target) else terms))
        return rows


def read_weights(path) -> Take:
    """``weights.csv`` (header ``frame,time,<name>,...``; an empty cell is NaN)."""
    path = Path(path)
    with open(path, newline="", encoding="utf-8") as fh:
        rows = [r for r in csv.reader(fh) if r]
    if not rows or rows[0][:2] != ["frame", "time"] or len(rows[0]) < 3:
        raise ValueError(f"{path}: expected a header 'frame,time,<name>,...'")
    values = tuple(tuple(float(c) if c else math.nan for c in r[2:]) for r in rows[1:])
    times = [float(r[1]) for r in rows[1:]]
    fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 and times[-1] > times[0] else 30.0
    return Take(tuple(rows[0][2:]), values, fps)


def _info(folder: Path) -> dict:
    if (folder / "take.json").is_file():
        return json.loads((folder / "take.json").read_text(encoding="utf-8"))
    return {}


def take_files(folder) -> dict:
    """``{"weights": name, "animation": name, ...}``: the take's files as ``take.json`` names them (else ``{}``)."""
    return dict(_info(Path(folder)).get("files") or {})


def read_take(folder) -> Take:
    """The key weights of a take folder, at the take's frame rate (``take.json`` when there is one)."""
    folder = Path(folder)
    info = _info(folder)
    name = info.get("files", {}).get("weights", "weights.csv")
    if not (folder / name).is_file():
        raise ValueError(f"{folder}: no {name} here; choose the output folder of `keyshape run`")
    take = read_weights(folder / name)
    return Take(take.names, take.values, float(info.get("fps") or take.fps))


def read_map(path) -> TargetMap:
    """A mapping file: ``{key: {target: gain}}``, the wrapped ``keyshape-map`` form or the matrix form."""
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    offset = {}
    if isinstance(data, dict) and "matrix" in data:
        data = {key: {t: row[k] for t, row in zip(data["targets"], data["matrix"]) if row[k]}
                for k, key in enumerate(data["keys"])}
    elif isinstance(data, dict) and data.get("format") == MAP_FORMAT:
        offset = {t: float(v) for t, v in (data.get("offset") or {}).items()}
        data = data["gains"]
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise ValueError(f"{path}: not a keyshape mapping ({{key: {{target: gain}}}})")
    gains = {}
    for key, targets in data.items():
        for target, gain in targets.items():
            gains.setdefault(target, {})[key] = float(gain)
    for target in offset:
        gains.setdefault(target, {})
    return TargetMap(gains, {t: offset.get(t, 0.0) for t in gains})


def by_name(take: Take, targets) -> TargetMap:
    """Each shape key driven by the key of its name (the sculpt kit's targets)."""
    return TargetMap({t: {t: 1.0} for t in targets if t in take.names}, {})


def target_weights(take: Take, mapping: TargetMap) -> dict:
    """``{target: [weight per frame]}``: ``c + Σ gain · w_key`` (NaN counts as 0)."""
    missing = sorted({k for keys in mapping.gains.values() for k in keys} - set(take.names))
    if missing:
        raise ValueError(f"the mapping needs keys the take does not have: {missing}")
    column = {name: i for i, name in enumerate(take.names)}
    out = {}
    for target, keys in mapping.gains.items():
        c = mapping.offset.get(target, 0.0)
        series = [c + sum(g * _zero(row[column[k]]) for k, g in keys.items()) for row in take.values]
        out[target] = [max(v, 0.0) for v in series] if c else series
    return out


def _zero(value: float) -> float:
    return 0.0 if math.isnan(value) else value
