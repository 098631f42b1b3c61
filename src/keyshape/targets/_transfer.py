"""Expression transfer: carry each key shape's landmark motion onto a character's mesh.

For every key shape, the character's neutral is moved by the key's landmark displacements,
brought into the character's space and proportions, and spread smoothly over the surface::

    key deltas (n_keys, n_landmarks, d), image axes
      ──similarity (Umeyama) + per-feature scale──▶ motion at corresponded points (n_keys, n_corr, 3)
      ──biharmonic spread with geodesic falloff──▶ target deltas (n_keys, n_vertices, 3)

1. **Into the character's space** (:func:`landmark_motion`): image axes become glTF axes
   (x, −y, −z); one similarity (Umeyama 1991) maps the actor's neutral landmarks onto the
   character's corresponding points; then each facial feature (each eye, the brows, the mouth)
   rescales its motion by the ratio of its extent on the character to its extent on the actor,
   per axis where the feature has a height of its own. A character with eyes twice as tall
   blinks twice as far, so its lids still meet (Noh & Neumann 2001 adjust motion vectors to the
   target's local proportions in the same spirit).
2. **Over the surface** (:func:`spread`): the displacement field ``x`` minimises the discrete
   thin-plate (biharmonic) energy on the mesh, with the landmark motions as soft point
   constraints and a stiffness that grows with geodesic distance from the moving landmarks::

       E(x) = xᵀ C M⁻¹ C x  +  xᵀ M diag(α(g)) x  +  w Σ_c κ_c |B_c x − δ_c|²

   ``C`` is the cotangent Laplacian and ``M`` the lumped mass matrix (Pinkall & Polthier 1993;
   Botsch & Sorkine 2008), ``g`` the geodesic distance (Dijkstra on mesh edges) to the nearest
   moving landmark, ``α`` zero near the face features and rising smoothly to a pin beyond the
   falloff radius, ``B`` the barycentric rows of the correspondence and ``κ`` each landmark's
   confidence (low on silhouettes such as the jaw line, whose landmarks slide with the head). Geodesic rather than
   Euclidean distance keeps the lips and eyelids apart: across a mouth or eye opening they are
   far apart on the surface. The landmarks of every *other* region are held still, so a key of
   the upper face does not move the mouth; landmarks in no region are left free.
3. **Rigid parts**: mesh components with no corresponded landmark (eyeballs, teeth, a mouth
   bag) do not move; vertex sets the user lists as ``rigid`` move by the rigid motion (Umeyama,
   no scale) that best follows the field around them.

References
----------
.. [1] J. Noh and U. Neumann, "Expression cloning", SIGGRAPH 2001.
.. [2] M. Botsch and O. Sorkine, "On linear variational surface deformation methods",
   IEEE TVCG 14(1), 2008.
.. [3] U. Pinkall and K. Polthier, "Computing discrete minimal surfaces and their
   conjugates", Experimental Mathematics 2(1), 1993.
.. [4] S. Umeyama, "Least-squares estimation of transformation parameters between two
   point patterns", IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from ..alignment import procrustes
from ..containers import KeyShapes
from ..exceptions import DegenerateFrameWarning, InputError, RigError
from ..mesh import NormalEstimator, weld_vertices
from ..schemes import as_xyz, points_to_gltf, resolve_regions, stable_points
from ._correspond import Correspondence

__all__ = ["LandmarkMotion", "feature_groups", "landmark_motion", "spread", "transfer_expressions"]

_SCALE_LIMITS = (1 / 3, 3.0)


@dataclass(frozen=True, eq=False)
class LandmarkMotion:
    """The key shapes' landmark motion, in the character's space and proportions.

    Attributes
    ----------
    deltas : (n_keys, n_corr, 3) float
        Displacement of each corresponded point per key (z = 0 for 2D key shapes).
    constrained : (n_corr,) bool
        Points whose motion is known for every key: landmarks of some region (zero outside
        the key's own region) and stable landmarks; the others are free.
    moving : (n_corr,) bool
        Points that move in at least one key.
    confidence : (n_corr,) float in (0, 1]
        How far each point's motion is trusted: low where the character's surface turns away
        from the actor's camera (the jaw line and face outline are silhouettes in the video,
        whose landmarks slide with the head rather than with the skin).
    n_dims : int
        2 or 3: the key shapes' dimension (2D keys say nothing about depth).
    scale : float
        The similarity's scale (character units per key-shape unit).
    feature_scales : dict str -> (3,) float
        Per-feature, per-axis rescaling applied on top of the similarity.
    """

    deltas: np.ndarray
    constrained: np.ndarray
    moving: np.ndarray
    confidence: np.ndarray
    n_dims: int
    scale: float
    feature_scales: dict


def landmark_motion(keys: KeyShapes, correspondence: Correspondence, vertices: np.ndarray,
                    faces: np.ndarray | None = None, *, rescale: bool = True) -> LandmarkMotion:
    """Bring the key deltas onto the character's corresponding points.

    Parameters
    ----------
    keys : KeyShapes
        ``neutral (n_landmarks, d)`` and ``deltas (n_keys, n_landmarks, d)`` in image axes
        (x right, y down, z away from the camera), d in {2, 3}.
    correspondence : Correspondence
        At least 3 landmarks with a point on the character.
    vertices : (n_vertices, 3) float
        The character's neutral, glTF axes (+Y up, facing +Z for 2D keys; any orientation for
        3D keys, which are turned onto it).
    faces : (n_faces, 3) int, optional
        Its triangles, for the surface normals behind ``confidence`` (all 1 without them).
    rescale : bool, keyword-only
        Rescale each feature to the character's proportions (see the module docstring).

    Returns
    -------
    LandmarkMotion

    Raises
    ------
    RigError
        Too few correspondences, or a degenerate similarity.
    """
    vertices = np.asarray(vertices, dtype=float)
    correspondence.check(len(vertices), keys.n_landmarks)
    if correspondence.n_corr < 3:
        raise RigError(f"expression transfer needs at least 3 corresponded landmarks; got {correspondence.n_corr}")
    points = correspondence.points(vertices)
    index = correspondence.landmarks
    source = points_to_gltf(keys.neutral[index])
    deltas = points_to_gltf(keys.deltas[:, index])
    scale, rotation, placed = _similarity(source, points)
    # k: key, c: point, i/j: dimension
    moved = scale * np.einsum("ij,kcj->kci", rotation, deltas)
    moved = as_xyz(moved)
    features = {}
    if rescale:
        moved, features = _rescale_features(moved, placed, points, index, keys.n_landmarks)
    constrained = np.isin(index, _constrained_landmarks(keys))
    moving = np.abs(moved).max(axis=(0, 2), initial=0) > 0
    toward_camera = rotation[:, 2] if keys.n_dims == 3 else np.array([0.0, 0.0, 1.0])
    confidence = _facing(vertices, faces, correspondence, toward_camera)
    return LandmarkMotion(moved, constrained, moving, confidence, keys.n_dims, scale, features)


def _facing(vertices, faces, correspondence: Correspondence, toward_camera: np.ndarray) -> np.ndarray:
    """(n_corr,) confidence from ``|n · v|``: 1 facing the camera (≥ 0.7), down to 0.1 edge-on (≤ 0.25)."""
    if faces is None:
        return np.ones(correspondence.n_corr)
    normals = correspondence.points(NormalEstimator(faces, len(vertices))(vertices))
    length = np.linalg.norm(normals, axis=1)
    cosine = np.abs(normals @ toward_camera) / np.where(length > 0, length, 1.0)
    return np.clip((cosine - 0.25) / 0.45, 0.1, 1.0)


def _similarity(source: np.ndarray, target: np.ndarray):
    """Scale, rotation ``(d, d)`` and the placed source ``(n, 3)`` of the best similarity source→target.

    2D sources fit the target's (x, y) only: 2D key shapes are seen from the front.
    """
    d = source.shape[1]
    finite = np.isfinite(source).all(axis=1)
    with warnings.catch_warnings():  # a degenerate fit is reported below, as an error
        warnings.simplefilter("ignore", DegenerateFrameWarning)
        pose = procrustes(source[finite], target[finite, :d])
    scale, rotation, shift = float(pose.scales[0]), pose.rotations[0], pose.translations[0]
    if not np.isfinite(scale) or scale <= 0:
        raise RigError("the corresponded landmarks are degenerate (collinear or coincident): "
                       "correspond more, and more spread-out, landmarks")
    placed = scale * source @ rotation.T + shift
    if d == 2:
        placed = np.concatenate([placed, target[:, 2:3]], axis=1)
    return scale, rotation, placed


def _constrained_landmarks(keys: KeyShapes) -> np.ndarray:
    regions = np.concatenate([np.asarray(ix) for ix in keys.regions.values()])
    stable = keys.stable if keys.stable is not None else stable_points(keys.n_landmarks)
    if len(stable) == keys.n_landmarks:  # an unknown scheme: "stable" means every point
        stable = np.zeros(0, dtype=int)
    return np.union1d(regions, stable)


def feature_groups(n_landmarks: int) -> dict[str, np.ndarray]:
    """Facial features whose proportions are matched separately: each eye, the brows, the mouth.

    Empty for landmark schemes without known features.
    """
    if n_landmarks not in (68, 468, 478):
        return {}
    return resolve_regions("eyes", n_landmarks)


def _rescale_features(moved, placed, points, index, n_landmarks):
    """Scale each feature's motion ``(n_keys, n_corr, 3)`` by its extent ratio character / actor."""
    moved = moved.copy()
    scales, done = {}, np.zeros(len(index), dtype=bool)
    for name, members in feature_groups(n_landmarks).items():
        rows = np.flatnonzero(np.isin(index, members) & ~done)
        if len(rows) < 3:
            continue
        ratio = _extent_ratio(placed[rows], points[rows])
        moved[:, rows] *= ratio
        done[rows] = True
        scales[name] = ratio
    return moved, scales


