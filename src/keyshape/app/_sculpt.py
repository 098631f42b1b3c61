"""The sculpt kit: everything an artist needs to sculpt one target per key shape.

The paper's artist sculpts, for every key shape, the character's version of that expression
("a smile for a smile"). :func:`write_sculpt_kit` writes into a folder

* ``sculpt.glb``: the character with one morph target per key shape, named after it, each
  starting as the neutral (or as a proposal from ``propose``). For a glTF character the
  artist's own file is kept whole (materials, skinning, other meshes); the key targets
  replace any targets the chosen meshes had.
* ``keys.png``: the contact sheet: per region a row with the neutral frame and each key's
  frame, cropped to the face, landmarks drawn and the region's landmarks highlighted.
* ``README.md``: what to do, with the table of keys (name, region, frame, time).

The artist sculpts the targets (e.g. Blender's shape keys), exports a ``.glb``, and
``keyshape retarget WEIGHTS.csv --rig THAT.glb`` drives it as it is: targets match keys by name.

Hook for automatic targets: ``propose(keys, neutral) -> (n_keys, n_vertices, 3)`` deltas,
given the key shapes and the character's neutral (:class:`~keyshape.containers.Rig`, no
targets; glTF vertices in world space, as :func:`keyshape.io.load_rig` reads them); its result
becomes the starting targets (written back in each mesh's own space).
"""

from __future__ import annotations

import textwrap
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..containers import KeyShapes, Rig, Track, Weights
from ..exceptions import InputError, RigError
from ..io.atomic import atomic_path, staged_folder

__all__ = ["SculptKit", "sculpt_targets", "write_sculpt_kit", "check_kit_folder", "contact_sheet", "Proposer"]

Proposer = Callable[[KeyShapes, Rig], np.ndarray]
GLB, SHEET, README = "sculpt.glb", "keys.png", "README.md"
_REGION_COLOURS = [(230, 80, 60), (40, 150, 240), (80, 190, 90), (240, 180, 30), (170, 90, 220), (30, 200, 200)]


@dataclass(frozen=True)
class SculptKit:
    """The files of a written sculpt kit."""

    folder: Path
    glb: Path
    sheet: Path
    readme: Path


def sculpt_targets(keys: KeyShapes, neutral: Rig, *, propose: Proposer | None = None) -> Rig:
    """The character with one target per key shape, named after it.

    Parameters
    ----------
    keys : KeyShapes
    neutral : Rig
        The character; its own targets, if any, are dropped.
    propose : callable, optional, keyword-only
        ``propose(keys, neutral) -> (n_keys, n_vertices, 3)`` starting deltas. Default: zeros
        (every target starts as the neutral).

    Returns
    -------
    Rig
        ``names = keys.names``, ``deltas (n_keys, n_vertices, 3)``.

    Examples
    --------
    >>> keys = KeyShapes(np.zeros((2, 2)), np.ones((1, 2, 2)), ("lower_00",), [4], ("lower",), {"lower": [0, 1]})
    >>> rig = sculpt_targets(keys, Rig(np.eye(3), [[0, 1, 2]], np.zeros((0, 3, 3)), ()))
    >>> rig.names, rig.deltas.shape, float(abs(rig.deltas).max())
    (('lower_00',), (1, 3, 3), 0.0)
    """
    base = Rig(neutral.vertices, neutral.faces, np.zeros((0, neutral.n_vertices, 3)), ())
    deltas = np.zeros((keys.n_keys, neutral.n_vertices, 3))
    if propose is not None:
        deltas = np.array(propose(keys, base), dtype=float)
        if deltas.shape != (keys.n_keys, neutral.n_vertices, 3) or not np.isfinite(deltas).all():
            raise RigError(f"propose must return finite deltas of shape ({keys.n_keys}, "
                           f"{neutral.n_vertices}, 3); got {deltas.shape}")
        deltas[keys.mirrored] = 0.0  # a mirrored key's target is made from its source's (targets.complete_mirrors)
    return Rig(neutral.vertices, neutral.faces, deltas, keys.names)


