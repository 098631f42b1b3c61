"""Offscreen OpenGL rendering with moderngl on EGL: the only module that imports ``moderngl``.

Headless and GPU-free: ``moderngl.create_context(standalone=True, backend="egl")`` runs on
Mesa's llvmpipe (Debian packages ``libegl1 libegl-mesa0 libgl1-mesa-dri``). The mesh is drawn
with per-vertex normals computed every frame and the two-sided Lambert model of
:mod:`keyshape.render.camera`, into a colour + depth framebuffer that is read back as RGB.
"""

from __future__ import annotations

import numpy as np

from ..exceptions import MissingDependencyError
from ..mesh import NormalEstimator
from .camera import AMBIENT, BACKGROUND, LIGHT, Camera, vertex_colours

__all__ = ["GLRenderer"]

_VERTEX_SHADER = """
#version 330
uniform mat4 mvp;
in vec3 in_position;
in vec3 in_normal;
in vec3 in_color;
out vec3 v_normal;
out vec3 v_color;
void main() {
    gl_Position = mvp * vec4(in_position, 1.0);
    v_normal = in_normal;
    v_color = in_color;
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform vec3 light;
uniform float ambient;
in vec3 v_normal;
in vec3 v_color;
out vec4 f_color;
void main() {
    float diffuse = abs(dot(normalize(v_normal), light));  // two-sided Lambert
    f_color = vec4(v_color * (ambient + (1.0 - ambient) * diffuse), 1.0);
}
"""


def _moderngl():
    try:
        import moderngl
    except ImportError:
        raise MissingDependencyError("moderngl") from None
    return moderngl


class GLRenderer:
    """Smooth-shaded renderer of one mesh topology on an offscreen EGL context.

    Parameters
    ----------
    faces : (n_faces, 3) int
    width, height : int
    n_vertices : int, optional
        Defaults to ``faces.max() + 1``.
    samples : int, keyword-only
        Multisample anti-aliasing samples (0 = off).
    colours : (n_vertices, 3) float in [0, 1], optional, keyword-only
        Base colour per vertex (interpolated over the triangles); default: clay everywhere.

    Raises
    ------
    MissingDependencyError
        moderngl is not installed.
    Exception
        Whatever moderngl raises when no EGL context can be created.
    """

    backend = "gl"

    def __init__(self, faces: np.ndarray, width: int, height: int, n_vertices: int | None = None, *,
                 samples: int = 0, colours: np.ndarray | None = None):
        moderngl = _moderngl()
        self.faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        self.width, self.height = int(width), int(height)
        n_vertices = int(self.faces.max()) + 1 if n_vertices is None else int(n_vertices)
        self._normals = NormalEstimator(self.faces, n_vertices)
        self._colours = vertex_colours(colours, n_vertices)
        self.ctx = moderngl.create_context(standalone=True, backend="egl")
        try:
            self._setup(moderngl, n_vertices, samples)
        except Exception:
            self.ctx.release()
            raise

    def _setup(self, moderngl, n_vertices: int, samples: int) -> None:
        ctx = self.ctx
        self.program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        self.program["light"].value = tuple(LIGHT)
        self.program["ambient"].value = AMBIENT
        self.vbo = ctx.buffer(reserve=n_vertices * 6 * 4, dynamic=True)
        self.cbo = ctx.buffer(self._colours.astype("f4").tobytes())
        self.ibo = ctx.buffer(self.faces.astype("u4").tobytes())
        self.vao = ctx.vertex_array(self.program, [(self.vbo, "3f 3f", "in_position", "in_normal"),
                                                   (self.cbo, "3f", "in_color")],
                                    index_buffer=self.ibo, index_element_size=4)
        size = (self.width, self.height)
        self.fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 4, samples=samples)],
                                   depth_attachment=ctx.depth_renderbuffer(size, samples=samples))
        self.resolve = self.fbo if samples == 0 else ctx.framebuffer(
            color_attachments=[ctx.renderbuffer(size, 4)])
        ctx.enable(moderngl.DEPTH_TEST)

    @property
    def renderer_name(self) -> str:
        """The OpenGL renderer string, e.g. ``llvmpipe (LLVM 15.0.6, 256 bits)``."""
        return self.ctx.info["GL_RENDERER"]

    def render(self, vertices: np.ndarray, camera: Camera) -> np.ndarray:
        """Picture ``(height, width, 3) uint8`` of the mesh at ``vertices (n_vertices, 3)``."""
        vertices = np.asarray(vertices, dtype=float)
        data = np.hstack([vertices, self._normals(vertices)]).astype("f4")
        self.vbo.write(data.tobytes())
        self.program["mvp"].write(camera.matrix.T.astype("f4").tobytes())  # GL is column-major
        self.fbo.use()
        self.fbo.clear(*BACKGROUND, 1.0, depth=1.0)
        self.vao.render()
        if self.resolve is not self.fbo:
            self.ctx.copy_framebuffer(self.resolve, self.fbo)
        raw = self.resolve.read(components=4, alignment=1)  # RGBA reads faster than RGB on llvmpipe
        return np.frombuffer(raw, np.uint8).reshape(self.height, self.width, 4)[::-1, :, :3].copy()

    def close(self) -> None:
        """Release the OpenGL context and everything in it."""
        if self.ctx is not None:
            self.ctx.release()
            self.ctx = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
