"""Characters: load a blendshape rig, or build the default one from key shapes.

A rig is one of

* a folder of OBJ files sharing one topology (``neutral.obj`` plus one ``<target>.obj`` per
  target; the file stem is the target name; quads and n-gons are fan-triangulated);
* a ``.glb``/``.gltf`` whose morph targets are named in ``mesh.extras.targetNames``
  (:func:`keyshape.io.gltf.read_rig`: several meshes and primitives sharing the names,
  skinned or not, placed in the world by their nodes);
* a USD file (``.usd``, ``.usda``, ``.usdc``, ``.usdz``) with UsdSkel blend shapes
  (:func:`keyshape.io.usd.read_rig`, needs ``usd-core``);
* a VRM avatar (``.vrm``, VRM 1.0 or 0.x): one target per expression, the mix of morph targets
  it binds (:func:`load_vrm`).

Either way it becomes a :class:`~keyshape.containers.Rig`: neutral vertices plus one delta
(target − neutral) per target, so that ``V(t) = N + Σ w_i(t) (T_i − N)`` (the paper's Eq. 1).
Rigs are in glTF's convention: metres, +Y up, facing +Z. OBJ files carry no unit, so
``unit`` (metres per file unit) scales them; USD files are converted from their
``metersPerUnit`` and ``upAxis``; glTF is metres by definition.
"""

from __future__ import annotations

import functools
import re
import warnings
from pathlib import Path

import numpy as np

from ..containers import Rig
from ..exceptions import InputError, RigError
from ._vrm_read import VrmAvatar, VrmExpression
from .atomic import atomic_path

__all__ = ["load_rig", "load_vrm", "save_obj_folder", "read_obj", "parse_unit", "RIG_SUFFIXES", "VrmAvatar",
           "VrmExpression"]

NEUTRAL = "neutral"
GLTF_SUFFIXES = (".glb", ".gltf")
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
VRM_SUFFIXES = (".vrm",)
RIG_SUFFIXES = (*GLTF_SUFFIXES, *VRM_SUFFIXES, *USD_SUFFIXES, ".obj")
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
# image (x right, y down, z away from camera) -> glTF (x right, y up, z toward viewer)
_SAFE_NAME = re.compile(r"^[^/\\:*?\"<>|\x00-\x1f]+$")


def load_rig(path, *, unit: float = 1.0) -> Rig:
    """Load a character's blendshapes from an OBJ folder, a glTF file or a USD file.

    Parameters
    ----------
    path : str or Path
        A folder holding ``neutral.obj`` (or exactly one OBJ whose name contains
        "neutral") and ``<target>.obj`` files with one topology (targets sorted by name);
        a single ``.obj`` (a neutral with no targets, e.g. to sculpt on); a ``.glb``/``.gltf``
        with named morph targets (in world space: node transforms applied, skinned meshes as stored;
        quantized geometry decoded); a ``.vrm`` avatar (its expressions as targets, see
        :func:`load_vrm`); or a USD file with UsdSkel blend shapes.
    unit : float, keyword-only
        Metres per OBJ unit (0.01 for centimetres). glTF and USD files state their units.

    Returns
    -------
    Rig

    Raises
    ------
    RigError
        Missing neutral, a target whose vertex count or faces differ from the neutral's,
        a glTF or USD file without (named) blend shapes, or an unsupported path.
    InputError
        ``unit`` given for a format that states its own, or not a positive number.

    Examples
    --------
    >>> import tempfile
    >>> rig = Rig(np.eye(3), [[0, 1, 2]], np.ones((1, 3, 3)), ("smile",))
    >>> folder = save_obj_folder(rig, tempfile.mkdtemp())
    >>> load_rig(folder).names
    ('smile',)
    >>> float(load_rig(folder, unit=0.01).deltas.max())
    0.01
    """
    path = Path(path)
    unit = _check_unit(unit)
    suffix = path.suffix.lower()
    if path.is_dir() or suffix == ".obj":
        rig = _load_obj_folder(path) if path.is_dir() else _load_obj_file(path)
        return _scaled(rig, unit)
    if unit != 1.0 and suffix in GLTF_SUFFIXES + VRM_SUFFIXES + USD_SUFFIXES:
        raise InputError(f"{str(path)!r}: unit applies to OBJ files only; glTF is in metres and USD "
                         "states its metersPerUnit")
    if suffix in GLTF_SUFFIXES:
        from .gltf import read_rig

        try:
            return read_rig(path)
        except (IndexError, KeyError, TypeError, AttributeError, OverflowError, ZeroDivisionError,
                FloatingPointError) as error:  # a field missing or of the wrong kind, deep in the file
            raise RigError(f"{path}: a damaged glTF file ({error.__class__.__name__}: {error})") from None
    if suffix in VRM_SUFFIXES:
        return load_vrm(path).rig
    if suffix in USD_SUFFIXES:
        from .usd import read_rig

        return read_rig(path)
    expected = "an OBJ folder, an .obj, a .glb/.gltf, a .vrm or a USD (.usd/.usda/.usdc/.usdz) file"
    if not path.exists():
        raise RigError(f"no rig at {str(path)!r}: expected {expected}")
    raise RigError(f"cannot load a rig from {str(path)!r}: expected {expected}")


