"""Finding MediaPipe's landmarks on a character: render its neutral from the front, track the render.

The third way to a :class:`~keyshape.targets.Correspondence` (see ``_correspond``): automatically.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..defaults import FRONTS
from ..exceptions import InputError, RigError
from ..mesh import mesh_components, snap_to_surface
from ._correspond import Correspondence

__all__ = ["find_correspondence", "view_rotation", "FRONTS"]


# the views "auto" tries, in order: (the axis the face looks along, the axis up the face)
_VIEWS = (("+z", "+y"), ("-y", "+z"), ("+y", "+z"), ("-z", "+y"), ("+x", "+y"), ("-x", "+y"))


class NoFaceFound(RigError):
    """MediaPipe found no face on any front render of the character."""


def find_correspondence(vertices: np.ndarray, faces: np.ndarray, *, size: int = 640,
                        backend: str = "auto", front: str = "auto",
                        colours: np.ndarray | None = None) -> Correspondence:
    """MediaPipe's 478 landmarks on a human-like head, found on a front render of its neutral.

    The mesh is turned so that its front faces the camera, rendered with an orthographic camera,
    MediaPipe's face landmarker runs on the picture, and the picture is rendered again framed on
    the face it found (a second, sharper pass). Each landmark becomes the visible surface point
    under its pixel (barycentric in the visible triangle, so it holds for the mesh as it is, not
    turned); a landmark that falls off the mesh, on a small part (an eyeball, a tooth) or on a
    surface seen from behind (the inside of the head through an open mouth) takes the nearest
    visible vertex instead (the steps below).

    Parameters
    ----------
    vertices : (n_vertices, 3) float
    faces : (n_faces, 3) int
    size : int, keyword-only
        Side of the square renders, pixels.
    backend : "auto", "gl" or "numpy", keyword-only
        Renderer (see :func:`keyshape.render.make_renderer`).
    front : "auto", "+z", "-z", "+x", "-x", "+y" or "-y", keyword-only
        The axis the character's face looks along. "auto" tries +Z (glTF's convention, Y up), then
        −Y and +Y (Z-up exports), −Z, +X and −X, and keeps the first view where MediaPipe finds a
        face.
    colours : (n_vertices, 3) or (n_vertices, 4) float in [0, 1], optional, keyword-only
        What the character looks like (e.g. :func:`keyshape.io.gltf.read_colours`): rendered so, the
        tracker sees lips, brows and eyes as in a face; triangles whose corners are mostly
        see-through (mean alpha below 0.5: eye overlays, lash cards) are left out; default clay.

    Returns
    -------
    Correspondence
        ``n_landmarks = 478``.

    Raises
    ------
    RigError
        If MediaPipe finds no face on any view tried (not a human-like head, or facing elsewhere).
    """
    from ..render import frame_points

    colours, faces = _seen(colours, np.asarray(faces, dtype=np.int64))
    if front not in FRONTS:
        raise InputError(f"front must be one of {', '.join(FRONTS)}; got {front!r}")
    faces = np.asarray(faces, dtype=np.int64)
    views = _VIEWS if front == "auto" else [next(v for v in _VIEWS if v[0] == front)]
    for axis, up in views:
        vertices_turned = np.asarray(vertices, dtype=float) @ view_rotation(axis, up).T
        camera = frame_points(vertices_turned, margin=1.05)
        found, scores = _detect(_render(vertices_turned, faces, camera, size, backend, colours))
        if found is not None:
            break
    else:
        tried = ", ".join(axis.upper() for axis, _ in views)
        raise NoFaceFound(f"MediaPipe found no face on a front render of the character (facing {tried} tried; is it "
                       "a human-like head?): pass --front AXIS (front=...) if its face looks along another "
                       "axis, or give the correspondence as a JSON file (--correspondence)")
    vertices = vertices_turned
    camera = _face_camera(vertices, camera, found, size)
    closer, closer_scores = _detect(_render(vertices, faces, camera, size, backend, colours))
    landmarks = closer if closer is not None else found
    scores = closer_scores if closer is not None else scores
    camera = camera if closer is not None else frame_points(vertices, margin=1.05)
    corr = _surface_points(landmarks[:, :2], vertices, faces, camera, size)
    return dataclasses.replace(corr, rest_scores=scores)


def view_rotation(front: str, up: str) -> np.ndarray:
    """The rotation ``(3, 3)`` that turns axis ``front`` to +Z (toward the camera) and ``up`` to +Y.

    >>> view_rotation("-y", "+z") @ [0, -1, 0]
    array([0., 0., 1.])
    """
    axes = {"x": 0, "y": 1, "z": 2}

    def unit(name):
        vector = np.zeros(3)
        vector[axes[name[1]]] = 1.0 if name[0] == "+" else -1.0
        return vector

    forward, upward = unit(front), unit(up)
    return np.stack([np.cross(upward, forward), upward, forward]) + 0.0  # rows: the new x, y, z


def _seen(colours, faces: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """RGB colours (or None) and the triangles a render shows: none that are mostly see-through."""
    if colours is None:
        return None, faces
    colours = np.asarray(colours, dtype=float)
    if colours.shape[1] == 4:
        faces = faces[colours[faces, 3].mean(axis=1) >= 0.5]
        colours = colours[:, :3]
    return colours, faces


def _render(vertices, faces, camera, size: int, backend: str, colours=None) -> np.ndarray:
    """The render (clay, or the character's ``colours``), with what is seen through the openings
    painted dark, as in a real face.

    The renderer shades every surface alike, so the inside of the head seen through an open mouth
    would look like lip to the tracker.
    """
    from ..render import make_renderer
    from ..render.raster import rasterize

    with make_renderer(faces, size, size, n_vertices=len(vertices), backend=backend, colours=colours) as renderer:
        picture = renderer.render(vertices, camera)
    screen, in_front = camera.to_screen(vertices, size, size)
    deep = _deep_pixels(vertices, faces, rasterize(screen, faces, size, size, in_front=in_front))
    picture = picture.copy()
    picture[deep] = (40, 22, 24)
    return picture


def _detect(picture: np.ndarray) -> tuple[np.ndarray | None, dict | None]:
    """MediaPipe's landmarks ``(478, 3)`` in pixels on one picture and its ARKit scores by name, or
    (None, None) (a fresh landmarker each time)."""
    from ..capture.mediapipe import MediaPipeTracker

    with MediaPipeTracker() as tracker:
        faces = tracker.detect(picture, 0)
        names = tracker.blendshape_names
    if not faces:
        return None, None
    scores = dict(zip(names, np.asarray(faces[0].scores, dtype=float).tolist())) if names else None
    return faces[0].points, scores


def _face_camera(vertices, camera, landmarks: np.ndarray, size: int):
    """A front camera framed on the vertices under the detected face's box (enlarged by 40 %)."""
    from ..render import frame_points

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

    A pixel whose visible triangle is on a small part, or deep behind the surface around it (the
    inside of the head through an open mouth, :func:`_not_deep`), or is off the mesh, or is
    across a gap from its neighbours
    (:func:`_across_a_gap`), moves toward its neighbours in
    MediaPipe's face mesh that were found on the surface, to the first usable triangle on the
    way (:func:`_march`): the lower lip's inner edge, in a mouth slit MediaPipe sees as closed,
    goes down onto the lower lip, and an eyelid landmark over an eyeball out onto its lid. Without
    such neighbours it takes the closest point (on screen) of the usable visible triangles.
    Landmarks that MediaPipe puts on one spot, or that end up on one point of the mesh, are
    dropped (see :func:`_collisions`).
    """
    from ..render.raster import rasterize

    screen, in_front = camera.to_screen(vertices, size, size)
    face_id = rasterize(screen, faces, size, size, in_front=in_front)
    usable = _large_parts(vertices, faces)[faces[:, 0]] & _not_deep(vertices, faces, face_id)
    column = np.clip(np.floor(pixels[:, 0]).astype(int), 0, size - 1)
    row = np.clip(np.floor(pixels[:, 1]).astype(int), 0, size - 1)
    hit = face_id[row, column]
    triangles = np.zeros((len(pixels), 3), dtype=np.int64)
    weights = np.zeros((len(pixels), 3))
    ok = (hit >= 0) & usable[np.maximum(hit, 0)]
    for i in np.flatnonzero(ok):
        triangles[i] = faces[hit[i]]
        weights[i] = _screen_barycentric(pixels[i], screen[faces[hit[i]], :2])
    ok &= ~_across_a_gap(triangles, weights, ok, vertices, faces)
    weights[~ok] = 0.0
    for i in np.flatnonzero(~ok):
        found = _march(i, pixels, ok, face_id, usable)
        if found is not None:
            triangles[i] = faces[found[0]]
            weights[i] = _screen_barycentric(found[1], screen[faces[found[0]], :2])
    missed = np.flatnonzero(~ok & (weights.sum(axis=1) == 0))
    if len(missed):
        seen = np.unique(face_id[face_id >= 0])
        flat = np.concatenate([screen[:, :2], np.zeros((len(screen), 1))], axis=1)
        on_screen = np.concatenate([pixels[missed], np.zeros((len(missed), 1))], axis=1)
        triangles[missed], weights[missed] = snap_to_surface(on_screen, flat, faces[seen[usable[seen]]])
    points = np.einsum("cj,cjd->cd", weights, vertices[triangles])
    keep = ~(_collisions(pixels, direct=ok) | _collisions(points, direct=ok))
    # how far each landmark's surface point lies, on the render, from where MediaPipe put it
    landed = np.einsum("cj,cjd->cd", weights, screen[triangles, :2])
    residual = np.linalg.norm(landed - pixels, axis=1) / size  # in picture widths
    return Correspondence(np.flatnonzero(keep), triangles[keep], weights[keep], len(pixels), residual[keep])


def _across_a_gap(triangles, weights, found, vertices, faces) -> np.ndarray:
    """(n,) bool: landmarks found on the surface but far, along it, from their mesh neighbours.

    In a mouth MediaPipe sees as closed, the lower lip's inner edge is drawn along the upper
    lip's: the pixel is on the upper lip, a few millimetres from the lower lip in space but far
    from it along the surface (around the mouth corner). A landmark none of whose found
    neighbours is within four times their straight-line distance along the mesh's edges is
    taken as on the wrong side.
    """
    from scipy import sparse
    from scipy.sparse.csgraph import dijkstra

    neighbours = _mesh_neighbours(len(found))
    if not neighbours:
        return np.zeros(len(found), dtype=bool)
    corner = triangles[np.arange(len(found)), np.argmax(weights, axis=1)]
    pairs = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    length = np.linalg.norm(vertices[pairs[:, 0]] - vertices[pairs[:, 1]], axis=1)
    graph = sparse.csr_matrix((np.maximum(length, 1e-12), (pairs[:, 0], pairs[:, 1])), shape=(len(vertices),) * 2)
    stray = np.zeros(len(found), dtype=bool)
    for i in np.flatnonzero(found):
        others = [j for j in neighbours.get(i, ()) if found[j]]
        if not others:
            continue
        straight = np.linalg.norm(vertices[corner[others]] - vertices[corner[i]], axis=1)
        along = dijkstra(graph, directed=False, indices=corner[i], limit=4 * straight.max() + 1e-12)
        stray[i] = not (along[corner[others]] <= 4 * straight + 1e-12).any()
    return stray


def _march(i: int, pixels: np.ndarray, found: np.ndarray, face_id: np.ndarray, usable: np.ndarray):
    """(face, pixel) of the first usable triangle from landmark ``i`` toward its found neighbours, or None."""
    neighbours = [j for j in _mesh_neighbours(len(pixels)).get(i, ()) if found[j]]
    if not neighbours:
        return None
    toward = pixels[neighbours].mean(axis=0) - pixels[i]
    steps = np.linspace(0, 1, int(np.ceil(np.linalg.norm(toward) / 0.5)) + 1)[1:]
    samples = pixels[i] + steps[:, None] * toward
    height, width = face_id.shape
    rows = np.clip(samples[:, 1].astype(int), 0, height - 1)
    columns = np.clip(samples[:, 0].astype(int), 0, width - 1)
    ids = face_id[rows, columns]
    good = (ids >= 0) & usable[np.maximum(ids, 0)]
    if not good.any():
        return None
    first = int(np.argmax(good))
    return int(ids[first]), samples[first]


def _mesh_neighbours(n_landmarks: int) -> dict[int, tuple[int, ...]]:
    """Landmark -> its neighbours in MediaPipe's face mesh (empty for other schemes)."""
    from ..schemes import face_triangles

    if n_landmarks not in (468, 478):
        return {}
    neighbours: dict[int, set[int]] = {}
    for a, b, c in face_triangles():
        for u, v in ((a, b), (b, c), (c, a), (b, a), (c, b), (a, c)):
            neighbours.setdefault(int(u), set()).add(int(v))
    return {k: tuple(sorted(v)) for k, v in neighbours.items()}


def _collisions(points: np.ndarray, *, direct: np.ndarray, tolerance: float = 0.015) -> np.ndarray:
    """(n,) bool: landmarks to drop because another one sits on the same spot (pixels or 3D points).

    MediaPipe sees a mouth slit as closed and puts the upper and lower inner lips together in the
    gap; snapped to the nearest lip edge, their motions (one lip up, the other down) would fight on
    one lip. Of two landmarks closer than ``tolerance`` face radii, the one snapped off the surface
    is dropped, or both when both were snapped, or both found on it directly.
    """
    from scipy.spatial import cKDTree

    radius = np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean())
    drop = np.zeros(len(points), dtype=bool)
    for i, j in cKDTree(points).query_pairs(tolerance * max(radius, 1e-12)):
        if direct[i] == direct[j]:
            drop[[i, j]] = True
        else:
            drop[j if direct[i] else i] = True
    return drop