def write_sculpt_kit(keys: KeyShapes, rig, folder, *, track: Track, video, unit: float = 1.0,
                     meshes=None, propose: Proposer | None = None, overwrite: bool = False,
                     neutral_source=None) -> SculptKit:
    """Write the sculpt kit for ``keys`` on the character ``rig`` into ``folder``.

    Parameters
    ----------
    keys : KeyShapes
    rig : str or Path
        The character's neutral: a ``.glb``/``.gltf`` (kept whole), an ``.obj``, an OBJ rig
        folder (its neutral is used) or a USD rig.
    folder : str or Path
        Created if needed; the kit's files are written atomically.
    track : Track, keyword-only
        The take the keys come from (image-space landmarks for the contact sheet).
    video : str or Path, keyword-only
        Its video (or image folder).
    unit : float, keyword-only
        Metres per OBJ unit (see :func:`keyshape.io.rig.load_rig`).
    meshes : sequence of int or str, optional, keyword-only
        glTF meshes to put the targets on; default: those with morph targets, else all.
    propose : callable, optional, keyword-only
        Starting targets (see :func:`sculpt_targets`).
    overwrite : bool, keyword-only
        Replace a kit already in ``folder``. By default a folder holding any of the kit's files
        is refused: its ``sculpt.glb`` may be an artist's work.
    neutral_source : str or Path, optional, keyword-only
        The still image or clip the keys' neutral comes from (``--neutral FILE``; ``take.json``'s
        ``neutral_source``): the contact sheet shows it as the neutral (see :func:`contact_sheet`).

    Returns
    -------
    SculptKit

    The three files are written together or not at all (staged beside ``folder``).
    """
    folder, rig = Path(folder), Path(rig)
    check_kit_folder(folder, overwrite=overwrite)
    _check_track(keys, track)
    is_gltf = rig.suffix.lower() in (".glb", ".gltf")
    neutral = _neutral(rig, unit=unit, meshes=meshes)
    targets = sculpt_targets(keys, neutral, propose=propose)
    with staged_folder(folder) as stage:
        _write_glb(rig if is_gltf else None, stage / GLB, targets, meshes)
        contact_sheet(keys, track, video, stage / SHEET, neutral_source=neutral_source)
        _write_readme(stage / README, keys, track, Path(video), rig, targets, _key_descriptions(keys, track))
    return SculptKit(folder, folder / GLB, folder / SHEET, folder / README)


def check_kit_folder(folder, *, overwrite: bool = False, replace: str = "overwrite=True") -> None:
    """Refuse a ``folder`` that holds a kit already (any of its files), unless ``overwrite``;
    ``replace`` names how to replace it, as the caller spells it (the command line: ``--force``)."""
    existing = [name for name in (GLB, SHEET, README) if (Path(folder) / name).exists()]
    if existing and not overwrite:
        raise InputError(f"{folder}: already holds a sculpt kit ({', '.join(existing)}), maybe sculpted; "
                         f"choose another folder, or replace it with {replace}")


def _check_track(keys: KeyShapes, track: Track) -> None:
    from ..report import separate_neutral

    if track.n_landmarks != keys.n_landmarks:
        raise InputError(f"the track has {track.n_landmarks} landmarks but the keys were made from "
                         f"{keys.n_landmarks}: give the track the keys come from")
    last = int(max(keys.frames.max(initial=0), -1 if separate_neutral(keys) else keys.neutral_frame))
    if last >= track.n_frames:
        raise InputError(f"the keys use frame {last} but the track has {track.n_frames} frames: "
                         "give the track (and video) the keys come from")


def _neutral(rig: Path, *, unit: float, meshes) -> Rig:
    if rig.suffix.lower() in (".glb", ".gltf"):
        from ..io.gltf import read_meshes

        return read_meshes(rig, meshes=meshes)[0]
    from ..io.rig import load_rig

    return load_rig(rig, unit=unit)


def _write_glb(source: Path | None, path: Path, targets: Rig, meshes) -> Path:
    from ..io.gltf import write_glb, write_gltf_targets

    if source is not None:
        return write_gltf_targets(source, path, targets, meshes=meshes)
    still = Weights(np.zeros((0, targets.n_targets)), targets.names, fps=30.0)
    return write_glb(path, targets, still)


