"""The stylised head's parts beyond the skin: eyes, mouth interior, colours, and what moves them.

* **Eyes** (:func:`eyeball`): a sphere whose rings sit at the pupil's and the iris's edges, so
  the per-vertex colours draw a crisp black pupil in a blue iris on a white sclera. The gaze
  turns each eye about its centre through eight morph targets named as ARKit's
  (``eyeLookInLeft`` ... ``eyeLookDownRight``), each a rotation of ``GAZE_DEGREES``
  (:func:`gaze_deltas`); :func:`gaze_weights` turns the tracker's yaw and pitch into them.
* **Mouth interior** (:func:`mouth_parts`): a dark cavity behind the lips (its triangles face
  inward), a row of upper teeth, a row of lower teeth and a
  tongue. At rest the closed lips hide them; the lower teeth, the tongue and the cavity's floor
  follow the jaw (:func:`jaw_deltas`: the rigid motion, Umeyama 1991, of the chin and lower-lip
  landmarks), the upper teeth and the cavity's roof the upper lip.
* **Colours** (:func:`skin_colours`): skin, lips inside MediaPipe's outer lip contour, brows
  along its brow contours, hair over the cranium, a blush on the cheeks; smoothed over the mesh.

Everything is left-right symmetric about ``x = 0``, so :func:`keyshape.mesh.mirror_map` pairs
the vertices of the whole head.

References
----------
.. [1] S. Umeyama, "Least-squares estimation of transformation parameters between two point
   patterns", IEEE TPAMI 13(4), 1991.
.. [2] Apple ARKit, ``ARFaceAnchor.BlendShapeLocation`` (the ``eyeLook*`` names).
"""

from __future__ import annotations

import numpy as np

from ..alignment import procrustes

__all__ = ["GAZE_DEGREES", "GAZE_NAMES", "JAW_LANDMARKS", "UPPER_LANDMARKS", "eyeball", "gaze_deltas", "gaze_weights",
           "jaw_deltas", "mouth_parts",
           "skin_colours"]

SKIN = (0.95, 0.74, 0.60)
LIPS = (0.80, 0.36, 0.38)
BROW = (0.30, 0.19, 0.13)
HAIR = (0.33, 0.20, 0.13)
BLUSH = (0.93, 0.56, 0.52)
SCLERA = (0.97, 0.97, 0.95)
IRIS = (0.24, 0.52, 0.80)
IRIS_RIM = (0.10, 0.24, 0.42)
PUPIL = (0.03, 0.03, 0.04)
TEETH = (0.97, 0.96, 0.90)
TONGUE = (0.80, 0.34, 0.38)
CAVITY = (0.28, 0.06, 0.08)

GAZE_DEGREES = 30.0
# per eye (Left = the character's left, +x): in (toward x = 0), out, up, down
GAZE_NAMES = tuple(f"eyeLook{d}{side}" for side in ("Left", "Right") for d in ("In", "Out", "Up", "Down"))

# landmarks that move with the jaw: the lower lip (inner and outer) and the chin, not the corners
JAW_LANDMARKS = (14, 87, 178, 88, 95, 317, 402, 318, 324, 17, 84, 181, 91, 146, 314, 405, 321, 375,
                 152, 148, 176, 377, 400, 199, 175, 200, 18)
# landmarks the upper teeth and the cavity's roof follow: the upper lip (inner and outer) and the
# philtrum, not the corners (a key that moves the whole mouth back must take the upper teeth along,
# or they poke through the lips)
UPPER_LANDMARKS = (13, 82, 81, 80, 312, 311, 310, 0, 37, 39, 40, 267, 269, 270, 164)

_PUPIL_DEG, _IRIS_DEG = 9.5, 23.0
_EYE_RINGS = (3.0, 6.0, 8.5, 10.0, 12.5, 16.0, 19.5, 21.5, 23.0, 24.0, 27.0, 33.0, 42.0, 55.0, 70.0, 90.0,
              110.0, 130.0, 150.0, 168.0)


# --------------------------------------------------------------------------- eyes


