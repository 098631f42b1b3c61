"""Correspondence: which point of a character's mesh each tracked landmark stands for.

Expression transfer and semantic mapping (:mod:`keyshape.targets._transfer`, :mod:`keyshape.targets._propose`)
compare the actor's landmark motion with the character's surface, so they need, for some
landmarks, a point on the character. A :class:`Correspondence` stores each such point as
barycentric weights over one triangle (a plain vertex is a triangle of one vertex repeated),
so it follows the mesh when the mesh deforms.

Three ways to get one:

* :meth:`Correspondence.from_vertex_ids`: landmark index -> vertex id (e.g. ICT-FaceKit's 68
  landmark vertices);
* :func:`read_correspondence`: a JSON file written by a person (vertex ids, barycentric
  points, or 3D points that are snapped to the surface);
* :func:`~keyshape.targets.find_correspondence` (in ``_correspond_auto``): for human-like heads,
  render the neutral from the front and run MediaPipe on the picture; each landmark becomes the
  visible surface point under it.

The JSON file (``CORRESPONDENCE.json``)::

    {"format": "keyshape-correspondence", "version": 1, "n_landmarks": 478,
     "landmarks": {"33": 1204,                                      # a vertex id
                   "263": [0.031, 0.042, 0.087],                     # a 3D point (snapped)
                   "61": {"vertices": [5, 6, 7], "weights": [0.2, 0.3, 0.5]}}}

A bare object ``{"33": 1204, ...}`` or a list of vertex ids (landmark ``i`` -> ``list[i]``)
is read too. Points are in the rig's units as loaded (metres for glTF).

The mesh geometry used here (``snap_to_surface``, ``mesh_components``, ``weld_vertices``) lives
in :mod:`keyshape.mesh`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import sparse

from ..exceptions import InputError, RigError
from ..mesh import snap_to_surface

__all__ = ["Correspondence", "read_correspondence", "correspondence_from_dict"]

FORMAT = "keyshape-correspondence"


@dataclass(frozen=True, eq=False)
class Correspondence:
    """Landmarks ↔ points on a target mesh, as barycentric combinations of its vertices.

    Attributes
    ----------
    landmarks : (n_corr,) int
        Landmark indices (unique, in ``0..n_landmarks-1``).
    vertices : (n_corr, 3) int
        The target vertices each point is made of (a triangle, or one vertex three times).
    weights : (n_corr, 3) float
        Barycentric weights, ≥ 0, each row summing to 1.
    n_landmarks : int
        Size of the landmark scheme (478 for MediaPipe, 68 for iBUG).
    residual : (n_corr,) float or None
        Found automatically: how far each point lies, on the render it was found on, from where the
        tracker put its landmark, in picture widths (0 where the landmark's pixel was on the surface;
        more where it had to move onto a usable part). None for given correspondences.
    rest_scores : dict str -> float or None
        Found automatically: MediaPipe's ARKit scores of the character's neutral on that render
        (how the tracker reads the character at rest; the score-based mapping subtracts them, see
        :func:`keyshape.targets._propose._score_mapping`). Kept in the JSON file.

    Examples
    --------
    >>> corr = Correspondence.from_vertex_ids({0: 2, 4: 0}, n_landmarks=5)
    >>> corr.points(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]))[:, 0].tolist()
    [2.0, 0.0]
    """

    landmarks: np.ndarray
    vertices: np.ndarray
    weights: np.ndarray
    n_landmarks: int
    residual: np.ndarray | None = None
    rest_scores: dict | None = None

    def __post_init__(self):
        landmarks = np.asarray(self.landmarks, dtype=np.int64).reshape(-1)
        vertices = np.asarray(self.vertices, dtype=np.int64).reshape(-1, 3)
        weights = np.asarray(self.weights, dtype=float).reshape(-1, 3)
        n = int(self.n_landmarks)
        if not len(landmarks) == len(vertices) == len(weights):
            raise InputError(f"a correspondence needs as many landmarks, vertex triples and weight triples; "
                             f"got {len(landmarks)}, {len(vertices)} and {len(weights)}")
        if len(landmarks) and (landmarks.min() < 0 or landmarks.max() >= n):
            raise InputError(f"landmark indices must be in 0..{n - 1}; got {landmarks.min()}..{landmarks.max()}")
        if len(np.unique(landmarks)) != len(landmarks):
            raise InputError("each landmark may correspond to one point only; repeated landmarks")
        if (vertices < 0).any() or (weights < -1e-9).any() or not np.allclose(weights.sum(axis=1), 1):
            raise InputError("correspondence vertices must be >= 0 and weights >= 0 summing to 1 per row")
        residual = None if self.residual is None else np.asarray(self.residual, dtype=float).reshape(-1)
        if residual is not None and (len(residual) != len(landmarks) or not (residual >= 0).all()):
            raise InputError(f"residual must be {len(landmarks)} numbers >= 0, one per landmark; got {self.residual!r}")
        for name, value in (("landmarks", landmarks), ("vertices", vertices), ("weights", weights),
                            ("residual", residual)):
            if value is not None:
                value.flags.writeable = False
            object.__setattr__(self, name, value)
        object.__setattr__(self, "n_landmarks", n)
        if self.rest_scores is not None:
            scores = {str(k): float(v) for k, v in dict(self.rest_scores).items()}
            if not all(np.isfinite(v) for v in scores.values()):
                raise InputError("rest_scores must be finite numbers")
            object.__setattr__(self, "rest_scores", scores)

    n_corr = property(lambda self: len(self.landmarks))

    def quality(self) -> dict | None:
        """How well an automatic correspondence holds up: landmarks kept, residual percentiles
        (% of the render's width); None for a given one."""
        if self.residual is None:
            return None
        pct = 100 * self.residual if self.n_corr else np.zeros(1)
        return {"landmarks_kept": self.n_corr, "of": self.n_landmarks,
                "median_residual_pct": round(float(np.median(pct)), 3),
                "p95_residual_pct": round(float(np.percentile(pct, 95)), 3),
                "moved": int((pct > 0.5).sum())}

    @classmethod
    def from_vertex_ids(cls, ids, *, n_landmarks: int | None = None) -> Correspondence:
        """Landmark ``i`` ↔ vertex ``ids[i]``.

        Parameters
        ----------
        ids : dict int -> int, or sequence of int (landmark ``i`` -> ``ids[i]``)
        n_landmarks : int, optional, keyword-only
            Default: the largest landmark index + 1.
        """
        pairs = dict(ids) if isinstance(ids, dict) else dict(enumerate(ids))
        landmarks = np.array([int(k) for k in pairs], dtype=np.int64)
        vertices = np.array([int(v) for v in pairs.values()], dtype=np.int64)
        n = int(n_landmarks) if n_landmarks is not None else int(landmarks.max(initial=-1)) + 1
        weights = np.zeros((len(vertices), 3))
        weights[:, 0] = 1.0
        return cls(landmarks, np.repeat(vertices[:, None], 3, axis=1), weights, n)

    def points(self, vertices: np.ndarray) -> np.ndarray:
        """Positions ``(..., n_corr, 3)`` of the points on a mesh ``(..., n_vertices, 3)``.

        Works on deltas too (``rig.deltas`` gives each target's motion at the points).
        """
        vertices = np.asarray(vertices, dtype=float)
        # c: point, j: triangle corner, d: dimension
        return np.einsum("...cjd,cj->...cd", vertices[..., self.vertices, :], self.weights)

    def matrix(self, n_vertices: int) -> sparse.csr_matrix:
        """``B (n_corr, n_vertices)``, sparse: ``points(V) == B @ V``."""
        rows = np.repeat(np.arange(self.n_corr), 3)
        return sparse.csr_matrix((self.weights.ravel(), (rows, self.vertices.ravel())),
                                 shape=(self.n_corr, n_vertices))

    def check(self, n_vertices: int, n_landmarks: int | None = None) -> Correspondence:
        """Raise :class:`RigError` unless the vertices exist (and the scheme size matches); return self."""
        if self.n_corr and self.vertices.max() >= n_vertices:
            raise RigError(f"the correspondence uses vertex {int(self.vertices.max())} but the mesh has "
                           f"{n_vertices} vertices: was it made for another mesh?")
        if n_landmarks is not None and n_landmarks != self.n_landmarks:
            raise RigError(f"the correspondence is for {self.n_landmarks} landmarks but the key shapes have "
                           f"{n_landmarks}: make one for this landmark scheme")
        return self

    def to_dict(self) -> dict:
        """The JSON form (see the module docstring); vertex ids where a point is a vertex."""
        entries = {}
        for landmark, tri, w in zip(self.landmarks, self.vertices, self.weights):
            if np.isclose(w.max(), 1.0):
                entries[str(int(landmark))] = int(tri[int(np.argmax(w))])
            else:
                entries[str(int(landmark))] = {"vertices": tri.tolist(), "weights": np.round(w, 6).tolist()}
        document = {"format": FORMAT, "version": 1, "n_landmarks": self.n_landmarks, "landmarks": entries}
        if self.residual is not None:
            document["quality"] = self.quality()  # for the report and the reader; ignored when read back
        if self.rest_scores is not None:
            document["rest_scores"] = {k: round(v, 6) for k, v in self.rest_scores.items()}
        return document

    def save(self, path) -> Path:
        """Write the JSON file atomically."""
        from ..io.atomic import atomic_path

        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(self.to_dict(), indent=1) + "\n", encoding="utf-8")
        return Path(path)

    def __repr__(self) -> str:
        return f"Correspondence(n_corr={self.n_corr}, n_landmarks={self.n_landmarks})"