# --------------------------------------------------------------------------- the contact sheet


def contact_sheet(keys: KeyShapes, track: Track, video, path, *, cell: int = 240, neutral_source=None) -> Path:
    """Draw the key frames as a PNG: one row per region, the neutral first, landmarks on the video.

    A neutral from a file of its own (``--neutral FILE``: ``keys.neutral_take`` is its name) is
    that file's picture (a still image, or the clip's frame ``keys.neutral_frame``) when
    ``neutral_source`` gives the file, else the neutral shape's landmarks alone; its tile is labelled with the file.

    Parameters
    ----------
    keys : KeyShapes
    track : Track
        Image-space landmarks of the take (``n_landmarks`` as ``keys``).
    video : str or Path
        The take's video or image folder (decoded with :func:`keyshape.capture.video.iter_frames`).
    path : str or Path
        Output ``.png`` (atomic).
    cell : int, keyword-only
        Side of each square picture, pixels.
    neutral_source : str or Path, optional, keyword-only
        The file the neutral comes from (ignored when the neutral is a frame of the take).

    Returns
    -------
    Path
    """
    from PIL import Image, ImageDraw

    from ..report import separate_neutral

    separate = separate_neutral(keys)
    frames = _decode(video, {*(() if separate else (int(keys.neutral_frame),)), *(int(f) for f in keys.frames)},
                     track.frame_index)
    rest = _rest_cells(keys, neutral_source, cell) if separate else None
    regions = list(keys.regions)
    columns = 1 + max(len(keys.keys_of(r)) for r in regions)
    described = dict(zip(keys.names, _key_descriptions(keys, track)))
    label, title = 62, 30
    sheet = Image.new("RGB", (columns * cell, title + len(regions) * (cell + label)), (24, 24, 24))
    draw = ImageDraw.Draw(sheet)
    draw.text((8, 7), f"{keys.n_keys} key shapes, {Path(video).name}: sculpt one target per key, named as shown",
              fill=(235, 235, 235), font=_font(15))
    for row, region in enumerate(regions):
        colour = _REGION_COLOURS[row % len(_REGION_COLOURS)]
        entries = [("neutral", int(keys.neutral_frame))]
        entries += [(keys.names[k], int(keys.frames[k])) for k in keys.keys_of(region)]
        for column, (name, frame) in enumerate(entries):
            if rest is not None and column == 0:  # the neutral from its own file
                picture, where = rest[0](keys.regions[region], colour), rest[1]
            else:
                picture = _cell(frames[frame], track.points[frame, :, :2], keys.regions[region], colour, cell)
                where = f"frame {track.frame_index[frame]}  {track.time[frame]:.2f} s"
            x, y = column * cell, title + row * (cell + label)
            sheet.paste(picture, (x, y))
            caption = f"{name}  ({region})" if name == "neutral" else name
            draw.text((x + 6, y + cell + 2), caption, fill=colour, font=_font(15))
            draw.text((x + 6, y + cell + 18), where, fill=(200, 200, 200), font=_font(12))
            for line, text in enumerate(textwrap.wrap(described.get(name, ""), 36)[:2]):  # what the key is
                draw.text((x + 6, y + cell + 33 + 13 * line), text, fill=(235, 235, 170), font=_font(11))
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")
    return Path(path)


def _rest_cells(keys: KeyShapes, neutral, size: int):
    """``(draw(region, colour) -> picture, label)`` for a neutral from its own file: the file's
    picture when ``neutral`` names it and a face is found there, else the neutral shape alone."""
    from ..capture.video import IMAGE_SUFFIXES
    from ..report import neutral_picture

    found = neutral_picture(neutral, int(keys.neutral_frame)) if neutral is not None else None
    still = neutral is not None and Path(neutral).suffix.lower() in IMAGE_SUFFIXES
    label = keys.neutral_take if still else f"{keys.neutral_take}, frame {int(keys.neutral_frame)}"
    if found is not None and np.isfinite(found[1]).all():
        return (lambda region, colour: _cell(found[0], found[1], region, colour, size)), label
    shape = keys.neutral[:, :2] - keys.neutral[:, :2].min(axis=0)  # the neutral's landmarks on a dark square
    shape = shape * (0.7 * size / max(float(shape.max()), 1e-9)) + 0.15 * size
    blank = np.full((size, size, 3), 40, np.uint8)
    return (lambda region, colour: _cell(blank, shape, region, colour, size)), f"{label} (no picture)"


