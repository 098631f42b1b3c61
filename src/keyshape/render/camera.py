"""Camera framing and shading inputs shared by both renderers (pure numpy).

Both the OpenGL renderer (:mod:`keyshape.render.gl`) and the numpy rasteriser
(:mod:`keyshape.render.raster`) project with the same 4×4 matrix and light the mesh with the
same Lambert model, so their pictures agree up to smooth-versus-flat shading.

Conventions follow glTF and OpenGL: +Y up, the camera on +Z looking down −Z, normalised
device coordinates in [−1, 1]³; image row 0 is the top of the picture.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..exceptions import InputError

__all__ = ["Camera", "frame_points", "LIGHT", "lambert", "vertex_colours"]

LIGHT = np.array([-0.35, 0.45, 1.0]) / np.linalg.norm([-0.35, 0.45, 1.0])  # toward the light
AMBIENT = 0.25
BASE_COLOR = np.array([0.86, 0.74, 0.66])  # clay
BACKGROUND = np.array([0.16, 0.17, 0.19])


@dataclass(frozen=True)
class Camera:
    """A fixed camera: world → clip space.

    Attributes
    ----------
    matrix : (4, 4) float
        ``projection @ view``; ``clip = matrix @ [x, y, z, 1]``.
    perspective : bool
    """

    matrix: np.ndarray
    perspective: bool = False

    def project(self, vertices: np.ndarray) -> np.ndarray:
        """Clip coordinates ``(n_vertices, 4)`` of world points ``(n_vertices, 3)``."""
        homogeneous = np.concatenate([vertices, np.ones((len(vertices), 1))], axis=1)
        return homogeneous @ self.matrix.T

    def to_screen(self, vertices: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates and depth of world points.

        Returns
        -------
        xyz : (n_vertices, 3) float
            x, y in pixels (row 0 at the top; pixel centres at ``i + 0.5``), z the NDC depth.
        in_front : (n_vertices,) bool
            False for points at or behind the camera plane.
        """
        clip = self.project(vertices)
        w = clip[:, 3]
        in_front = w > 1e-9
        ndc = clip[:, :3] / np.where(in_front, w, 1.0)[:, None]
        x = (ndc[:, 0] + 1) / 2 * width
        y = (1 - ndc[:, 1]) / 2 * height
        return np.stack([x, y, ndc[:, 2]], axis=1), in_front


def frame_points(points: np.ndarray, *, aspect: float = 1.0, margin: float = 1.08,
                 fov_deg: float | None = None) -> Camera:
    """A front camera (on +Z, looking down −Z) that frames every point.

    Parameters
    ----------
    points : (..., 3) float
        Every position the mesh takes (e.g. a few posed frames stacked); NaN rows ignored.
    aspect : float, keyword-only
        Width / height of the picture.
    margin : float, keyword-only
        Extra room around the points' bounding box (1 = tight).
    fov_deg : float or None, keyword-only
        Vertical field of view of a perspective camera; None for orthographic.

    Returns
    -------
    Camera

    Examples
    --------
    >>> cam = frame_points(np.array([[-1.0, -1, 0], [1, 1, 0]]), margin=1.0)
    >>> cam.to_screen(np.array([[1.0, 1, 0]]), 100, 100)[0][0, :2].tolist()
    [100.0, 0.0]
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise InputError("cannot frame a camera on no finite points")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = (lo + hi) / 2
    half_h = max((hi[1] - lo[1]) / 2, (hi[0] - lo[0]) / 2 / aspect, 1e-9) * margin
    depth = max(hi[2] - lo[2], 1e-9)
    if fov_deg is None:
        return Camera(_orthographic(centre, half_h, aspect, lo[2], hi[2]), perspective=False)
    return Camera(_perspective(centre, half_h, aspect, hi[2], depth, fov_deg), perspective=True)


def _orthographic(centre, half_h, aspect, z_lo, z_hi) -> np.ndarray:
    """glOrtho over the box, the camera just in front of its nearest point."""
    pad = max(z_hi - z_lo, half_h) * 0.5
    near, far = -(z_hi + pad), -(z_lo - pad)  # distances along −Z from the origin
    m = np.eye(4)
    m[0, 0], m[0, 3] = 1 / (half_h * aspect), -centre[0] / (half_h * aspect)
    m[1, 1], m[1, 3] = 1 / half_h, -centre[1] / half_h
    # z_ndc = -2/(far-near) * z_eye - (far+near)/(far-near), eye space = world here
    m[2, 2], m[2, 3] = -2 / (far - near), -(far + near) / (far - near)
    return m


def _perspective(centre, half_h, aspect, z_front, depth, fov_deg) -> np.ndarray:
    """gluPerspective from an eye on +Z far enough that the front plane shows ``half_h``."""
    t = np.tan(np.radians(fov_deg) / 2)
    distance = half_h / t
    eye = np.array([centre[0], centre[1], z_front + distance])
    near, far = distance * 0.5, distance + depth * 2 + half_h
    view = np.eye(4)
    view[:3, 3] = -eye
    proj = np.zeros((4, 4))
    proj[0, 0], proj[1, 1] = 1 / (t * aspect), 1 / t
    proj[2, 2], proj[2, 3] = -(far + near) / (far - near), -2 * far * near / (far - near)
    proj[3, 2] = -1
    return proj @ view


def lambert(normals: np.ndarray, colours: np.ndarray | None = None) -> np.ndarray:
    """RGB in [0, 1] ``(n, 3)`` of surfaces with unit ``normals (n, 3)`` (two-sided Lambert).

    ``colours (n, 3)`` are their base colours (default: clay).
    """
    diffuse = np.abs(normals @ LIGHT)
    base = BASE_COLOR if colours is None else colours
    return base * (AMBIENT + (1 - AMBIENT) * diffuse)[:, None]


def vertex_colours(colours, n_vertices: int) -> np.ndarray:
    """Base colours ``(n_vertices, 3)`` float in [0, 1]: ``colours`` checked, or clay everywhere if None."""
    if colours is None:
        return np.tile(BASE_COLOR, (n_vertices, 1))
    colours = np.asarray(colours, dtype=float)
    if colours.shape != (n_vertices, 3) or not np.isfinite(colours).all():
        raise InputError(f"colours must be finite with shape ({n_vertices}, 3); got {colours.shape}")
    return np.clip(colours, 0.0, 1.0)
