"""Headless float-precision renderer on top of pyrender (EGL, works on CPU via Mesa llvmpipe).

What this adds to stock pyrender
--------------------------------
* **Float output.**  The scene is drawn into a single-channel ``GL_R32F``
  colour texture with a 32-bit float depth buffer, box-averaged on the GPU
  into a ``GL_R32F`` render buffer of the output size and read back with
  ``glReadPixels(GL_RED, GL_FLOAT)`` (stock pyrender reads 8-bit RGB).  The
  albedo texture is uploaded as ``GL_R32F`` (stock pyrender converts float
  textures to 8 bit).  Intensities are therefore not quantised to 1/255.
* **Exact OpenCV camera.**  Vertices are transformed to the OpenCV camera
  frame in float64 on the CPU and handed to OpenGL in its camera frame
  (``y`` and ``z`` flipped); the projection matrix is built from ``K`` with
  the principal point shifted by half a pixel, because OpenGL's window
  coordinates put pixel *edges* on integers while :class:`Camera` puts pixel
  *centres* on integers.  The projection matrix is expressed in normalised
  device coordinates, so it is the same at any supersampling factor.
* **Supersampling.**  The scene is rasterised at ``supersample`` times the
  output resolution and box-averaged down (exact ``s x s`` mean).  Texture
  motion inside faces is then continuous to far below 0.001 px.  Coverage at
  silhouettes and occlusion edges is still point-sampled: an edge's intensity
  changes only when it crosses one of the ``s x s`` sample positions, so
  silhouette motion is quantised at roughly ``1 / s`` px.
* **Cheap frames.**  A displaced frame only rewrites the vertex buffer
  (``glBufferSubData``); the scene, shaders and texture stay on the GPU.
* **Linear lighting.**  ``lighting="lit"`` uses pyrender's PBR shader with its
  sRGB decode of the texture and its output gamma removed, so the image is
  linear in albedo: ``I = albedo * (ambient + k * max(n.l, 0)) + tiny specular``.
  ``lighting="lambert"`` evaluates the same Lambert term per vertex on the CPU
  and lets the flat shader interpolate it (as fast as unlit).

Environment
-----------
``PYOPENGL_PLATFORM`` is set to ``egl`` if unset (it must be set before
PyOpenGL is first imported).  Debian packages: ``libegl1 libegl-mesa0
libgl1-mesa-dri libgles2``.  ``EGL_DEVICE_ID`` picks the EGL device (default 0).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import types
from typing import Any, Literal

import numpy as np

from .camera import Camera
from .texture import TexturedMesh, speckle_texture, triplanar_mapping

__all__ = ["EGLUnavailableError", "Renderer", "DEBIAN_PACKAGES", "gl_info"]

# PyOpenGL picks its platform at first import: ask for EGL as early as possible.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

#: Debian packages needed for headless EGL rendering on the CPU.
DEBIAN_PACKAGES = ("libegl1", "libegl-mesa0", "libgl1-mesa-dri", "libgles2")

# Default texel footprint in *output* pixels at the median depth; with the
# default speckle grain (4 texels) this gives speckles of sigma ~ 1.5 px.
_DEFAULT_TEXEL_PX = 0.375
_DEFAULT_GRAIN = 4.0


class EGLUnavailableError(RuntimeError):
    """Headless OpenGL (EGL) could not be initialised."""


def egl_error(exc: BaseException) -> EGLUnavailableError:
    return EGLUnavailableError(
        "headless OpenGL rendering through EGL is unavailable "
        f"({type(exc).__name__}: {exc}). Install the Debian packages with "
        f"`apt-get install -y {' '.join(DEBIAN_PACKAGES)}` and make sure "
        "PYOPENGL_PLATFORM=egl is set before PyOpenGL is first imported "
        f"(current value: {os.environ.get('PYOPENGL_PLATFORM')!r})."
    )


_GL: types.SimpleNamespace | None = None


def _gl() -> types.SimpleNamespace:
    """Import pyrender / PyOpenGL (EGL) once and build the GL-dependent classes."""
    global _GL
    if _GL is not None:
        return _GL
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if os.environ["PYOPENGL_PLATFORM"] != "egl":
        raise egl_error(ValueError("PYOPENGL_PLATFORM is not 'egl'"))
    if "OpenGL.platform" in sys.modules:  # PyOpenGL fixes its platform at first import
        platform = type(sys.modules["OpenGL.platform"].PLATFORM).__name__
        if platform != "EGLPlatform":
            raise egl_error(
                RuntimeError(f"PyOpenGL was already imported with the {platform} platform")
            )
    if not hasattr(np, "infty"):  # removed in numpy 2, still used by pyrender
        np.infty = np.inf  # type: ignore[attr-defined]
    try:
        import pyrender
        from OpenGL import GL
        from pyrender.platforms import egl as pr_egl
        from pyrender.shader_program import ShaderProgramCache
    except Exception as exc:  # ImportError, OSError, OpenGL NullFunctionError...
        raise egl_error(exc) from exc
    ns = types.SimpleNamespace(pyrender=pyrender, GL=GL, egl=pr_egl)
    ns.FloatTexture = _make_float_texture(pyrender, GL)
    ns.FloatRenderer = _make_float_renderer(pyrender, GL)
    ns.OpenCVCamera = _make_opencv_camera(pyrender)
    ns.ShaderProgramCache = ShaderProgramCache
    _GL = ns
    return ns


# --------------------------------------------------------------------------- GL classes
def _make_float_texture(pyrender: Any, GL: Any) -> type:
    class FloatTexture(pyrender.Texture):
        """Single-channel float32 texture (``GL_R32F``), sampled as grey (r, r, r, 1)."""

        def __init__(self, image: np.ndarray, sampler: Any = None) -> None:
            img = np.asarray(image, dtype=np.float32)
            if img.ndim != 2:
                raise ValueError("texture image must be 2-D (grayscale)")
            super().__init__(
                source=img, source_channels="R", sampler=sampler, data_format=GL.GL_FLOAT
            )

        # stock pyrender converts float sources to uint8 here
        @property
        def source(self) -> np.ndarray | None:
            return self._source

        @source.setter
        def source(self, value: np.ndarray | None) -> None:
            self._source = None if value is None else np.ascontiguousarray(value, np.float32)
            self._is_transparent = False

        def is_transparent(self, cutoff: float = 1.0) -> bool:
            return False

        def _add_to_context(self) -> None:
            if self._texid is not None:
                raise ValueError("Texture already loaded into OpenGL context")
            src = self.source
            h, w = src.shape
            self._texid = GL.glGenTextures(1)
            GL.glBindTexture(GL.GL_TEXTURE_2D, self._texid)
            GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 4)
            data = np.ascontiguousarray(np.flip(src, axis=0))
            GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_R32F, w, h, 0, GL.GL_RED, GL.GL_FLOAT, data)
            GL.glGenerateMipmap(GL.GL_TEXTURE_2D)
            s = self.sampler
            mag = s.magFilter if s.magFilter is not None else GL.GL_LINEAR
            mnf = s.minFilter if s.minFilter is not None else GL.GL_LINEAR_MIPMAP_LINEAR
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, mag)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, mnf)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_WRAP_S, s.wrapS)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_WRAP_T, s.wrapT)
            swizzle = np.array([GL.GL_RED, GL.GL_RED, GL.GL_RED, GL.GL_ONE], dtype=np.int32)
            GL.glTexParameteriv(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_SWIZZLE_RGBA, swizzle)
            GL.glBindTexture(GL.GL_TEXTURE_2D, 0)

    return FloatTexture


def _make_opencv_camera(pyrender: Any) -> type:
    class OpenCVCamera(pyrender.IntrinsicsCamera):
        """pyrender camera reproducing an OpenCV ``K`` (pixel centres on integers).

        ``cx, cy`` are stored in OpenGL's edge convention (``+0.5``).  The
        projection matrix is computed in normalised device coordinates from the
        *native* image size, so it is independent of the viewport size
        (supersampling) and supports skew.  For zero skew and a viewport of the
        native size it equals ``IntrinsicsCamera.get_projection_matrix``.
        """

        def __init__(self, camera: Camera, znear: float, zfar: float) -> None:
            super().__init__(
                fx=camera.fx,
                fy=camera.fy,
                cx=camera.cx + 0.5,
                cy=camera.cy + 0.5,
                znear=znear,
                zfar=zfar,
            )
            self.native_width = camera.width
            self.native_height = camera.height
            self.skew = camera.skew

        def get_projection_matrix(self, width: Any = None, height: Any = None) -> np.ndarray:
            W, H = float(self.native_width), float(self.native_height)
            n, f = self.znear, self.zfar
            P = np.zeros((4, 4))
            P[0, 0] = 2.0 * self.fx / W
            P[0, 1] = -2.0 * self.skew / W
            P[0, 2] = 1.0 - 2.0 * self.cx / W
            P[1, 1] = 2.0 * self.fy / H
            P[1, 2] = 2.0 * self.cy / H - 1.0
            P[2, 2] = (f + n) / (n - f)
            P[2, 3] = 2.0 * f * n / (n - f)
            P[3, 2] = -1.0
            return P

    return OpenCVCamera


_DOWNSAMPLE_VS = """#version 330 core
void main() {
    // one triangle covering the viewport
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}
"""

_DOWNSAMPLE_FS = """#version 330 core
uniform sampler2D src;
uniform int factor;
out vec4 frag_color;
void main() {
    // exact box average of the factor x factor block under this output pixel
    ivec2 o = ivec2(gl_FragCoord.xy) * factor;
    float acc = 0.0;
    for (int j = 0; j < factor; ++j)
        for (int i = 0; i < factor; ++i)
            acc += texelFetch(src, o + ivec2(i, j), 0).r;
    frag_color = vec4(acc / float(factor * factor), 0.0, 0.0, 1.0);
}
"""


def _make_float_renderer(pyrender: Any, GL: Any) -> type:
    from OpenGL.GL import shaders as gl_shaders

    def new_fb(attachments: list[tuple[Any, Any, Any]]) -> Any:
        fb = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fb)
        for point, kind, obj in attachments:
            if kind == "tex":
                GL.glFramebufferTexture2D(GL.GL_FRAMEBUFFER, point, GL.GL_TEXTURE_2D, obj, 0)
            else:
                GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, point, GL.GL_RENDERBUFFER, obj)
        _check_fb(GL)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        return fb

    def new_rb(fmt: Any, w: int, h: int, samples: int = 0) -> Any:
        rb = GL.glGenRenderbuffers(1)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rb)
        if samples:
            GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, samples, fmt, w, h)
        else:
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, fmt, w, h)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, 0)
        return rb

    class FloatRenderer(pyrender.Renderer):
        """pyrender.Renderer with float32 render targets and a GPU box downsample.

        The scene is drawn into a ``GL_R32F`` colour texture with a 32-bit
        float depth buffer at the viewport size; ``_read_main_framebuffer``
        box-averages the colour by ``self.downsample`` on the GPU (exact
        ``factor x factor`` mean in a fragment shader), reads it back with
        ``glReadPixels(GL_RED, GL_FLOAT)`` and returns ``(color, depth)`` as
        float32 arrays in image row order.  ``depth`` is the window-space depth
        in [0, 1] at full viewport resolution, read only when
        ``self.read_depth`` is true, else None.
        """

        def __init__(self, width: int, height: int, msaa: int = 0, downsample: int = 1) -> None:
            self.msaa = int(msaa)
            self.downsample = int(downsample)
            if width % self.downsample or height % self.downsample:
                raise ValueError("viewport size must be a multiple of downsample")
            self.read_depth = False
            self._fbs: dict[tuple[int, int], dict[str, Any]] = {}
            self._ds_program = None
            self._ds_vao = None
            super().__init__(width, height)

        def _configure_main_framebuffer(self) -> None:
            dims = (self.viewport_width, self.viewport_height)
            if dims not in self._fbs:
                w, h = dims
                r: dict[str, Any] = {"tex": [], "rb": [], "fb": []}
                tex = GL.glGenTextures(1)
                GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
                GL.glTexStorage2D(GL.GL_TEXTURE_2D, 1, GL.GL_R32F, w, h)
                GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
                GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
                GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
                depth = new_rb(GL.GL_DEPTH_COMPONENT32F, w, h)
                fb = new_fb(
                    [
                        (GL.GL_COLOR_ATTACHMENT0, "tex", tex),
                        (GL.GL_DEPTH_ATTACHMENT, "rb", depth),
                    ]
                )
                r["tex"].append(tex)
                r["rb"].append(depth)
                r["fb"].append(fb)
                r["main"], r["color_tex"], r["draw"] = fb, tex, fb
                if self.msaa > 0:
                    mc = new_rb(GL.GL_R32F, w, h, self.msaa)
                    md = new_rb(GL.GL_DEPTH_COMPONENT32F, w, h, self.msaa)
                    mfb = new_fb(
                        [(GL.GL_COLOR_ATTACHMENT0, "rb", mc), (GL.GL_DEPTH_ATTACHMENT, "rb", md)]
                    )
                    r["rb"] += [mc, md]
                    r["fb"].append(mfb)
                    r["draw"] = mfb
                s = self.downsample
                if s > 1:
                    lo = new_rb(GL.GL_R32F, w // s, h // s)
                    lfb = new_fb([(GL.GL_COLOR_ATTACHMENT0, "rb", lo)])
                    r["rb"].append(lo)
                    r["fb"].append(lfb)
                    r["lo"] = lfb
                self._fbs[dims] = r
            r = self._fbs[dims]
            # pyrender draws into _main_fb_ms
            self._main_fb, self._main_fb_ms = r["main"], r["draw"]
            self._main_fb_dims = dims

        def _downsample_program(self) -> Any:
            if self._ds_program is None:
                self._ds_vao = GL.glGenVertexArrays(1)
                GL.glBindVertexArray(self._ds_vao)
                self._ds_program = gl_shaders.compileProgram(
                    gl_shaders.compileShader(_DOWNSAMPLE_VS, GL.GL_VERTEX_SHADER),
                    gl_shaders.compileShader(_DOWNSAMPLE_FS, GL.GL_FRAGMENT_SHADER),
                )
                GL.glBindVertexArray(0)
            return self._ds_program

        def _delete_main_framebuffer(self) -> None:
            for r in self._fbs.values():
                GL.glDeleteFramebuffers(len(r["fb"]), r["fb"])
                GL.glDeleteRenderbuffers(len(r["rb"]), r["rb"])
                GL.glDeleteTextures(r["tex"])
            self._fbs.clear()
            if self._ds_program is not None:
                GL.glDeleteProgram(self._ds_program)
                GL.glDeleteVertexArrays(1, [self._ds_vao])
                self._ds_program = self._ds_vao = None
            self._main_fb = self._main_fb_ms = None
            self._main_fb_dims = (None, None)

        def _read_main_framebuffer(self, scene: Any, flags: Any) -> Any:
            w, h = self._main_fb_dims
            r = self._fbs[(w, h)]
            if r["draw"] != r["main"]:  # resolve MSAA
                GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, r["draw"])
                GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, r["main"])
                bits = GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT
                GL.glBlitFramebuffer(0, 0, w, h, 0, 0, w, h, bits, GL.GL_NEAREST)
            GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 4)
            depth = None
            if self.read_depth:
                GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, r["main"])
                buf = GL.glReadPixels(0, 0, w, h, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT)
                depth = np.frombuffer(buf, dtype=np.float32).reshape(h, w)[::-1]
            s = self.downsample
            if s > 1:
                program = self._downsample_program()
                GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, r["lo"])
                GL.glViewport(0, 0, w // s, h // s)
                GL.glDisable(GL.GL_DEPTH_TEST)
                GL.glDisable(GL.GL_BLEND)
                GL.glDisable(GL.GL_CULL_FACE)
                GL.glDisable(GL.GL_MULTISAMPLE)
                GL.glPolygonMode(GL.GL_FRONT_AND_BACK, GL.GL_FILL)
                GL.glUseProgram(program)
                GL.glActiveTexture(GL.GL_TEXTURE0)
                GL.glBindTexture(GL.GL_TEXTURE_2D, r["color_tex"])
                GL.glUniform1i(GL.glGetUniformLocation(program, "src"), 0)
                GL.glUniform1i(GL.glGetUniformLocation(program, "factor"), s)
                GL.glBindVertexArray(self._ds_vao)
                GL.glDrawArrays(GL.GL_TRIANGLES, 0, 3)
                GL.glBindVertexArray(0)
                GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
                GL.glUseProgram(0)
                GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, r["lo"])
                w, h = w // s, h // s
            else:
                GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, r["main"])
            buf = GL.glReadPixels(0, 0, w, h, GL.GL_RED, GL.GL_FLOAT)
            color = np.frombuffer(buf, dtype=np.float32).reshape(h, w)[::-1]
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
            return color, depth

    return FloatRenderer


def _check_fb(GL: Any) -> None:
    status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
    if status != GL.GL_FRAMEBUFFER_COMPLETE:
        raise RuntimeError(f"float framebuffer incomplete (status 0x{int(status):x})")


def _linear_shader_dir(pyrender: Any) -> str:
    """Copy pyrender's shaders, removing the sRGB decode and the output gamma."""
    src = os.path.join(os.path.dirname(pyrender.__file__), "shaders")
    dst = tempfile.mkdtemp(prefix="vvtbench_shaders_")
    shutil.copytree(src, dst, dirs_exist_ok=True)
    path = os.path.join(dst, "mesh.frag")
    with open(path) as fh:
        code = fh.read()
    gamma = "vec4(pow(color.xyz, vec3(1.0/2.2)), color.a * base_color.a)"
    decode = "#ifndef SRGB_CORRECTED"
    if code.count(gamma) != 1 or code.count(decode) != 1:
        shutil.rmtree(dst, ignore_errors=True)
        raise RuntimeError("unexpected pyrender mesh.frag; cannot make lighting linear")
    code = code.replace(gamma, "vec4(color.xyz, color.a * base_color.a)")
    code = code.replace(decode, "#if 0  // vvtbench: texture is linear")
    with open(path, "w") as fh:
        fh.write(code)
    return dst