def eyeball(centre: np.ndarray, radius: float, *, n_lon: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A sphere facing +z with a slightly raised cornea: vertices ``(n, 3)``, faces ``(m, 3)``, colours ``(n, 3)``."""
    theta = np.radians(np.array(_EYE_RINGS))[:, None]
    phi = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)[None, :]
    unit = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta) + 0 * phi], -1)
    unit = np.vstack([[0.0, 0.0, 1.0], unit.reshape(-1, 3), [0.0, 0.0, -1.0]])
    angle = np.degrees(np.arccos(np.clip(unit[:, 2], -1, 1)))
    bulge = 1.0 + 0.05 * np.clip(1 - angle / (_IRIS_DEG + 1), 0, 1) ** 0.5
    points = centre + radius * bulge[:, None] * unit
    faces = _sphere_faces(len(_EYE_RINGS), n_lon)
    return points, _outward(points, faces, centre), _eye_colours(angle)


def _eye_colours(angle: np.ndarray) -> np.ndarray:
    rim = np.clip((angle - 16.0) / (_IRIS_DEG - 16.0), 0, 1)[:, None]
    iris = (1 - rim) * np.array(IRIS) + rim * np.array(IRIS_RIM)
    return np.where((angle < _PUPIL_DEG)[:, None], PUPIL, np.where((angle <= _IRIS_DEG)[:, None], iris, SCLERA))


def gaze_deltas(vertices: np.ndarray, eyes: tuple, centres: np.ndarray) -> np.ndarray:
    """Morph targets ``(8, n_vertices, 3)`` (:data:`GAZE_NAMES`): each eye turned by ``GAZE_DEGREES``.

    ``eyes``: the (left, right) eyeballs' vertex ids; ``centres (2, 3)``: their centres.
    """
    out = np.zeros((len(GAZE_NAMES), *vertices.shape))
    angle = np.radians(GAZE_DEGREES)
    for side, (ids, centre) in enumerate(zip(eyes, centres)):
        inward = -np.sign(centre[0])  # looking in is toward x = 0: -x for the left eye (at +x)
        turns = [_about_y(inward * angle), _about_y(-inward * angle), _about_x(-angle), _about_x(angle)]
        local = vertices[ids] - centre
        for j, rotation in enumerate(turns):
            out[4 * side + j, ids] = local @ rotation.T - local
    return out


def gaze_weights(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Weights ``(n_frames, 8)`` of :data:`GAZE_NAMES` from gaze angles in degrees.

    ``yaw, pitch (n_frames, 2)``, columns (right eye, left eye) as :class:`keyshape.capture.Gaze`:
    yaw > 0 toward the actor's left (the character's +x), pitch > 0 up. NaN gives 0.
    """
    yaw, pitch = np.nan_to_num(np.asarray(yaw, float)), np.nan_to_num(np.asarray(pitch, float))
    out = np.zeros((len(yaw), len(GAZE_NAMES)))
    for side, column in enumerate((1, 0)):  # GAZE_NAMES: left eye first
        toward_plus_x = yaw[:, column] / GAZE_DEGREES
        inward = -toward_plus_x if side == 0 else toward_plus_x  # the left eye sits at +x
        up = pitch[:, column] / GAZE_DEGREES
        out[:, 4 * side:4 * side + 4] = np.stack([inward, -inward, up, -up], axis=1)
    return np.clip(out, 0.0, 1.0)


def _about_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _about_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


# --------------------------------------------------------------------------- the mouth interior


def mouth_parts(inner_lip: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``{name: (vertices, faces, colours)}`` of the cavity, the teeth rows and the tongue.

    ``inner_lip (n, 3)``: the inner lip contour of the closed neutral mouth (metres).
    """
    order = np.argsort(inner_lip[:, 0])
    xs, zs = inner_lip[order, 0], inner_lip[order, 2]
    mid_y = float(inner_lip[np.abs(inner_lip[:, 0]) < 0.004, 1].mean())
    front = float(zs.max())
    half_width = float(xs.max())

    def arc_z(x):
        return np.interp(x, xs, zs) - 0.0045

    cavity = _ellipsoid(np.array([0.0, mid_y - 0.004, front - 0.022]), (0.9 * half_width, 0.017, 0.02),
                        CAVITY, inward=True)
    # (flattening the cavity's front behind the teeth shows them whole with the jaw open, but also
    # at rest through the lips' gap, which moved MediaPipe's lips on the front render: not done)
    parts = {
        "cavity": cavity,
        "upper_teeth": _teeth(arc_z, 0.62 * half_width, mid_y - 0.0015, mid_y + 0.0075, 0.0),
        "lower_teeth": _teeth(arc_z, 0.56 * half_width, mid_y - 0.0085, mid_y - 0.0022, -_LOWER_BACK),
        "tongue": _ellipsoid(np.array([0.0, mid_y - 0.0085, front - 0.019]), (0.5 * half_width, 0.0045, 0.013),
                             TONGUE),
    }
    return parts


_TOOTH_DEPTH = 0.0028  # front to back of a tooth (m)
_LOWER_BACK = 0.0016  # the lower row sits this far behind the upper


def _teeth(arc_z, half_width: float, bottom: float, top: float, back: float, *, n: int = 8):
    """A row of ``n`` box teeth along the lip arc ``z = arc_z(x)``, between heights bottom and top."""
    edges = np.linspace(-half_width, half_width, n + 1)
    vertices, faces = [], []
    for i in range(n):
        x0, x1 = edges[i] + 0.00025, edges[i + 1] - 0.00025
        z0, z1 = arc_z(x0) + back, arc_z(x1) + back
        tangent = np.array([x1 - x0, 0.0, z1 - z0])
        normal = np.cross([0.0, 1.0, 0.0], tangent / np.linalg.norm(tangent)) * _TOOTH_DEPTH  # backward
        front = np.array([[x0, 0, z0], [x1, 0, z1]])
        corners = np.array([p + [0, y, 0] + d for d in (np.zeros(3), normal) for p in front for y in (bottom, top)])
        faces.append(_BOX + 8 * i)
        vertices.append(corners)
    vertices = np.vstack(vertices)
    faces = np.vstack(faces)
    centre = vertices.reshape(n, 8, 3).mean(axis=1).repeat(12, axis=0)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    inward = (np.cross(b - a, c - a) * ((a + b + c) / 3 - centre)).sum(axis=1) < 0
    faces = np.where(inward[:, None], faces[:, [0, 2, 1]], faces)
    return vertices, faces, np.tile(TEETH, (len(vertices), 1))


# corners: (front/back) x (left/right) x (bottom/top) -> index 4 d + 2 p + y
_BOX = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                 [1, 5, 7], [1, 7, 3], [0, 2, 6], [0, 6, 4]])


def _ellipsoid(centre: np.ndarray, axes, colour, *, inward: bool = False, n_lat: int = 12, n_lon: int = 24):
    theta = np.linspace(0, np.pi, n_lat + 1)[1:-1, None]
    phi = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)[None, :]
    unit = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta) + 0 * phi], -1)
    unit = np.vstack([[0.0, 0.0, 1.0], unit.reshape(-1, 3), [0.0, 0.0, -1.0]])
    points = centre + unit * np.asarray(axes)
    faces = _outward(points, _sphere_faces(n_lat - 1, n_lon), centre)
    return points, faces[:, [0, 2, 1]] if inward else faces, np.tile(colour, (len(points), 1))


def _sphere_faces(n_rings: int, n_lon: int) -> np.ndarray:
    """Triangles of a pole, ``n_rings`` rings of ``n_lon`` points, and a pole (vertex order as built)."""

    def ring(i):
        return 1 + i * n_lon + np.arange(n_lon)

    faces = [np.stack([np.zeros(n_lon, int), ring(0), np.roll(ring(0), -1)], axis=1)]
    for i in range(n_rings - 1):
        a, b = ring(i), ring(i + 1)
        faces += [np.stack([a, b, np.roll(a, -1)], axis=1), np.stack([np.roll(a, -1), b, np.roll(b, -1)], axis=1)]
    last, bottom = ring(n_rings - 1), 1 + n_rings * n_lon
    faces.append(np.stack([last, np.full(n_lon, bottom), np.roll(last, -1)], axis=1))
    return np.vstack(faces)


def _outward(points: np.ndarray, faces: np.ndarray, centre: np.ndarray) -> np.ndarray:
    a, b, c = (points[faces[:, i]] for i in range(3))
    inward = (np.cross(b - a, c - a) * ((a + b + c) / 3 - centre)).sum(axis=1) < 0
    return np.where(inward[:, None], faces[:, [0, 2, 1]], faces)


def jaw_deltas(vertices: np.ndarray, landmark_deltas: np.ndarray, landmark_points: np.ndarray,
               weights: np.ndarray) -> np.ndarray:
    """Deltas ``(n_keys, n_part, 3)`` of part vertices that follow the jaw, each by ``weights (n_part,)``.

    The jaw's motion per key is the rigid motion (Umeyama, no scale) taking ``landmark_points
    (n_jaw, 3)`` to ``landmark_points + landmark_deltas (n_keys, n_jaw, 3)``.
    """
    moved = landmark_points[None] + landmark_deltas
    poses = procrustes(np.broadcast_to(landmark_points, moved.shape), moved, scale=False)
    # k: key, i/j: axis, v: vertex — p' = R p + t
    rigid = np.einsum("kij,vj->kvi", poses.rotations, vertices) + poses.translations[:, None]
    return weights[None, :, None] * (rigid - vertices[None])


# --------------------------------------------------------------------------- colours


def skin_colours(vertices: np.ndarray, faces: np.ndarray, landmarks: np.ndarray, contours: dict) -> np.ndarray:
    """Colours ``(n_vertices, 3)`` of the skin mesh; ``landmarks (468, 3)`` on it, ``contours`` MediaPipe's."""
    colour = np.tile(np.array(SKIN), (len(vertices), 1))
    front = vertices[:, 2] > landmarks[:, 2].min()
    lips = _inside(vertices[:, :2], landmarks[_outer_lip(contours, landmarks), :2]) & front
    lips &= vertices[:, 2] > landmarks[[61, 291], 2].min() - 0.004
    colour = _mix(colour, LIPS, lips.astype(float))
    for side in ("left", "right"):
        cheek = landmarks[[205 if side == "right" else 425]][0] + [0, 0.004, 0]
        colour = _mix(colour, BLUSH, 0.45 * np.exp(-((vertices - cheek) ** 2).sum(axis=1) / (2 * 0.011**2)))
        edges = np.asarray(contours[f"{side}_eyebrow_edges"])
        t = np.linspace(0, 1, 9)[None, :, None]
        brow = (landmarks[edges[:, 0]][:, None] * (1 - t) + landmarks[edges[:, 1]][:, None] * t).reshape(-1, 3)
        near = np.linalg.norm(vertices[:, None] - brow[None], axis=2).min(axis=1)
        colour = _mix(colour, BROW, np.clip((0.0055 - near) / 0.002, 0, 1) * front)
    direction = vertices - [0.0, 0.012, -0.045]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    hair = np.clip((direction[:, 1] + 0.6 * np.maximum(-direction[:, 2], 0) - 0.45 * np.maximum(direction[:, 2], 0)
                    - 0.2) / 0.04, 0, 1)
    colour = _mix(colour, HAIR, hair)
    return _smooth(colour, faces, len(vertices), steps=2)


def _outer_lip(contours: dict, landmarks: np.ndarray) -> list[int]:
    """The outer lip contour, ordered by angle about the mouth centre."""
    ids = np.array(sorted(set(contours["lips"])))
    centre = landmarks[ids, :2].mean(axis=0)
    radius = np.linalg.norm(landmarks[ids, :2] - centre, axis=1)
    angle = np.arctan2(*(landmarks[ids, :2] - centre).T[::-1])
    outer = []  # per angle sector, the point furthest out
    for sector in np.array_split(np.argsort(angle), 20):
        outer.append(ids[sector[np.argmax(radius[sector])]])
    return outer


def _inside(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd rule: which ``points (n, 2)`` lie inside ``polygon (m, 2)``."""
    x, y = points[:, 0:1], points[:, 1:2]
    a, b = polygon, np.roll(polygon, -1, axis=0)
    crosses = (a[:, 1] > y) != (b[:, 1] > y)
    t = (y - a[:, 1]) / np.where(b[:, 1] != a[:, 1], b[:, 1] - a[:, 1], 1.0)
    at = a[:, 0] + t * (b[:, 0] - a[:, 0])
    return (crosses & (x < at)).sum(axis=1) % 2 == 1


def _mix(colour: np.ndarray, other, amount: np.ndarray) -> np.ndarray:
    amount = np.asarray(amount, float)[:, None]
    return (1 - amount) * colour + amount * np.asarray(other)


def _smooth(colour: np.ndarray, faces: np.ndarray, n: int, *, steps: int) -> np.ndarray:
    from scipy import sparse

    pairs = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    adjacency = sparse.csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    adjacency = ((adjacency + adjacency.T) > 0).astype(float) + sparse.identity(n)
    average = sparse.diags(1.0 / np.asarray(adjacency.sum(axis=1)).ravel()) @ adjacency
    for _ in range(steps):
        colour = average @ colour
    return colour
