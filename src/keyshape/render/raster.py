"""A pure-numpy triangle rasteriser: z-buffered, flat-shaded. Slow but needs nothing.

The fallback for machines without EGL. Triangles are processed in chunks; each chunk
expands every triangle into the pixels of its bounding box, keeps those inside it
(edge functions, Pineda 1988), and resolves visibility with a z-buffer.

References
----------
.. [1] J. Pineda, "A parallel algorithm for polygon rasterization", SIGGRAPH 1988.
"""

from __future__ import annotations

import numpy as np

from .camera import BACKGROUND, Camera, face_normals, lambert

__all__ = ["NumpyRenderer", "rasterize"]

_CHUNK_PIXELS = 1 << 21  # candidate (triangle, pixel) pairs per chunk


class NumpyRenderer:
    """Flat-shaded renderer of one mesh topology, in numpy.

    Parameters
    ----------
    faces : (n_faces, 3) int
    width, height : int
    """

    backend = "numpy"

    def __init__(self, faces: np.ndarray, width: int, height: int):
        self.faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        self.width, self.height = int(width), int(height)

    def render(self, vertices: np.ndarray, camera: Camera) -> np.ndarray:
        """Picture ``(height, width, 3) uint8`` of the mesh at ``vertices (n_vertices, 3)``."""
        screen, in_front = camera.to_screen(np.asarray(vertices, dtype=float), self.width, self.height)
        face_id = rasterize(screen, self.faces, self.width, self.height, in_front=in_front)
        normals = face_normals(np.asarray(vertices, dtype=float), self.faces)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        colours = lambert(np.divide(normals, length, out=np.zeros_like(normals), where=length > 0))
        palette = np.vstack([colours, BACKGROUND])  # index -1 → background
        return np.round(palette[face_id] * 255).astype(np.uint8)

    def close(self) -> None:
        """Nothing to release (symmetry with the OpenGL renderer)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def rasterize(screen: np.ndarray, faces: np.ndarray, width: int, height: int, *,
              in_front: np.ndarray | None = None) -> np.ndarray:
    """Visible triangle of every pixel.

    Parameters
    ----------
    screen : (n_vertices, 3) float
        x, y in pixels (pixel centres at ``i + 0.5``), z the depth (smaller is nearer, in [−1, 1]).
    faces : (n_faces, 3) int
    width, height : int
    in_front : (n_vertices,) bool, optional, keyword-only
        Triangles touching a vertex not in front of the camera are skipped.

    Returns
    -------
    (height, width) int
        Index of the nearest triangle covering each pixel centre, −1 for none.

    Examples
    --------
    >>> tri = np.array([[0.0, 0, 0], [4, 0, 0], [0, 4, 0]])
    >>> rasterize(tri, np.array([[0, 1, 2]]), 4, 4)
    array([[ 0,  0,  0,  0],
           [ 0,  0,  0, -1],
           [ 0,  0, -1, -1],
           [ 0, -1, -1, -1]])
    """
    keep = _drawable(screen, faces, in_front)
    face_index = np.flatnonzero(keep)
    boxes = _bounding_boxes(screen, faces[face_index], width, height)
    zbuffer = np.full(width * height, np.inf)
    face_id = np.full(width * height, -1, dtype=np.int64)
    for chunk in _chunks(boxes[:, 4]):
        _draw_chunk(screen, faces, face_index[chunk], boxes[chunk], width, zbuffer, face_id)
    return face_id.reshape(height, width)


def _drawable(screen, faces, in_front) -> np.ndarray:
    ok = np.isfinite(screen).all(axis=1)
    if in_front is not None:
        ok &= in_front
    return ok[faces].all(axis=1)


def _bounding_boxes(screen, faces, width, height) -> np.ndarray:
    """(n_faces, 5) int: x0, y0, box width, box height, pixel count (0 when off screen)."""
    xy = screen[faces][:, :, :2]  # (n_faces, 3 corners, 2)
    lo = np.maximum(np.ceil(xy.min(axis=1) - 0.5), 0)
    hi = np.minimum(np.floor(xy.max(axis=1) - 0.5), [width - 1, height - 1])
    size = np.maximum(hi - lo + 1, 0).astype(np.int64)
    lo = lo.astype(np.int64)
    return np.column_stack([lo, size, size[:, 0] * size[:, 1]])


def _chunks(counts: np.ndarray):
    """Slices of consecutive faces whose pixel counts add up to about ``_CHUNK_PIXELS``."""
    total = np.cumsum(counts)
    start = 0
    while start < len(counts):
        done = total[start - 1] if start else 0
        end = max(int(np.searchsorted(total, done + _CHUNK_PIXELS, side="right")), start + 1)
        yield slice(start, end)
        start = end


def _draw_chunk(screen, faces, face_index, boxes, width, zbuffer, face_id) -> None:
    counts = boxes[:, 4]
    owner = np.repeat(np.arange(len(boxes)), counts)  # local face of each candidate pixel
    offset = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    px = boxes[owner, 0] + offset % np.maximum(boxes[owner, 2], 1)
    py = boxes[owner, 1] + offset // np.maximum(boxes[owner, 2], 1)
    corners = screen[faces[face_index]][owner]  # (n_candidates, 3, 3)
    depth, inside = _barycentric_depth(corners, px + 0.5, py + 0.5)
    pixel = (py * width + px)[inside]
    depth, owner = depth[inside], face_index[owner[inside]]
    order = np.lexsort((depth, pixel))
    pixel, first = np.unique(pixel[order], return_index=True)
    depth, owner = depth[order][first], owner[order][first]
    nearer = depth < zbuffer[pixel]
    zbuffer[pixel[nearer]] = depth[nearer]
    face_id[pixel[nearer]] = owner[nearer]


def _barycentric_depth(corners, x, y) -> tuple[np.ndarray, np.ndarray]:
    """Interpolated depth and the inside test of points ``(x, y)`` in their triangles."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    # edge functions: w_a is the signed area opposite a, and so on
    w_a = (c[:, 0] - b[:, 0]) * (y - b[:, 1]) - (c[:, 1] - b[:, 1]) * (x - b[:, 0])
    w_b = (a[:, 0] - c[:, 0]) * (y - c[:, 1]) - (a[:, 1] - c[:, 1]) * (x - c[:, 0])
    w_c = (b[:, 0] - a[:, 0]) * (y - a[:, 1]) - (b[:, 1] - a[:, 1]) * (x - a[:, 0])
    safe = np.where(np.abs(area) > 1e-12, area, 1.0)
    w_a, w_b, w_c = w_a / safe, w_b / safe, w_c / safe
    depth = w_a * a[:, 2] + w_b * b[:, 2] + w_c * c[:, 2]
    inside = (np.abs(area) > 1e-12) & (w_a >= 0) & (w_b >= 0) & (w_c >= 0) & (np.abs(depth) <= 1)
    return depth, inside
