"""The default character: a stylised head built from MediaPipe's canonical face, deterministically.

The demo's character must look nothing like the actor, yet be close enough to a face that the
actor's key shapes transfer onto it. :func:`stylised_head` builds one in a few steps, with no
random numbers and no file other than the vendored MediaPipe model:

1. the **canonical face** (468 vertices, 898 triangles, centimetres) is read from the geometry
   metadata inside ``face_landmarker.task`` (:func:`canonical_face`);
2. the eye openings and the mouth slit are cut open, so lids and lips can part;
3. a smooth **caricature warp** enlarges the eyes, shrinks the nose, widens the mouth, shortens
   the chin and swells the cranium (each a Gaussian-weighted scaling about a feature centre);
4. the face's outline is closed by a **cranium** of rings running to a pole at the back;
5. two **Loop subdivisions** (Loop 1987) smooth it to about 11,000 vertices;
6. **eyeballs** with a pupil and an iris sit in the eye openings, and a **mouth interior** (a dark
   cavity, two rows of teeth, a tongue) behind the lips, which are closed at rest
   (:mod:`keyshape.targets._head_parts`); each a separate component;
7. **colours** per vertex: skin, lips, brows, hair, blush, eyes, teeth.

Vertex ``i < 468`` of the result is MediaPipe landmark ``i`` (subdivision keeps the original
vertices first), so the correspondence for MediaPipe key shapes is known by construction.

References
----------
.. [1] C. Loop, "Smooth subdivision surfaces based on triangles", M.S. thesis, University of
   Utah, 1987.
.. [2] MediaPipe Face Mesh canonical face model (Apache-2.0), in ``face_landmarker.task``.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass, field

import numpy as np

from ..capture.model_file import canonical_face
from ..containers import Rig
from ..exceptions import InputError
from ..schemes import mediapipe_scheme
from ._correspond import Correspondence
from ._head_parts import GAZE_NAMES, eyeball, gaze_deltas, gaze_weights, mouth_parts, skin_colours

__all__ = ["Character", "stylised_head", "with_gaze_targets", "gaze_weights", "GAZE_NAMES"]

_N_FACE = 468
_CM = 0.01


@dataclass(frozen=True, eq=False)
class Character:
    """A built-in character: its neutral mesh and where MediaPipe's landmarks sit on it.

    Attributes
    ----------
    rig : Rig
        Neutral vertices (metres, +Y up, facing +Z), faces, no targets.
    landmark_vertices : (468,) int
        Vertex of MediaPipe landmark ``i``.
    rigid : tuple of (n_part,) int
        Vertex sets of the rigid parts (the eyeballs: separate components, which expression
        transfer leaves still).
    name : str
    colours : (n_vertices, 3) float in [0, 1], optional
        Base colour per vertex (sRGB).
    parts : dict of str to (n_part,) int, optional
        Named vertex sets: ``skin``, ``left_eye``, ``right_eye``, ``cavity``, ``upper_teeth``,
        ``lower_teeth``, ``tongue``.
    eye_centres : (2, 3) float, optional
        Centres of the (left, right) eyeballs, about which the gaze turns them.
    """

    rig: Rig
    landmark_vertices: np.ndarray
    rigid: tuple
    name: str
    colours: np.ndarray | None = None
    parts: dict = field(default_factory=dict)
    eye_centres: np.ndarray | None = None

    def correspondence(self, n_landmarks: int = 478) -> Correspondence:
        """Landmark ``i`` ↔ vertex ``landmark_vertices[i]``, for MediaPipe key shapes (468 or 478)."""
        if n_landmarks not in (468, 478):
            raise InputError(f"the built-in character knows MediaPipe's landmarks (468 or 478); the key shapes "
                             f"have {n_landmarks}: give your own rig and a correspondence file")
        return Correspondence.from_vertex_ids(dict(enumerate(self.landmark_vertices)), n_landmarks=n_landmarks)

    def __repr__(self) -> str:
        return f"Character({self.name!r}, n_vertices={self.rig.n_vertices}, n_faces={len(self.rig.faces)})"


# --------------------------------------------------------------------------- the stylised head


@functools.cache
def stylised_head() -> Character:
    """The built-in stylised head (built once per process, the same every time).

    Returns
    -------
    Character
        About 11,000 vertices; 0.25 m tall.
    """
    vertices, faces = canonical_face()
    faces = _open_features(faces)
    vertices = _close_mouth(_caricature(vertices * _CM))
    vertices, faces = _add_cranium(vertices, faces)
    for _ in range(2):
        vertices, faces = _loop_subdivide(vertices, faces)
    faces = _facing_outward(vertices, faces)
    n_skin = len(vertices)
    scheme = mediapipe_scheme()
    contours = {**scheme["contours"], **{f"{k}_edges": v for k, v in scheme["contour_edges"].items()}}
    colours = skin_colours(vertices, faces, vertices[:_N_FACE], contours)
    pieces, centres = {}, []
    for side in ("left_eye", "right_eye"):
        centre, radius = _eye_socket(vertices, side)
        pieces[side] = eyeball(centre, radius)
        centres.append(centre)
    pieces.update(mouth_parts(vertices[_feature_loops()["mouth"]]))
    parts = {"skin": np.arange(n_skin)}
    all_vertices, all_faces, all_colours = [vertices], [faces], [colours]
    offset = n_skin
    for name, (part_vertices, part_faces, part_colours) in pieces.items():
        parts[name] = np.arange(offset, offset + len(part_vertices))
        all_vertices.append(part_vertices)
        all_faces.append(part_faces + offset)
        all_colours.append(part_colours)
        offset += len(part_vertices)
    vertices = np.vstack(all_vertices)
    rig = Rig(vertices, np.vstack(all_faces), np.zeros((0, len(vertices), 3)), ())
    return Character(rig, np.arange(_N_FACE), (parts["left_eye"], parts["right_eye"]), "stylised head",
                     colours=np.clip(np.vstack(all_colours), 0, 1), parts=parts, eye_centres=np.array(centres))


def with_gaze_targets(rig: Rig) -> Rig:
    """The stylised head's rig (as :func:`keyshape.targets.default_character` makes it) with eight
    more targets, :data:`GAZE_NAMES`, that turn its eyes (drive them with :func:`gaze_weights`)."""
    head = stylised_head()
    if rig.n_vertices != head.rig.n_vertices:
        raise InputError(f"gaze targets are the stylised head's: a rig of {head.rig.n_vertices} vertices; "
                         f"got {rig.n_vertices}")
    deltas = gaze_deltas(head.rig.vertices, head.rigid, head.eye_centres)
    return Rig(rig.vertices, rig.faces, np.concatenate([rig.deltas, deltas]), (*rig.names, *GAZE_NAMES))


def _close_mouth(vertices: np.ndarray, *, gap: float = 0.0004, sigma: float = 0.006) -> np.ndarray:
    """Bring the lips together at rest (the canonical face's are apart): the inner lip contour's
    upper and lower halves meet ``gap`` apart, the skin around them following with Gaussian falloff."""
    loop = np.asarray(_feature_loops()["mouth"])
    inner = vertices[loop]
    mid = float(np.median(inner[:, 1]))
    upper, lower = inner[inner[:, 1] >= mid], inner[inner[:, 1] < mid]
    upper, lower = upper[np.argsort(upper[:, 0])], lower[np.argsort(lower[:, 0])]
    x = vertices[:, 0]
    top, bottom = np.interp(x, upper[:, 0], upper[:, 1]), np.interp(x, lower[:, 0], lower[:, 1])
    centre = (top + bottom) / 2
    half = np.maximum(top - bottom - gap, 0) / 2
    above = vertices[:, 1] >= centre
    edge = np.where(above, top, bottom)
    inside = np.abs(x) <= np.abs(inner[:, 0]).max()
    reach = np.exp(-((vertices[:, 1] - edge) ** 2) / (2 * sigma**2)) * inside
    reach *= np.exp(-np.maximum(inner[:, 2].min() - 0.01 - vertices[:, 2], 0) ** 2 / (2 * sigma**2))
    moved = vertices.copy()
    moved[:, 1] += np.where(above, -half, half) * reach
    return moved


def _loops(edges: list) -> list[list[int]]:
    """Closed loops ``[[v0, v1, ...], ...]`` of a set of undirected edges where every vertex has degree 2."""
    neighbours: dict[int, list[int]] = {}
    for a, b in edges:
        neighbours.setdefault(int(a), []).append(int(b))
        neighbours.setdefault(int(b), []).append(int(a))
    loops, seen = [], set()
    for start in sorted(neighbours):
        if start in seen:
            continue
        loop, previous, current = [start], None, start
        seen.add(start)
        while True:
            step = [v for v in neighbours[current] if v != previous and v not in seen]
            if not step:
                break
            previous, current = current, step[0]
            loop.append(current)
            seen.add(current)
        loops.append(loop)
    return loops


def _feature_loops() -> dict[str, list[int]]:
    """The ordered inner-lip loop and the two eye loops, from MediaPipe's contour edges."""
    edges = mediapipe_scheme()["contour_edges"]
    lips = _loops(edges["lips"])
    canonical = canonical_face()[0]
    inner = min(lips, key=lambda loop: np.ptp(canonical[loop, 0]))
    return {"mouth": inner, "right_eye": _loops(edges["right_eye"])[0], "left_eye": _loops(edges["left_eye"])[0]}


def _open_features(faces: np.ndarray) -> np.ndarray:
    """Drop the triangles spanning the mouth slit and the eye openings (all corners on one loop)."""
    keep = np.ones(len(faces), dtype=bool)
    for loop in _feature_loops().values():
        keep &= ~np.isin(faces, loop).all(axis=1)
    return faces[keep]


def _caricature(vertices: np.ndarray) -> np.ndarray:
    """A smooth warp of the face (metres): big eyes, small nose, wide mouth, short chin, big brow.

    Each feature scales space about its centre by ``s`` with Gaussian weight
    ``exp(−|p − c|² / 2σ²)``: ``p ← p + Σ_f w_f(p) (S_f − I)(p − c_f)``.
    """
    loops = _feature_loops()
    right, left = vertices[loops["right_eye"]].mean(axis=0), vertices[loops["left_eye"]].mean(axis=0)
    mouth = vertices[loops["mouth"]].mean(axis=0)
    nose = vertices[[1, 2, 4, 5, 6, 19, 94, 195, 197]].mean(axis=0)
    chin = vertices[152]
    features = [  # centre, sigma (m), per-axis scale
        (right, 0.022, (1.55, 1.7, 1.3)),
        (left, 0.022, (1.55, 1.7, 1.3)),
        (nose, 0.022, (0.8, 0.85, 0.7)),
        (mouth, 0.02, (1.12, 1.0, 1.0)),
        (chin + [0, -0.01, 0], 0.035, (0.8, 0.75, 0.9)),
        (np.array([0.0, 0.06, -0.02]), 0.06, (1.12, 1.2, 1.1)),
    ]
    moved = vertices.copy()
    for centre, sigma, scale in features:
        offset = vertices - centre
        weight = np.exp(-(offset**2).sum(axis=1) / (2 * sigma**2))[:, None]
        moved += weight * offset * (np.asarray(scale) - 1.0)
    return moved


def _add_cranium(vertices: np.ndarray, faces: np.ndarray, *, n_rings: int = 7):
    """Close the face outline with rings that run over an ellipsoid to a pole behind the head."""
    boundary = _boundary_loop(faces)
    centre = np.array([0.0, 0.012, -0.045])
    axes = np.array([0.088, 0.112, 0.105])
    pole_direction = np.array([0.0, 0.1, -1.0]) / np.linalg.norm([0.0, 0.1, -1.0])
    start = vertices[boundary] - centre
    radius0 = np.linalg.norm(start, axis=1)
    direction0 = start / radius0[:, None]
    rings = []
    for j in range(1, n_rings):
        t = j / n_rings
        direction = _slerp(direction0, pole_direction, t)
        on_ellipsoid = 1.0 / np.sqrt(((direction / axes) ** 2).sum(axis=1))
        blend = np.clip(t / 0.45, 0, 1)
        blend = blend * blend * (3 - 2 * blend)
        radius = (1 - blend) * radius0 + blend * on_ellipsoid
        rings.append(centre + direction * radius[:, None])
    pole = centre + pole_direction / np.sqrt(((pole_direction / axes) ** 2).sum())
    n, m = len(vertices), len(boundary)
    index = [np.asarray(boundary)] + [n + j * m + np.arange(m) for j in range(n_rings - 1)]
    new_faces = []
    for a, b in itertools.pairwise(index):
        a2, b2 = np.roll(a, -1), np.roll(b, -1)
        new_faces += [np.stack([a, b, a2], axis=1), np.stack([a2, b, b2], axis=1)]
    pole_index = n + (n_rings - 1) * m
    last = index[-1]
    new_faces.append(np.stack([last, np.full(m, pole_index), np.roll(last, -1)], axis=1))
    vertices = np.vstack([vertices, *rings, pole])
    return vertices, np.vstack([faces, *new_faces])


def _slerp(start: np.ndarray, end: np.ndarray, t: float) -> np.ndarray:
    """Spherical interpolation of unit vectors ``(n, 3)`` toward one unit vector ``end``."""
    cos = np.clip(start @ end, -1.0, 1.0)
    angle = np.arccos(cos)[:, None]
    sin = np.sin(angle)
    safe = np.where(sin > 1e-9, sin, 1.0)
    out = np.where(sin > 1e-9, (np.sin((1 - t) * angle) * start + np.sin(t * angle) * end) / safe, start)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _boundary_loop(faces: np.ndarray) -> list[int]:
    """The longest boundary loop (the face outline), ordered."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    loops = _loops(unique[count == 1].tolist())
    return max(loops, key=len)


def _facing_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Wind every triangle so its normal points away from the head's centre (glTF front faces)."""
    centre = np.array([0.0, 0.012, -0.03])
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    outward = ((a + b + c) / 3 - centre * [1, 1, 1]) * [1, 1, 1]
    inward = (normal * outward).sum(axis=1) < 0
    return np.where(inward[:, None], faces[:, [0, 2, 1]], faces)


def _loop_subdivide(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One step of Loop subdivision (Loop 1987), with the boundary rules; old vertices keep their indices.

    Edge points: ``3/8 (a + b) + 1/8 (c + d)`` inside, the midpoint on the boundary. Vertex
    points: ``(1 − nβ) v + β Σ neighbours`` with ``β = (5/8 − (3/8 + cos(2π/n)/4)²) / n``
    inside, ``3/4 v + 1/8 (b₁ + b₂)`` on the boundary.
    """
    from scipy import sparse

    n = len(vertices)
    half = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 3, 2)
    opposite = faces[:, [2, 0, 1]]
    key = np.sort(half.reshape(-1, 2), axis=1)
    edges, edge_of, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    edge_of = edge_of.reshape(-1)
    boundary = count == 1
    opposite_sum = np.zeros((len(edges), 3))
    np.add.at(opposite_sum, edge_of, vertices[opposite.reshape(-1)])
    ends = vertices[edges[:, 0]] + vertices[edges[:, 1]]
    odd = np.where(boundary[:, None], ends / 2, 3 / 8 * ends + 1 / 8 * opposite_sum)
    adjacency = sparse.csr_matrix((np.ones(2 * len(edges)), (edges.ravel(), edges[:, ::-1].ravel())),
                                  shape=(n, n))
    valence = np.asarray(adjacency.sum(axis=1)).ravel()
    beta = np.where(valence > 3, (5 / 8 - (3 / 8 + np.cos(2 * np.pi / np.maximum(valence, 1)) / 4) ** 2)
                    / np.maximum(valence, 1), 3 / 16)
    even = (1 - valence * beta)[:, None] * vertices + beta[:, None] * (adjacency @ vertices)
    on_boundary = np.zeros(n, dtype=bool)
    on_boundary[edges[boundary].ravel()] = True
    rim = sparse.csr_matrix((np.ones(2 * boundary.sum()), (edges[boundary].ravel(), edges[boundary][:, ::-1].ravel())),
                            shape=(n, n))
    even[on_boundary] = (3 / 4 * vertices + 1 / 8 * (rim @ vertices))[on_boundary]
    e = n + edge_of.reshape(-1, 3)  # edge points of (v0 v1), (v1 v2), (v2 v0)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    new_faces = np.concatenate([np.stack([a, e[:, 0], e[:, 2]], 1), np.stack([b, e[:, 1], e[:, 0]], 1),
                                np.stack([c, e[:, 2], e[:, 1]], 1), e])
    return np.vstack([even, odd]), new_faces


def _eye_socket(vertices: np.ndarray, side: str) -> tuple[np.ndarray, float]:
    """Centre and radius of the eyeball behind one eye opening, just behind the lids."""
    rim = vertices[_feature_loops()[side]]
    radius = 0.5 * float(np.ptp(rim[:, 0]))
    front = rim[:, 2].mean() - 0.08 * radius
    return np.array([*rim[:, :2].mean(axis=0), front - radius * 1.06]), radius
