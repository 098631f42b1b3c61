"""Finding MediaPipe's landmarks on a character: render its neutral from the front, track the render.

The implementation behind :func:`keyshape.correspond.find_correspondence`.
"""

from __future__ import annotations

import numpy as np

from .correspond import Correspondence, mesh_components
from .exceptions import RigError

__all__ = ["find_on_render"]


def find_on_render(vertices: np.ndarray, faces: np.ndarray, *, size: int, backend: str) -> Correspondence:
    """See :func:`keyshape.correspond.find_correspondence`."""
    from .render import frame_points

    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    camera = frame_points(vertices, margin=1.05)
    picture = _render(vertices, faces, camera, size, backend)
    found = _detect(picture)
    if found is None:
        raise RigError("MediaPipe found no face on a front render of the character (is it a human-like "
                       "head facing +Z?): give the correspondence as a JSON file")
    camera = _face_camera(vertices, camera, found, size)
    closer = _detect(_render(vertices, faces, camera, size, backend))
    landmarks = closer if closer is not None else found
    camera = camera if closer is not None else frame_points(vertices, margin=1.05)
    return _surface_points(landmarks[:, :2], vertices, faces, camera, size)


def _render(vertices, faces, camera, size: int, backend: str) -> np.ndarray:
    from .render import make_renderer

    with make_renderer(faces, size, size, n_vertices=len(vertices), backend=backend) as renderer:
        return renderer.render(vertices, camera)


def _detect(picture: np.ndarray) -> np.ndarray | None:
    """MediaPipe's landmarks ``(478, 3)`` in pixels on one picture, or None (a fresh landmarker each time)."""
    from .capture.mediapipe import MediaPipeTracker

    with MediaPipeTracker() as tracker:
        faces = tracker.detect(picture, 0)
    return faces[0].points if faces else None


def _face_camera(vertices, camera, landmarks: np.ndarray, size: int):
    """A front camera framed on the vertices under the detected face's box (enlarged by 40 %)."""
    from .render import frame_points

    screen, _ = camera.to_screen(vertices, size, size)
    low, high = landmarks[:, :2].min(axis=0), landmarks[:, :2].max(axis=0)
    centre, half = (low + high) / 2, (high - low).max() * 0.7
    inside = (np.abs(screen[:, :2] - centre) <= half).all(axis=1)
    if inside.sum() < 10:
        return camera
    box = vertices[inside]
    depth = vertices[:, 2]
    box = np.vstack([box, [[box[0, 0], box[0, 1], depth.min()], [box[0, 0], box[0, 1], depth.max()]]])
    return frame_points(box, margin=1.0)


def _surface_points(pixels: np.ndarray, vertices, faces, camera, size: int) -> Correspondence:
    """Barycentric surface points under ``pixels (478, 2)``.

    A pixel whose visible triangle is on a small part, or is seen from behind (the inside of
    the head through an open mouth), takes the nearest visible front-facing vertex instead.
    """
    from .render.raster import rasterize

    screen, in_front = camera.to_screen(vertices, size, size)
    face_id = rasterize(screen, faces, size, size, in_front=in_front)
    usable = _large_parts(vertices, faces)[faces[:, 0]] & _front_facing(vertices, faces, face_id)
    column = np.clip(np.floor(pixels[:, 0]).astype(int), 0, size - 1)
    row = np.clip(np.floor(pixels[:, 1]).astype(int), 0, size - 1)
    hit = face_id[row, column]
    triangles = np.zeros((len(pixels), 3), dtype=np.int64)
    weights = np.zeros((len(pixels), 3))
    ok = (hit >= 0) & usable[np.maximum(hit, 0)]
    for i in np.flatnonzero(ok):
        triangles[i] = faces[hit[i]]
        weights[i] = _screen_barycentric(pixels[i], screen[faces[hit[i]], :2])
    seen = np.unique(face_id[face_id >= 0])
    pool = np.unique(faces[seen[usable[seen]]].ravel())
    for i in np.flatnonzero(~ok):
        nearest = pool[np.argmin(((screen[pool, :2] - pixels[i]) ** 2).sum(axis=1))]
        triangles[i], weights[i] = nearest, (1.0, 0.0, 0.0)
    return Correspondence(np.arange(len(pixels)), triangles, weights, len(pixels))


def _front_facing(vertices: np.ndarray, faces: np.ndarray, face_id: np.ndarray) -> np.ndarray:
    """(n_faces,) bool: False for triangles clearly seen from behind (unit normal's z < −0.5).

    The front camera looks down −Z, so the inside of the back of the head, seen through an open
    mouth, has normals pointing away from it; grazing triangles (a lid curling under) are kept.
    Normals follow the winding, flipped if most visible triangles face away (a mesh wound the
    other way round).
    """
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    length = np.linalg.norm(normal, axis=1)
    facing = normal[:, 2] / np.where(length > 0, length, 1.0)
    visible = face_id[face_id >= 0]
    if len(visible) and (facing[visible] > 0).mean() < 0.5:
        facing = -facing
    return facing > -0.5


def _large_parts(vertices, faces) -> np.ndarray:
    """(n_vertices,) bool: vertices of components with at least 10 % of the largest one's vertices."""
    label = mesh_components(vertices, faces)
    counts = np.bincount(label)
    return counts[label] >= 0.1 * counts.max()


def _screen_barycentric(pixel: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (3,) of a 2D point in a 2D triangle, clipped into it."""
    a, b, c = corners
    matrix = np.array([b - a, c - a]).T
    try:
        v, w = np.linalg.solve(matrix, pixel - a)
    except np.linalg.LinAlgError:
        return np.array([1.0, 0.0, 0.0])
    bary = np.clip([1 - v - w, v, w], 0, None)
    return bary / bary.sum() if bary.sum() > 0 else np.array([1.0, 0.0, 0.0])