def _font(size: int):
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


def _decode(video, wanted: set[int], source: np.ndarray) -> dict[int, np.ndarray]:
    """The video frames of the track rows ``wanted``, by row; ``source`` is the track's
    ``frame_index`` (row -> the video's frame number)."""
    from ..capture.video import iter_frames

    rows = {int(source[r]): r for r in wanted}
    found, count = {}, 0
    for index, (_, rgb) in enumerate(iter_frames(video, end=max(rows) + 1)):
        count = index + 1
        if index in rows:
            found[rows[index]] = rgb
    missing = sorted(set(rows) - {int(source[r]) for r in found})
    if missing:
        raise InputError(f"{video}: has no frame {missing[0]} (it has {count} frames); "
                         "give the video the keys come from")
    return found


def _cell(rgb: np.ndarray, points: np.ndarray, region: np.ndarray, colour, size: int):
    """The face in one square picture, landmarks grey and the region's in ``colour``."""
    from PIL import Image, ImageDraw

    image = Image.fromarray(rgb)
    box = _face_box(points, image.size)
    picture = image.crop(box).resize((size, size))
    draw = ImageDraw.Draw(picture)
    if not np.isfinite(points).all():
        draw.text((8, 8), "no face in this frame", fill=(255, 90, 90), font=_font(14))
        return picture
    scale = size / (box[2] - box[0])
    xy = (points - [box[0], box[1]]) * scale
    for x, y in xy:
        draw.point((x, y), fill=(170, 170, 170))
    for x, y in xy[region]:
        draw.ellipse((x - 1.5, y - 1.5, x + 1.5, y + 1.5), fill=colour)
    return picture


def _face_box(points: np.ndarray, image_size) -> tuple[int, int, int, int]:
    """A square around the landmarks with a margin (the whole picture without a face)."""
    if not np.isfinite(points).all():
        side = max(image_size)
        return (0, 0, side, side)
    low, high = points.min(axis=0), points.max(axis=0)
    centre, side = (low + high) / 2, max(1.0, float((high - low).max()) * 1.3)
    x0, y0 = (centre - side / 2).round().astype(int)
    return (int(x0), int(y0), int(x0 + round(side)), int(y0 + round(side)))


# --------------------------------------------------------------------------- README


def _key_descriptions(keys: KeyShapes, track: Track) -> tuple[str, ...]:
    """A readable line per key (:func:`keyshape.report.describe_keys`) for keys made from ``track``
    (the sculpt kit's rule: the track the keys come from), its neutral too unless from a file of its own."""
    from ..report import describe_keys, separate_neutral

    ours = tuple({*keys.takes, *(() if separate_neutral(keys) else (keys.neutral_take,))})
    return describe_keys(keys, track, take=ours)