def _vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # area weighted
    idx = F.ravel()
    vn = np.stack(
        [np.bincount(idx, np.repeat(fn[:, c], 3), minlength=len(V)) for c in range(3)], axis=1
    )
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.where(norm > 0, norm, 1.0)


def gl_info() -> dict[str, str]:
    """Vendor / renderer / version strings of a throw-away EGL context."""
    with Renderer(
        np.array([[0, 0, 1.0], [1, 0, 1], [0, 1, 1]]),
        np.array([[0, 1, 2]]),
        Camera.from_intrinsics(10.0, width=4, height=4),
        supersample=1,
    ) as r:
        r._make_current()
        GL = r._ns.GL
        return {
            k: GL.glGetString(v).decode()
            for k, v in (
                ("vendor", GL.GL_VENDOR),
                ("renderer", GL.GL_RENDERER),
                ("version", GL.GL_VERSION),
            )
        }


# --------------------------------------------------------------------------- public API
class Renderer:
    """Render a textured, displaceable triangle surface through a pinhole camera.

    Parameters
    ----------
    vertices : array_like, shape (N, 3)
        Rest positions (world frame, metres or any unit consistent with ``camera``).
    triangles : array_like, shape (F, 3), int
        Faces; winding does not matter (faces are double sided).
    camera : Camera
        Output camera; images are ``(camera.height, camera.width)``.
    texture : ndarray (S, S) float in [0, 1], optional
        Square grayscale albedo image, tiled over the surface with triplanar mapping
        (see :func:`~vvtbench.render.texture.triplanar_mapping`).  Should be
        periodic.  Default: ``speckle_texture(1024, grain=4, seed=texture_seed)``.
    texture_tile : float, optional
        World length covered by one repetition of ``texture``.  Default: such
        that one texel covers 0.375 output pixels at the median vertex depth
        (default speckles then have sigma ~ 1.5 px).
    supersample : int
        Rasterise at this factor times the output resolution, then box-average.
        4 is needed for motions below ~0.005 px.
    lighting : {"flat", "lit", "lambert"}
        ``"flat"``: image = albedo (unlit).  ``"lit"``: pyrender's per-pixel
        PBR shading (matte dielectric) by a directional light plus ambient,
        made linear in albedo (about 5x slower than flat on llvmpipe).
        ``"lambert"``: ``albedo * (ambient + k * max(n.l, 0))`` evaluated per
        vertex on the CPU and interpolated (Gouraud); as fast as ``"flat"``.
        In all shaded modes a white surface facing the light renders at ~0.9
        and lighting is two-sided (normals are turned towards the camera).
    background : float
        Intensity of pixels not covered by the surface.
    light_direction : array_like (3,), optional
        World direction *in which the light travels* (shaded modes only).
        Default: the viewing direction tilted so the light comes from the
        upper left of the camera.
    ambient : float
        Ambient term of the shaded modes; the directional light is scaled so
        that a white surface facing it renders at 0.9.
    msaa : int
        Extra multisampling per supersample (0 = off; rarely useful).
    texture_seed : int
        Seed of the default speckle texture.

    Notes
    -----
    Create, render, :meth:`close` (or use ``with``).  Each instance owns an
    EGL context; methods make it current, so several instances may coexist in
    one thread.  Not thread-safe.
    """

    def __init__(
        self,
        vertices: Any,
        triangles: Any,
        camera: Camera,
        texture: np.ndarray | None = None,
        *,
        texture_tile: float | None = None,
        supersample: int = 4,
        lighting: Literal["flat", "lit", "lambert"] = "flat",
        background: float = 0.0,
        light_direction: Any = None,
        ambient: float = 0.15,
        msaa: int = 0,
        texture_seed: int = 0,
    ) -> None:
        self._platform = None
        self._renderer = None
        self._shader_dir: str | None = None
        V = np.asarray(vertices, dtype=np.float64)
        F = np.asarray(triangles)
        if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
            raise ValueError("vertices must have shape (N, 3), N > 0")
        if not isinstance(camera, Camera):
            raise TypeError("camera must be a vvtbench.render.Camera")
        if lighting not in ("flat", "lit", "lambert"):
            raise ValueError("lighting must be 'flat', 'lit' or 'lambert'")
        supersample = int(supersample)
        if supersample < 1:
            raise ValueError("supersample must be >= 1")
        z = camera.depth(V)
        if not np.all(z > 0):
            raise ValueError("all vertices must be in front of the camera (depth > 0)")
        self.camera = camera
        self.supersample = supersample
        self.lighting = lighting
        self.background = float(background)
        self.n_vertices = len(V)
        self._rest = V
        self._rest_depth_cache: tuple[np.ndarray, np.ndarray] | None = None
        self._uploaded_rest = True

        if texture is None:
            texture = speckle_texture(1024, grain=_DEFAULT_GRAIN, seed=texture_seed)
        tex = np.asarray(texture, dtype=np.float32)
        if tex.ndim != 2 or tex.shape[0] != tex.shape[1]:
            raise ValueError("texture must be a square 2-D grayscale image")
        if texture_tile is None:
            texel = _DEFAULT_TEXEL_PX * float(np.median(z)) / min(camera.fx, camera.fy)
            texture_tile = tex.shape[1] * texel
        self.texture_tile = float(texture_tile)
        self.mesh: TexturedMesh = triplanar_mapping(V, F, self.texture_tile)

        ns = _gl()
        self._ns = ns
        pyrender = ns.pyrender
        W, H = camera.width * supersample, camera.height * supersample
        try:
            device = ns.egl.get_device_by_index(int(os.environ.get("EGL_DEVICE_ID", "0")))
            self._platform = ns.egl.EGLPlatform(W, H, device=device)
            self._platform.init_context()
            self._platform.make_current()
        except Exception as exc:
            self._platform = None
            raise egl_error(exc) from exc
        try:
            self._renderer = ns.FloatRenderer(W, H, msaa=msaa, downsample=supersample)
            if lighting == "lit":
                self._shader_dir = _linear_shader_dir(pyrender)
                self._renderer._program_cache = ns.ShaderProgramCache(shader_dir=self._shader_dir)
            self._build_scene(tex, z, light_direction, ambient)
            self._upload(self._rest)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ setup
    def _build_scene(
        self, tex: np.ndarray, z: np.ndarray, light_direction: Any, ambient: float
    ) -> None:
        ns = self._ns
        pr = ns.pyrender
        GL = ns.GL
        zmin, zmax = float(z.min()), float(z.max())
        extent = float(np.ptp(self._rest, axis=0).max())
        znear = 0.5 * zmin
        zfar = 2.0 * zmax + extent
        self._znear, self._zfar = znear, zfar
        self._gl_camera = ns.OpenCVCamera(self.camera, znear, zfar)

        sampler = pr.Sampler(
            magFilter=GL.GL_LINEAR,
            minFilter=GL.GL_LINEAR_MIPMAP_LINEAR,
            wrapS=GL.GL_REPEAT,
            wrapT=GL.GL_REPEAT,
        )
        material = pr.MetallicRoughnessMaterial(
            baseColorFactor=(1.0, 1.0, 1.0, 1.0),
            baseColorTexture=ns.FloatTexture(tex, sampler=sampler),
            metallicFactor=0.0,
            roughnessFactor=1.0,
            doubleSided=True,
        )
        m = self.mesh
        lit = self.lighting == "lit"
        lambert = self.lighting == "lambert"
        nv = len(m.vertices)
        cam_pts = self._to_gl_camera(m.vertices)
        prim = pr.Primitive(
            positions=cam_pts.astype(np.float32),
            normals=np.zeros((nv, 3), np.float32) if lit else None,
            texcoord_0=m.uv.astype(np.float32),
            color_0=np.ones((nv, 4), np.float32) if lambert else None,
            indices=m.triangles.astype(np.uint32),
            material=material,
        )
        self._primitive = prim
        # interleaved layout used by pyrender: position, [normal], texcoord_0, [color_0]
        ncol = {"flat": 5, "lit": 8, "lambert": 9}[self.lighting]
        self._vdata = np.ones((nv, ncol), dtype=np.float32)
        uv_col = 6 if lit else 3
        self._vdata[:, uv_col : uv_col + 2] = m.uv
        bg = self.background
        scene = pr.Scene(bg_color=(bg, bg, bg, 1.0), ambient_light=(ambient,) * 3)
        scene.add(pr.Mesh(primitives=[prim]), pose=np.eye(4))
        scene.add(self._gl_camera, pose=np.eye(4))
        if light_direction is None:
            d_cv = np.array([0.35, 0.45, 1.0])  # from upper left, OpenCV camera frame
        else:
            d_cv = self.camera.R @ np.asarray(light_direction, dtype=np.float64)
        d = np.array([d_cv[0], -d_cv[1], -d_cv[2]])  # OpenGL camera frame
        d /= np.linalg.norm(d)
        self._to_light = -d
        self._ambient = float(ambient)
        if lit:
            # light travels along its node's -z axis
            zax = -d
            xax = np.cross([0.0, 1.0, 0.0], zax)
            if np.linalg.norm(xax) < 1e-6:
                xax = np.cross([1.0, 0.0, 0.0], zax)
            xax /= np.linalg.norm(xax)
            pose = np.eye(4)
            pose[:3, :3] = np.stack([xax, np.cross(zax, xax), zax], axis=1)
            # pyrender's diffuse term: (1 - F) * base * (1 - 0.04) / pi, F = 0.04
            # at normal incidence -> white, facing the light: ambient + diffuse = 0.9
            intensity = max(0.9 - ambient, 0.0) * np.pi / 0.96**2
            scene.add(pr.DirectionalLight(color=np.ones(3), intensity=intensity), pose=pose)
        self._scene = scene
        self._flags = pr.RenderFlags.OFFSCREEN | (0 if lit else pr.RenderFlags.FLAT)
        # first pass uploads mesh and texture to the GPU
        self._draw()
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, prim._buffers[0])
        size = int(GL.glGetBufferParameteriv(GL.GL_ARRAY_BUFFER, GL.GL_BUFFER_SIZE))
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
        if size != self._vdata.nbytes:  # guards the interleaved-layout assumption
            raise RuntimeError(f"unexpected pyrender vertex buffer size {size}")

    def _to_gl_camera(self, X: np.ndarray) -> np.ndarray:
        """World points to OpenGL camera frame (x right, y up, looking along -z), float64."""
        c = X @ self.camera.R.T + self.camera.t
        c[:, 1:] *= -1.0
        return c

    def _make_current(self) -> None:
        if self._platform is None:
            raise RuntimeError("renderer is closed")
        self._platform.make_current()

    def _upload(self, positions: np.ndarray) -> None:
        """Write original-vertex positions (N, 3) into the vertex buffer."""
        GL = self._ns.GL
        cam_pts = self._to_gl_camera(self.mesh.expand(positions))
        self._vdata[:, :3] = cam_pts
        if self.lighting != "flat":
            n = _vertex_normals(cam_pts, self.mesh.triangles)
            # two-sided lighting: normals face the camera (at the origin)
            n *= np.where(np.einsum("ij,ij->i", n, cam_pts) > 0, -1.0, 1.0)[:, None]
            if self.lighting == "lit":
                self._vdata[:, 3:6] = n
            else:  # per-vertex Lambert, interpolated across faces, times the texture
                k = max(0.9 - self._ambient, 0.0)
                shade = self._ambient + k * np.clip(n @ self._to_light, 0.0, None)
                self._vdata[:, 5:8] = shade[:, None]
        self._make_current()
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._primitive._buffers[0])
        GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, self._vdata.nbytes, self._vdata)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)

    def _draw(self, read_depth: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        self._make_current()
        self._renderer.read_depth = read_depth
        return self._renderer.render(self._scene, self._flags)

    # ------------------------------------------------------------------ public
    @property
    def shape(self) -> tuple[int, int]:
        """Output image shape ``(height, width)``."""
        return (self.camera.height, self.camera.width)

    def render(self, displacement: Any = None) -> np.ndarray:
        """Render one frame.

        Parameters
        ----------
        displacement : array_like, shape (N, 3), optional
            World-frame displacement of every original vertex; ``None`` renders
            the rest pose.

        Returns
        -------
        ndarray, shape (H, W), float32
            Grayscale intensities in ``[0, 1]``.
        """
        if displacement is None:
            if not self._uploaded_rest:
                self._upload(self._rest)
                self._uploaded_rest = True
        else:
            d = np.asarray(displacement, dtype=np.float64)
            if d.shape != self._rest.shape:
                raise ValueError(f"displacement must have shape {self._rest.shape}")
            self._upload(self._rest + d)
            self._uploaded_rest = False
        color, _ = self._draw()
        return np.array(color, dtype=np.float32)

    def _rest_depth(self) -> tuple[np.ndarray, np.ndarray]:
        """Metric z-depth of the rest pose at supersampled and output resolution."""
        if self._rest_depth_cache is None:
            if not self._uploaded_rest:
                self._upload(self._rest)
                self._uploaded_rest = True
            _, zbuf = self._draw(read_depth=True)
            n, f = self._znear, self._zfar
            zb = zbuf.astype(np.float64)
            bg = zb >= 1.0
            ndc = 2.0 * zb - 1.0
            hi = 2.0 * f * n / (f + n - ndc * (f - n))
            hi[bg] = np.inf
            # output pixel = depth at its centre: the mean of the s x s block's
            # central samples (one for odd s, 2 x 2 for even s); inf if any is
            # background.
            s = self.supersample
            h, w = self.shape
            blocks = hi.reshape(h, s, w, s)
            c = slice((s - 1) // 2, s // 2 + 1)
            lo = blocks[:, c, :, c].mean(axis=(1, 3))
            self._rest_depth_cache = (hi.astype(np.float32), lo.astype(np.float32))
        return self._rest_depth_cache

    def depth(self) -> np.ndarray:
        """Metric depth (camera-frame ``z``) of the rest pose, ``inf`` on background.

        Returns
        -------
        ndarray, shape (H, W), float32
            Depth at each output pixel centre (for even ``supersample`` the mean
            of the four supersamples around it).  Cached.
        """
        return self._rest_depth()[1].copy()

    def visible_vertices(self, tolerance: float | None = None) -> np.ndarray:
        """Which original vertices are seen by the camera in the rest pose.

        A vertex is visible if it projects inside the image
        (``-0.5 <= u < W - 0.5``, same for ``v``) and its depth is at most
        ``tolerance`` behind the rendered depth at the nearest supersampled
        pixel.

        Parameters
        ----------
        tolerance : float, optional
            Depth tolerance in world units; default 1% of the mesh's bounding
            box diagonal.

        Returns
        -------
        ndarray, shape (N,), bool
        """
        if tolerance is None:
            tolerance = 0.01 * float(np.linalg.norm(np.ptp(self._rest, axis=0)))
        hi, _ = self._rest_depth()
        cam = self.camera
        uv = cam.project(self._rest)
        z = cam.depth(self._rest)
        s = self.supersample
        inside = (
            (uv[:, 0] >= -0.5)
            & (uv[:, 0] < cam.width - 0.5)
            & (uv[:, 1] >= -0.5)
            & (uv[:, 1] < cam.height - 0.5)
            & (z > 0)
        )
        # supersampled pixel containing the point
        col = np.clip(np.floor(s * (uv[:, 0] + 0.5)), 0, hi.shape[1] - 1).astype(np.int64)
        row = np.clip(np.floor(s * (uv[:, 1] + 0.5)), 0, hi.shape[0] - 1).astype(np.int64)
        zmap = hi[row, col].astype(np.float64)
        return inside & (z <= zmap + tolerance)

    def close(self) -> None:
        """Free the GL resources and the EGL context (idempotent)."""
        if self._platform is not None:
            try:
                self._platform.make_current()
                if self._renderer is not None:
                    self._renderer.delete()
            finally:
                # destroy only our context: eglTerminate would also kill other
                # renderers sharing the same EGL display
                from OpenGL.EGL import (
                    EGL_NO_CONTEXT,
                    EGL_NO_SURFACE,
                    eglDestroyContext,
                    eglMakeCurrent,
                )

                p = self._platform
                eglMakeCurrent(p._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
                eglDestroyContext(p._egl_display, p._egl_context)
                self._platform = None
                self._renderer = None
        if self._shader_dir is not None:
            shutil.rmtree(self._shader_dir, ignore_errors=True)
            self._shader_dir = None

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