# --------------------------------------------------------------------------- reading a file


def read_correspondence(path, vertices: np.ndarray, faces: np.ndarray, *,
                        n_landmarks: int | None = None) -> Correspondence:
    """Read a correspondence JSON file for the mesh ``(vertices, faces)``.

    Parameters
    ----------
    path : str or Path
    vertices : (n_vertices, 3) float
        The target's neutral (3D points in the file are snapped onto it).
    faces : (n_faces, 3) int
    n_landmarks : int, optional, keyword-only
        The landmark scheme's size; default: the file's ``n_landmarks``, else the largest index + 1.

    Returns
    -------
    Correspondence

    Raises
    ------
    InputError
        Unreadable file or a bad entry (the message names the file and the landmark).
    RigError
        A vertex id the mesh does not have.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: correspondence file not found") from None
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise InputError(f"{path}: not a readable JSON file ({error.__class__.__name__}: {error})") from None
    try:
        return correspondence_from_dict(data, vertices, faces, n_landmarks=n_landmarks)
    except (InputError, RigError) as error:
        raise type(error)(f"{path}: {error}") from None


def correspondence_from_dict(data, vertices: np.ndarray, faces: np.ndarray, *,
                             n_landmarks: int | None = None) -> Correspondence:
    """The :func:`read_correspondence` parser, on already-decoded JSON."""
    vertices = np.asarray(vertices, dtype=float)
    entries, declared = _entries(data)
    n = n_landmarks if n_landmarks is not None else declared
    landmarks, triangles, weights, points, at = [], [], [], [], []
    for key, value in entries.items():
        landmark = _landmark_index(key)
        tri, w = _parse_entry(landmark, value, len(vertices))
        landmarks.append(landmark)
        triangles.append(tri)
        weights.append(w)
        if tri is None:
            points.append(w)
            at.append(len(landmarks) - 1)
    if points:
        snapped_tri, snapped_w = snap_to_surface(np.array(points), vertices, faces)
        for i, tri, w in zip(at, snapped_tri, snapped_w):
            triangles[i], weights[i] = tri, w
    if not landmarks:
        raise InputError("the correspondence names no landmarks")
    n = int(n) if n is not None else max(landmarks) + 1
    rest = data.get("rest_scores") if isinstance(data, dict) else None
    numbers = isinstance(rest, dict) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                             for v in rest.values())
    if rest is not None and not numbers:
        raise InputError("\"rest_scores\" must map score names to numbers")
    return Correspondence(landmarks, np.array(triangles), np.array(weights), n,
                          rest_scores=rest).check(len(vertices))


def _entries(data) -> tuple[dict, int | None]:
    if isinstance(data, list):
        return dict(enumerate(data)), None
    if not isinstance(data, dict):
        raise InputError(f"expected a JSON object or list; got {type(data).__name__}")
    if "landmarks" in data:
        entries = data["landmarks"]
        entries = dict(enumerate(entries)) if isinstance(entries, list) else entries
        if not isinstance(entries, dict):
            raise InputError('"landmarks" must be an object {landmark: vertex id, point or barycentric}')
        return entries, data.get("n_landmarks")
    return data, None


def _landmark_index(key) -> int:
    try:
        index = int(key)
    except (TypeError, ValueError):
        raise InputError(f"landmark keys must be integers (landmark indices); got {key!r}") from None
    if index < 0:
        raise InputError(f"landmark indices must be >= 0; got {index}")
    return index


def _parse_entry(landmark: int, value, n_vertices: int):
    """``(triangle (3,) int, weights (3,))`` or ``(None, point (3,))`` for a point to snap."""
    if isinstance(value, bool):
        raise InputError(f"landmark {landmark}: expected a vertex id, [x, y, z] or "
                         f"{{\"vertices\", \"weights\"}}; got {value!r}")
    if isinstance(value, int):
        if not 0 <= value < n_vertices:
            raise RigError(f"landmark {landmark}: vertex {value} is not in the mesh (0..{n_vertices - 1})")
        return np.array([value] * 3), np.array([1.0, 0.0, 0.0])
    if isinstance(value, list) and len(value) == 3 and all(isinstance(v, (int, float)) for v in value):
        point = np.array(value, dtype=float)
        if not np.isfinite(point).all():
            raise InputError(f"landmark {landmark}: point must be finite; got {value!r}")
        return None, point
    if isinstance(value, dict):
        return _parse_barycentric(landmark, value, n_vertices)
    raise InputError(f"landmark {landmark}: expected a vertex id, [x, y, z] or "
                     f"{{\"vertices\": [a, b, c], \"weights\": [u, v, w]}}; got {value!r}")


def _parse_barycentric(landmark: int, value: dict, n_vertices: int):
    try:
        tri = np.array(value["vertices"], dtype=np.int64).reshape(3)
        w = np.array(value["weights"], dtype=float).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise InputError(f"landmark {landmark}: a barycentric point needs \"vertices\" (3 ids) and "
                         f"\"weights\" (3 numbers); got {value!r}") from None
    if (tri < 0).any() or (tri >= n_vertices).any():
        raise RigError(f"landmark {landmark}: vertices {tri.tolist()} not all in the mesh (0..{n_vertices - 1})")
    if (w < 0).any() or w.sum() <= 0:
        raise InputError(f"landmark {landmark}: weights must be >= 0 and not all 0; got {w.tolist()}")
    return tri, w / w.sum()