def _write_readme(path: Path, keys: KeyShapes, track: Track, video: Path, rig: Path, targets: Rig,
                  described: tuple[str, ...]) -> Path:
    rows = [f"| `{keys.names[k]}` | {described[k]} | {keys.key_regions[k]} | "
            f"{int(track.frame_index[keys.frames[k]])} | "
            f"{track.time[keys.frames[k]]:.2f} | "
            + (f"no: the mirror image of `{keys.mirror_of[k]}`" if keys.mirror_of[k] else "yes") + " |"
            for k in range(keys.n_keys)]
    n_mirrored = int(keys.mirrored.sum())
    mirrored = "" if not n_mirrored else _MIRRORED.format(n=n_mirrored, example=keys.names[int(keys.mirrored.argmax())],
                                                          source=keys.mirror_of[int(keys.mirrored.argmax())])
    text = _README.format(n_keys=keys.n_keys, video=video.name, rig=rig.name, n_vertices=targets.n_vertices,
                          neutral=_neutral_sentence(keys, video), table="\n".join(rows), first=keys.names[0],
                          to_sculpt=keys.n_keys - n_mirrored, mirrored=mirrored)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def _neutral_sentence(keys: KeyShapes, video: Path) -> str:
    """Where the neutral comes from: a frame of the take, or a file of its own (``--neutral FILE``)."""
    from ..capture.video import IMAGE_SUFFIXES
    from ..report import separate_neutral

    frame = int(keys.neutral_frame)
    if not separate_neutral(keys):
        return f"The neutral frame is {frame}."
    if Path(keys.neutral_take).suffix.lower() in IMAGE_SUFFIXES:
        return (f"The neutral is the still image `{keys.neutral_take}` of the actor at rest, "
                f"not a frame of `{video.name}`.")
    return (f"The neutral is frame {frame} of `{keys.neutral_take}`, a separate clip of the actor at rest "
            f"(its frame nearest the clip's median shape), not a frame of `{video.name}`.")


_README = """# Sculpt kit: {n_keys} key shapes

keyshape found {n_keys} **key shapes** in `{video}`: real frames of the performance that, blended
with non-negative weights, reproduce every other frame. Give the character one target per key
shape, sculpted as *its* version of that expression, and the same weights will animate it.
You sculpt {to_sculpt} of them; the others are mirror images of a sculpted one.{mirrored}

| file | what |
|---|---|
| `{glb}` | `{rig}` ({n_vertices} vertices) with one morph target (shape key) per key shape, named after it; each starts as the neutral |
| `{sheet}` | the key frames: one row per face region, the neutral frame first, the region's landmarks highlighted |

## Sculpt

1. Look at `{sheet}`. Each key moves only its own region (upper: brows and eyes; lower: mouth and jaw);
   sculpt only that region in its target and leave the rest neutral, so keys of different regions
   combine freely.
2. Open `{glb}` in your tool. Blender: *File > Import > glTF 2.0*; the mesh's *Shape Keys* are
   `{first}` and the others, all at value 0 and identical to the *Basis*.
3. For each shape key, select it, set its value to 1 and sculpt or edit the mesh (edit mode works on the
   selected shape key) until the character makes the expression of that frame. Exaggerate or stylise
   freely; the weights carry timing and intensity, not the actor's geometry.
4. Export a binary glTF (`.glb`) with shape keys (Blender: *Data > Shape Keys*, on by default). Keep the
   shape-key names: they connect targets to keys.

## Animate

    keyshape retarget weights.csv --rig sculpted.glb --track track.npz -o animation.glb

`weights.csv` and `track.npz` are the outputs of `keyshape run` (or `solve` and `track`). The output is
your file, kept whole, with an animation `keyshape` added (morph weights, and the head rotation on a node
named like `head`). Other formats: `-o animation.usda` (USD), `--format livelink -o take.csv`.

Units and axes: glTF metres, +Y up, the character facing +Z. {neutral}

## Key shapes

| name | what it is (MediaPipe's strongest ARKit expressions at its frame) | region | frame | time (s) | sculpt? |
|---|---|---|---|---|---|
{table}
""".replace("{glb}", GLB).replace("{sheet}", SHEET)  # noqa: E501 - markdown table rows cannot wrap

_MIRRORED = """

**Mirrored keys ({n}).** A key such as `{example}` is the left-right mirror image of `{source}` (the
same frame, reflected through the face's symmetry plane): it lets a one-sided move the actor made on
one side drive the other side too. Leave its target as it is (neutral): when keyshape animates the
character it makes the target as the mirror image of `{source}`'s on a symmetric mesh. To make or
adjust it yourself in Blender: select `{source}`'s shape key, *Shape Key Specials > New Shape from Mix*
with only it at 1 (or duplicate it), rename the copy `{example}`, then *Shape Key Specials > Mirror
Shape Key* (tick *Topology Mirror* for a mesh whose halves are not placed exactly symmetric). A
sculpted (non-neutral) mirrored target is used as it is."""
