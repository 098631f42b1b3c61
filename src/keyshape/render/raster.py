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

from ..mesh import face_normals
from .camera import BACKGROUND, Camera, lambert, vertex_colours

__all__ = ["NumpyRenderer", "rasterize"]

_CHUNK_PIXELS = 1 << 21  # candidate (triangle, pixel) pairs per chunk


class NumpyRenderer:
    """Flat-shaded renderer of one mesh topology, in numpy.

    Parameters
    ----------
    faces : (n_faces, 3) int
    width, height : int
    colours : (n_vertices, 3) float in [0, 1], optional, keyword-only
        Base colour per vertex (each triangle takes the mean of its corners'); default: clay.
    """

    backend = "numpy"

    def __init__(self, faces: np.ndarray, width: int, height: int, *, colours: np.ndarray | None = None):
        self.faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        self.width, self.height = int(width), int(height)
        n_vertices = int(self.faces.max()) + 1 if self.faces.size else 0
        if colours is not None:
            colours = vertex_colours(colours, max(n_vertices, len(colours)))[self.faces].mean(axis=1)
        self._colours = colours  # (n_faces, 3): each triangle the mean of its corners

    def render(self, vertices: np.ndarray, camera: Camera) -> np.ndarray:
        """Picture ``(height, width, 3) uint8`` of the mesh at ``vertices (n_vertices, 3)``."""
        screen, in_front = camera.to_screen(np.asarray(vertices, dtype=float), self.width, self.height)
        face_id = rasterize(screen, self.faces, self.width, self.height, in_front=in_front)
        normals = face_normals(np.asarray(vertices, dtype=float), self.faces)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        colours = lambert(np.divide(normals, length, out=np.zeros_like(normals), where=length > 0), self._colours)
        palette = np.round(np.vstack([colours, BACKGROUND]) * 255).astype(np.uint8)  # -1 → background
        return palette[face_id]

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
    planes, rows = _setup(screen, faces, width, height, in_front)
    spans = _spans(planes, rows, width)
    zbuffer = np.full(width * height, np.inf)
    face_id = np.full(width * height, -1, dtype=np.int64)
    for chunk in _chunks(spans[3] - spans[2] + 1):
        _fill(spans[:, chunk], width, zbuffer, face_id)
    return face_id.reshape(height, width)


def _setup(screen, faces, width, height, in_front) -> tuple[np.ndarray, np.ndarray]:
    """Planes ``(10, n_drawn)`` and row ranges ``(n_drawn, 2)`` of the drawable faces.

    Rows 0–2, 3–5 and 6–8 of ``planes`` are (A, B, C) of the barycentric weights ``w_a``,
    ``w_b`` and of the depth ``z`` as affine functions ``A x + B y + C`` of the pixel
    position; row 9 is the face index. Row ranges are the first and last pixel row.
    """
    ok = np.isfinite(screen).all(axis=1)
    if in_front is not None:
        ok &= in_front
    index = np.flatnonzero(ok[faces].all(axis=1))
    (ax, ay, az), (bx, by, bz), (cx, cy, cz) = (screen[faces[index, i]].T for i in range(3))
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    keep = np.abs(area) > 1e-12
    index = index[keep]
    (ax, ay, az, bx, by, bz, cx, cy, cz, area) = (v[keep] for v in (ax, ay, az, bx, by, bz, cx, cy, cz, area))
    # edge functions (Pineda 1988), normalised: w_a(x, y) = ((c − b) × (p − b))_z / area, and so on
    wa = np.stack([-(cy - by), cx - bx, (cy - by) * bx - (cx - bx) * by]) / area
    wb = np.stack([-(ay - cy), ax - cx, (ay - cy) * cx - (ax - cx) * cy]) / area
    wc = -wa - wb
    wc[2] += 1.0  # w_c = 1 − w_a − w_b
    z = wa * az + wb * bz + wc * cz  # depth is affine in screen space
    ys = np.stack([ay, by, cy], axis=1)
    first = np.maximum(np.ceil(ys.min(axis=1) - 0.5), 0)
    last = np.minimum(np.floor(ys.max(axis=1) - 0.5), height - 1)
    return np.vstack([wa, wb, z, index[None].astype(float)]), np.stack([first, last], axis=1).astype(np.int64)


def _spans(planes: np.ndarray, rows: np.ndarray, width: int) -> np.ndarray:
    """(6, n_spans): row, face, first and last pixel column, z at x = 0 of the row, dz/dx.

    Each face's covered pixels on each row form one run: the intersection of the three
    half-lines ``w_e(x, y) >= 0`` (``w_c = 1 − w_a − w_b``).
    """
    counts = np.maximum(rows[:, 1] - rows[:, 0] + 1, 0)
    owner = np.repeat(np.arange(len(rows)), counts)
    row = rows[owner, 0] + np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    p, y = planes[:, owner], row + 0.5
    lo, hi = np.zeros(len(row)), np.full(len(row), float(width))
    edges = ((p[0], p[1] * y + p[2]), (p[3], p[4] * y + p[5]),
             (-p[0] - p[3], 1.0 - (p[1] + p[4]) * y - p[2] - p[5]))
    for slope, offset in edges:  # slope·x + offset >= 0
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = -offset / slope
        lo = np.where(slope > 0, np.maximum(lo, bound), lo)
        hi = np.where(slope < 0, np.minimum(hi, bound), hi)
        hi = np.where((slope == 0) & (offset < 0), -1.0, hi)
    first, last = np.ceil(lo - 0.5), np.minimum(np.floor(hi - 0.5), width - 1)
    return np.stack([row, p[9], first, last, p[7] * y + p[8], p[6]])


def _chunks(counts: np.ndarray):
    """Slices of consecutive spans whose pixel counts add up to about ``_CHUNK_PIXELS``."""
    total = np.cumsum(np.maximum(counts, 0))
    start = 0
    while start < len(counts):
        done = total[start - 1] if start else 0
        end = max(int(np.searchsorted(total, done + _CHUNK_PIXELS, side="right")), start + 1)
        yield slice(start, end)
        start = end


def _fill(spans: np.ndarray, width: int, zbuffer: np.ndarray, face_id: np.ndarray) -> None:
    """Write the pixels of some spans into the z-buffer (nearest wins)."""
    row, face, first, last, z_row, slope = spans
    counts = np.maximum(last - first + 1, 0).astype(np.int64)
    owner = np.repeat(np.arange(len(counts)), counts)
    x = first[owner] + (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts))
    z = z_row[owner] + slope[owner] * (x + 0.5)
    pixel = row[owner].astype(np.int64) * width + x.astype(np.int64)
    near = np.abs(z) <= 1
    pixel, z, owner = pixel[near], z[near], owner[near]
    np.minimum.at(zbuffer, pixel, z)
    won = z <= zbuffer[pixel]
    face_id[pixel[won]] = face[owner[won]].astype(np.int64)