def _extent_ratio(actor: np.ndarray, character: np.ndarray) -> np.ndarray:
    """(3,) per-axis ratio of spreads; y follows x for flat features, z is their geometric mean."""
    spread_a, spread_c = actor[:, :2].std(axis=0), character[:, :2].std(axis=0)
    ratio_x = spread_c[0] / spread_a[0] if spread_a[0] > 0 else 1.0
    tall = spread_a[1] > 0.15 * spread_a[0] and spread_c[1] > 0.15 * spread_c[0]
    ratio_y = spread_c[1] / spread_a[1] if tall else ratio_x
    ratio = np.clip([ratio_x, ratio_y], *_SCALE_LIMITS)
    return np.array([ratio[0], ratio[1], np.sqrt(ratio[0] * ratio[1])])


# --------------------------------------------------------------------------- spreading over the mesh


def spread(vertices: np.ndarray, faces: np.ndarray, correspondence: Correspondence, motion: LandmarkMotion, *,
           falloff: float = 1.0, rigid: Sequence[np.ndarray] = ()) -> np.ndarray:
    """Displacement fields ``(n_keys, n_vertices, 3)`` that carry ``motion`` over the mesh.

    Parameters
    ----------
    vertices : (n_vertices, 3) float
        The character's neutral.
    faces : (n_faces, 3) int
    correspondence : Correspondence
    motion : LandmarkMotion
        From :func:`landmark_motion` with the same correspondence.
    falloff : float, keyword-only
        Reach of the motion beyond the moving landmarks, in units of the face's radius (the
        RMS distance of the corresponded points from their centroid); the surface is held
        still beyond ``falloff`` radii (geodesic) and eases in from ``falloff / 3``.
    rigid : sequence of (n_part,) int, keyword-only
        Vertex sets that move rigidly (teeth, eyeballs inside the skin mesh).

    Returns
    -------
    (n_keys, n_vertices, 3) float
    """
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    correspondence.check(len(vertices))
    welded, n = weld_vertices(vertices)
    mesh = _Welded.build(vertices, faces, welded, n)
    rows = correspondence.matrix(len(vertices))
    rows = sparse.csr_matrix((rows.data, welded[rows.indices], rows.indptr), shape=(rows.shape[0], n))
    constrained = np.flatnonzero(motion.constrained)
    radius = _face_radius(correspondence.points(vertices))
    sources = np.unique(welded[correspondence.vertices[motion.moving & motion.constrained].ravel()])
    distance = mesh.geodesic(sources) / radius
    field = _solve(mesh, rows[constrained], motion.deltas[:, constrained], motion.confidence[constrained],
                   distance, falloff, radius)
    field = field[:, welded]
    for part in rigid:
        field = _follow_rigidly(field, vertices, np.asarray(part, dtype=np.int64))
    return field