def load_vrm(path) -> VrmAvatar:
    """A VRM avatar (``.vrm``: VRM 1.0's ``VRMC_vrm`` or VRM 0.x's ``VRM`` extension) and its rig.

    The rig holds the meshes with morph targets in world space (as :func:`load_rig` reads a
    ``.glb``; a VRM 0.x avatar, which faces −Z, turned to face +Z), and one target per expression,
    named as the avatar names it (VRM 1.0: ``aa``, ``blink``, custom names; VRM 0.x: ``A``,
    ``Blink``, ``Joy``, group names): ``delta = Σ weight · morph delta`` over its binds (weights
    in [0, 1]; VRM 0.x's 0..100 divided by 100). Morph targets with ARKit names that no
    expression has are targets too ("perfect sync").

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    VrmAvatar
        ``rig`` (a :class:`~keyshape.containers.Rig`), ``version`` (``"1.0"`` or ``"0.x"``),
        ``expressions`` (name, VRM 1.0 preset or None, binds), ``arkit`` (perfect-sync names).

    Raises
    ------
    RigError
        One line naming the file and what is wrong with it.
    """
    from ._vrm_read import read_vrm

    path = Path(path)
    if not path.is_file():
        raise RigError(f"no rig at {str(path)!r}: no such VRM file")
    try:
        return read_vrm(path)
    except (IndexError, KeyError, TypeError, AttributeError, OverflowError, ZeroDivisionError,
            FloatingPointError, ValueError) as error:
        raise RigError(f"{path}: a damaged VRM file ({error.__class__.__name__}: {error})") from None


def _check_unit(unit) -> float:
    try:
        unit = float(unit)
    except (TypeError, ValueError):
        raise InputError(f"unit must be metres per file unit (a number); got {unit!r}") from None
    if not np.isfinite(unit) or unit <= 0:
        raise InputError(f"unit must be a positive number of metres per file unit; got {unit!r}")
    return unit


def parse_unit(text: str) -> float:
    """Metres per unit from ``m``, ``cm``, ``mm``, ``in``, ``ft`` or a number (e.g. ``0.01``)."""
    text = str(text).strip().lower()
    if text in UNITS:
        return UNITS[text]
    try:
        return _check_unit(float(text))
    except (ValueError, InputError):
        raise InputError(f"unit must be one of {', '.join(UNITS)} or metres per unit; got {text!r}") from None


def _scaled(rig: Rig, unit: float) -> Rig:
    if unit == 1.0:
        return rig
    return Rig(rig.vertices * unit, rig.faces, rig.deltas * unit, rig.names)


# --------------------------------------------------------------------------- OBJ


