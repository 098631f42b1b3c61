"""Stage 7, preview: render meshes offscreen and write the side-by-side preview video.

* :mod:`~keyshape.render.camera` — camera framing, normals, Lambert shading (numpy)
* :mod:`~keyshape.render.gl` — OpenGL on EGL (moderngl; Mesa llvmpipe on CPU); the fast path
* :mod:`~keyshape.render.raster` — pure-numpy z-buffer rasteriser; the fallback
* :mod:`~keyshape.render.draw` — 2D overlays (landmarks, weight bars, labels) with Pillow
* :mod:`~keyshape.render.encode` — H.264 MP4 writing with PyAV
* :mod:`~keyshape.render.preview` — :func:`render_preview`, the side-by-side video

:func:`make_renderer` picks OpenGL and falls back to numpy (with one warning per process)
when moderngl or EGL is unavailable. Every renderer has ``render(vertices, camera) ->
(height, width, 3) uint8`` and ``close()``.
"""

from ..exceptions import RenderFallbackWarning
from ._backend import Renderer, make_renderer
from .camera import Camera, frame_points
from .preview import render_preview
from .raster import NumpyRenderer

__all__ = ["Renderer", "make_renderer", "Camera", "frame_points", "NumpyRenderer", "render_preview",
           "RenderFallbackWarning"]