def _face_radius(points: np.ndarray) -> float:
    radius = float(np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean()))
    if not radius > 0:
        raise RigError("the corresponded points coincide: cannot size the face")
    return radius


@dataclass(frozen=True, eq=False)
class _Welded:
    """A welded triangle mesh: positions ``(n, 3)``, faces ``(n_faces, 3)``, edge graph."""

    vertices: np.ndarray
    faces: np.ndarray
    edges: sparse.csr_matrix

    @classmethod
    def build(cls, vertices, faces, welded, n) -> _Welded:
        position = np.zeros((n, 3))
        position[welded] = vertices
        tri = welded[faces]
        tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])]
        pairs = tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        length = np.linalg.norm(position[pairs[:, 0]] - position[pairs[:, 1]], axis=1)
        edges = sparse.csr_matrix((np.maximum(length, 1e-12), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        return cls(position, tri, edges.maximum(edges.T).tocsr())

    def geodesic(self, sources: np.ndarray) -> np.ndarray:
        """(n,) shortest edge-path distance to the nearest source (inf where unreachable)."""
        from scipy.sparse.csgraph import dijkstra

        if len(sources) == 0:
            return np.full(len(self.vertices), np.inf)
        return dijkstra(self.edges, directed=False, indices=sources, min_only=True)

    def laplacian(self) -> tuple[sparse.csr_matrix, np.ndarray]:
        """Cotangent Laplacian ``C (n, n)`` (positive semi-definite) and lumped masses ``(n,)``."""
        v, f = self.vertices, self.faces
        n = len(v)
        cot = np.zeros((len(f), 3))
        for i in range(3):  # cotangent of the angle at corner i, opposite edge (i+1, i+2)
            a, b = v[f[:, (i + 1) % 3]] - v[f[:, i]], v[f[:, (i + 2) % 3]] - v[f[:, i]]
            cross = np.linalg.norm(np.cross(a, b), axis=1)
            cot[:, i] = np.clip((a * b).sum(1) / np.maximum(cross, 1e-12 * (a * a).sum(1) + 1e-30), -50, 50)
        j, k = f[:, [1, 2, 0]].ravel(), f[:, [2, 0, 1]].ravel()
        w = 0.5 * cot.ravel()
        off = sparse.csr_matrix((-w, (j, k)), shape=(n, n))
        off = off + off.T
        lap = off - sparse.diags(np.asarray(off.sum(axis=1)).ravel())
        area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        mass = np.bincount(f.ravel(), weights=np.repeat(area / 3, 3), minlength=n)
        return lap.tocsr(), mass


def _solve(mesh: _Welded, rows: sparse.csr_matrix, deltas: np.ndarray, confidence: np.ndarray,
           distance: np.ndarray, falloff: float, radius: float) -> np.ndarray:
    """Minimise E(x) (module docstring) for every key: ``(n_keys, n, 3)``, zero where pinned."""
    from scipy.sparse.linalg import splu

    n_keys = deltas.shape[0]
    field = np.zeros((n_keys, len(mesh.vertices), 3))
    free = np.flatnonzero(distance < falloff)
    if len(free) == 0 or n_keys == 0:
        return field
    lap, mass = mesh.laplacian()
    mass = np.maximum(mass, 1e-12 * max(mass.max(), 1e-30)) / radius**2  # unit face radius
    stiffness = _falloff_stiffness(distance, falloff)
    energy = lap @ sparse.diags(1.0 / mass) @ lap + sparse.diags(mass * stiffness)
    weight = 1e4 * float(np.median(energy.diagonal()[free]))
    sub = rows[:, free]
    trust = sparse.diags(weight * confidence)  # w c_l per point
    system = (energy[free][:, free] + sub.T @ trust @ sub).tocsc()
    rhs = sub.T @ (trust @ deltas.transpose(1, 0, 2).reshape(rows.shape[0], -1))
    solution = splu(system).solve(np.asarray(rhs))
    field[:, free] = solution.reshape(len(free), n_keys, 3).transpose(1, 0, 2)
    return field


def _falloff_stiffness(distance: np.ndarray, falloff: float) -> np.ndarray:
    """α(g): 0 up to ``falloff / 3`` face radii, then a smoothstep up to a stiff hold at ``falloff``."""
    start = falloff / 3
    t = np.clip((distance - start) / max(falloff - start, 1e-9), 0, 1)
    return 1e3 * t * t * (3 - 2 * t)


def _follow_rigidly(field: np.ndarray, vertices: np.ndarray, part: np.ndarray) -> np.ndarray:
    """Replace the field on ``part`` by the rigid motion that best follows it (per key)."""
    from scipy.spatial import cKDTree

    if len(part) < 3:
        return field
    outside = np.setdiff1d(np.arange(len(vertices)), part)
    moving = outside[np.abs(field[:, outside]).max(axis=(0, 2), initial=0) > 0]
    pool = moving if len(moving) else outside
    _, near = cKDTree(vertices[pool]).query(vertices[part], k=min(8, len(pool)))
    near = pool[np.asarray(near).reshape(len(part), -1)]
    out = field.copy()
    for k in range(field.shape[0]):
        guided = vertices[part] + field[k][near].mean(axis=1)
        pose = procrustes(vertices[part], guided, scale=False)
        out[k, part] = vertices[part] @ pose.rotations[0].T + pose.translations[0] - vertices[part]
    return out


# --------------------------------------------------------------------------- the whole transfer


def transfer_expressions(keys: KeyShapes, vertices: np.ndarray, faces: np.ndarray,
                         correspondence: Correspondence, *, falloff: float = 1.0, rescale: bool = True,
                         rigid: Sequence[np.ndarray] = ()) -> np.ndarray:
    """One target per key shape on the character: deltas ``(n_keys, n_vertices, 3)``.

    :func:`landmark_motion` then :func:`spread` (see the module docstring for the method).

    Parameters
    ----------
    keys : KeyShapes
    vertices : (n_vertices, 3) float
        The character's neutral (glTF axes).
    faces : (n_faces, 3) int
    correspondence : Correspondence
        For ``keys.n_landmarks`` landmarks, on this mesh.
    falloff, rigid
        See :func:`spread`.
    rescale : bool, keyword-only
        See :func:`landmark_motion`.

    Returns
    -------
    (n_keys, n_vertices, 3) float
    """
    vertices = np.asarray(vertices, dtype=float)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError(f"vertices must have shape (n_vertices, 3); got {vertices.shape}")
    correspondence.check(len(vertices), keys.n_landmarks)
    motion = landmark_motion(keys, correspondence, vertices, faces, rescale=rescale)
    return spread(vertices, faces, correspondence, motion, falloff=falloff, rigid=rigid)