def read_obj(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and fan-triangulated faces of a Wavefront OBJ file.

    Only ``v`` and ``f`` records are read; texture and normal indices in ``f a/b/c``
    are ignored, and negative (relative) indices are resolved.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    vertices : (n_vertices, 3) float
    faces : (n_faces, 3) int, 0-based triangles (a polygon of n corners gives n − 2)
    """
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.__class__.__name__})") from None
    vertices, faces = _read_obj_fast(text) or _read_obj_checked(text.splitlines(), path)
    if not len(vertices):
        raise InputError(f"{path}: an OBJ mesh needs vertices ('v x y z' lines); it has none")
    return vertices, faces


_VERTEX = re.compile(r"^v[ \t]+([^\n]*)", re.MULTILINE)
_FACE = re.compile(r"^f[ \t]+([^\n]*)", re.MULTILINE)


def _read_obj_fast(text: str):
    """The common case (no relative indices, no bad records), vectorised; None otherwise."""
    vertices = _fast_vertices(_VERTEX.findall(text))
    faces = _fast_faces("\n".join(_FACE.findall(text)))
    if vertices is None or faces is None or (faces.size and faces.max() >= len(vertices)):
        return None
    return vertices, faces.copy()


def _fast_vertices(lines: list[str]) -> np.ndarray | None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # older numpy warns on unparsable text
        try:
            flat = np.fromstring("\n".join(lines), sep=" ") if lines else np.zeros(0)
        except ValueError:  # newer numpy raises instead
            flat = np.zeros(0)
    if flat.size == 3 * len(lines):
        return flat.reshape(-1, 3)
    try:  # extra columns (vertex colours): keep x, y, z
        return np.array([line.split()[:3] for line in lines], dtype=float).reshape(-1, 3)
    except ValueError:
        return None


@functools.lru_cache(maxsize=4)
def _fast_faces(text: str) -> np.ndarray | None:
    """Fan-triangulated faces of the ``f`` records (cached: a rig's files share them)."""
    corners = re.sub(r"/\S*", "", text)
    try:
        index = np.array(corners.split(), dtype=np.int64) - 1
    except ValueError:
        return None
    counts = np.array([len(line.split()) for line in corners.split("\n")] if text else [], dtype=np.int64)
    if (counts < 3).any() or (index < 0).any():
        return None
    faces = _fan(index, counts)
    faces.flags.writeable = False
    return faces


def _fan(index: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(n_faces, 3): polygon p of ``counts[p]`` corners -> (c0, c1, c2), (c0, c2, c3), ..."""
    starts = np.cumsum(counts) - counts
    n_triangles = counts - 2
    first = np.repeat(starts, n_triangles)
    # k = 1 .. n - 2 within each polygon
    k = np.arange(n_triangles.sum()) - np.repeat(np.cumsum(n_triangles) - n_triangles, n_triangles) + 1
    return np.stack([index[first], index[first + k], index[first + k + 1]], axis=1)


def _read_obj_checked(lines: list[str], path) -> tuple[np.ndarray, np.ndarray]:
    """Line by line, resolving relative indices and quoting the first bad record."""
    vertices, polygons = [], []
    for number, line in enumerate(lines, 1):
        fields = line.split()
        if not fields:
            continue
        if fields[0] == "v":
            vertices.append(_parse_vertex(fields, path, number))
        elif fields[0] == "f":
            polygons.append(_parse_face(fields, len(vertices), path, number))
    vertices = np.array(vertices, dtype=float).reshape(-1, 3)
    faces = _fan_triangulate(polygons)
    if faces.size and faces.max() >= len(vertices):
        raise InputError(f"{path}: a face refers to vertex {faces.max() + 1}; the file has {len(vertices)}")
    return vertices, faces


def _parse_vertex(fields, path, number) -> list[float]:
    try:
        x, y, z = (float(v) for v in fields[1:4])
    except ValueError:
        _bad(path, number, fields)
    return [x, y, z]


def _parse_face(fields, n_vertices, path, number) -> list[int]:
    try:
        corners = [int(corner.split("/")[0]) for corner in fields[1:]]
    except ValueError:
        _bad(path, number, fields)
    if len(corners) < 3 or 0 in corners:
        _bad(path, number, fields)
    # OBJ is 1-based; negative indices count back from the last vertex read so far.
    return [c - 1 if c > 0 else n_vertices + c for c in corners]


def _bad(path, number, fields):
    raise InputError(f"{path}, line {number}: cannot read {' '.join(fields)!r}")


def _fan_triangulate(polygons: list[list[int]]) -> np.ndarray:
    """(n_faces, 3) int: polygon (a, b, c, d, ...) -> (a, b, c), (a, c, d), ..."""
    triangles = [(p[0], p[i], p[i + 1]) for p in polygons for i in range(1, len(p) - 1)]
    return np.array(triangles, dtype=np.int64).reshape(-1, 3)


def _neutral_path(folder: Path) -> Path:
    exact = folder / f"{NEUTRAL}.obj"
    if exact.is_file():
        return exact
    named = sorted(p for p in folder.glob("*.obj") if NEUTRAL in p.stem.lower())
    if len(named) == 1:
        return named[0]
    found = f"; candidates: {[p.name for p in named]}" if named else ""
    raise RigError(f"rig folder {str(folder)!r} has no {NEUTRAL}.obj (the neutral shape){found}")


def _load_obj_folder(folder: Path) -> Rig:
    neutral_path = _neutral_path(folder)
    vertices, faces = read_obj(neutral_path)
    target_paths = sorted(p for p in folder.glob("*.obj") if p != neutral_path)
    deltas = [_target_delta(p, neutral_path.name, vertices, faces) for p in target_paths]
    return Rig(vertices, faces, np.array(deltas).reshape(-1, *vertices.shape),
               tuple(p.stem for p in target_paths))


def _load_obj_file(path: Path) -> Rig:
    if not path.is_file():
        raise RigError(f"no rig at {str(path)!r}: no such OBJ file")
    vertices, faces = read_obj(path)
    return Rig(vertices, faces, np.zeros((0, *vertices.shape)), ())


def _target_delta(path: Path, neutral_name: str, neutral: np.ndarray, neutral_faces: np.ndarray) -> np.ndarray:
    """(n_vertices, 3) float: target − neutral, after checking both share one topology."""
    vertices, faces = read_obj(path)
    if len(vertices) != len(neutral):
        raise RigError(
            f"{path.name} has {len(vertices)} vertices but {neutral_name} has {len(neutral)}: "
            "every target must share the neutral's topology"
        )
    if faces.size and not np.array_equal(faces, neutral_faces):
        raise RigError(
            f"{path.name} has the same {len(vertices)} vertices as {neutral_name} but other faces "
            f"({len(faces)} triangles vs {len(neutral_faces)}): every target must share the neutral's topology"
        )
    return vertices - neutral


def save_obj_folder(rig: Rig, folder) -> Path:
    """Write a rig as ``neutral.obj`` plus ``<name>.obj`` per target (the form :func:`load_rig` reads).

    Parameters
    ----------
    rig : Rig
    folder : str or Path
        Created if needed; each file is written atomically.

    Returns
    -------
    Path
        The folder.

    Raises
    ------
    RigError
        If a target name cannot be a file name, or is ``neutral``.
    """
    folder = Path(folder)
    bad = [n for n in rig.names if not _SAFE_NAME.match(n) or n == NEUTRAL or n.strip(". ") == ""]
    if bad:
        raise RigError(f"target names {bad} cannot be written as OBJ file names")
    folder.mkdir(parents=True, exist_ok=True)
    _write_obj(folder / f"{NEUTRAL}.obj", rig.vertices, rig.faces)
    for name, delta in zip(rig.names, rig.deltas):
        _write_obj(folder / f"{name}.obj", rig.vertices + delta, rig.faces)
    return folder


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    with atomic_path(path) as tmp:
        tmp.write_text("# written by keyshape\n" + "\n".join(lines) + "\n", encoding="utf-8")
