"""Choosing a renderer: :func:`make_renderer` picks OpenGL and falls back to numpy (with one warning per process)
when moderngl or EGL is unavailable. Every renderer has ``render(vertices, camera) ->
(height, width, 3) uint8`` and ``close()``.
"""

from __future__ import annotations

import warnings
from typing import Literal, Protocol

import numpy as np

from ..exceptions import RenderFallbackWarning
from .camera import Camera, frame_points  # noqa: F401 - frame_points: used by the doctest
from .raster import NumpyRenderer

__all__ = ["Renderer", "make_renderer"]

Backend = Literal["auto", "gl", "numpy"]



class Renderer(Protocol):
    """What :func:`make_renderer` returns."""

    backend: str
    width: int
    height: int

    def render(self, vertices: np.ndarray, camera: Camera) -> np.ndarray: ...

    def close(self) -> None: ...


_warned = False


def make_renderer(faces: np.ndarray, width: int, height: int, *, n_vertices: int | None = None,
                  backend: Backend = "auto", colours: np.ndarray | None = None) -> Renderer:
    """A renderer for meshes with the triangles ``faces (n_faces, 3) int``.

    Parameters
    ----------
    faces : (n_faces, 3) int
    width, height : int
        Picture size in pixels.
    n_vertices : int, optional, keyword-only
        Defaults to ``faces.max() + 1``.
    colours : (n_vertices, 3) float in [0, 1], optional, keyword-only
        Base colour of every vertex (default: clay everywhere).
    backend : "auto", "gl" or "numpy", keyword-only
        "auto" tries OpenGL and falls back to numpy, warning once per process
        (:class:`RenderFallbackWarning`); "gl" raises if OpenGL is unavailable.

    Examples
    --------
    >>> with make_renderer(np.array([[0, 1, 2]]), 8, 8, backend="numpy") as r:
    ...     r.render(np.eye(3), frame_points(np.eye(3))).shape
    (8, 8, 3)
    """
    if backend not in ("auto", "gl", "numpy"):
        raise ValueError(f"backend must be 'auto', 'gl' or 'numpy'; got {backend!r}")
    if backend == "numpy":
        return NumpyRenderer(faces, width, height, colours=colours)
    try:
        from .gl import GLRenderer

        return GLRenderer(faces, width, height, n_vertices, colours=colours)
    except Exception as exc:
        if backend == "gl":
            raise
        _warn_fallback(exc)
        return NumpyRenderer(faces, width, height, colours=colours)


def _warn_fallback(exc: Exception) -> None:
    global _warned  # noqa: PLW0603 - once per process; tests reset it with monkeypatch
    if not _warned:
        _warned = True
        warnings.warn(f"OpenGL rendering unavailable ({exc.__class__.__name__}: {exc}); using the slow "
                      f"numpy rasteriser. Install moderngl and the EGL libraries "
                      f"(apt libegl1 libegl-mesa0 libgl1-mesa-dri) for speed.",
                      RenderFallbackWarning, stacklevel=3)