def _deep_pixels(vertices: np.ndarray, faces: np.ndarray, face_id: np.ndarray) -> np.ndarray:
    """(height, width) bool: pixels showing a surface far behind the surface around them.

    Through an open mouth or eye the camera sees the inside of the back of the head, a head's
    depth behind the lips. A pixel is deep where its triangle lies more than a quarter of the
    face's height behind the nearest surface within 3 % of the picture around it (a maximum
    filter of the depth map); the inside of a lip, a few millimetres back, is not.
    """
    from scipy.ndimage import maximum_filter

    depth = vertices[faces].mean(axis=1)[:, 2]  # toward the camera is +Z
    shown = face_id >= 0
    picture = np.where(shown, depth[np.maximum(face_id, 0)], -np.inf)
    around = maximum_filter(picture, size=max(3, int(0.03 * face_id.shape[0]) | 1))
    seen = vertices[np.unique(faces[np.unique(face_id[shown])])]
    size = float(np.ptp(seen[:, 1])) if len(seen) else 1.0
    return shown & (picture < around - 0.25 * size)


def _not_deep(vertices: np.ndarray, faces: np.ndarray, face_id: np.ndarray) -> np.ndarray:
    """(n_faces,) bool: False for triangles mostly seen deep behind their surroundings (:func:`_deep_pixels`)."""
    shown = face_id >= 0
    deep_pixels = _deep_pixels(vertices, faces, face_id)
    counts = np.bincount(face_id[shown], minlength=len(faces))
    deep = np.bincount(face_id[deep_pixels], minlength=len(faces))
    return ~((counts > 0) & (deep > counts / 2))


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
