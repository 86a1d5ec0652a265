"""Virtual G-buffer (albedo, depth, world position and normal, coverage), rasterised with pyrender or ray-traced.

Offscreen through OSMesa (CPU) or EGL (GPU): PYOPENGL_PLATFORM is set to 'egl' when unset and an NVIDIA
device is present, else 'osmesa'. The view renders at `supersample` times the camera's resolution with
face indices as flat colours (pyrender resolves its 4x MSAA into the colour buffer, so a blended index
at an edge is caught by checking it against the depth buffer: the face's plane must give the same z).
Each subsample is depth-tested against the real surface (real objects occlude virtual ones); the
pixel's coverage is the share of its subsamples that show a virtual face, and its attributes come
from one of those subsamples (exact geometry: the ray meets the face's plane): that resolve is one Warp kernel
on the renderer's device (photoreg.kernels.gbuffer). The render stage asks only
for the window round the objects' projection (RenderStage.window). One offscreen renderer per size serves
every G-buffer renderer of the process (_offscreen), and every OpenGL call of the process runs on one thread
(_on_gl): a GL context is current in one thread at a time, and pyrender's EGL platform asserts that making its
context current succeeds, which fails while another thread holds it (pipelines in several threads: the server's
connections with `--threads`).

The `raycast` backend (render.gbuffer) makes the same layers with no draw and no OpenGL: each subsample's ray meets the
faces in a Warp mesh on the renderer's device (photoreg.kernels.gbuffer.trace); the edges' coverage then comes from the
subsamples' exact rays instead of the rasteriser's rules.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from photoreg.config import GBUFFER_BACKENDS
from photoreg.io.poses import check_pose
from photoreg.kernels.gbuffer import Faces, Varying, resolve, trace
from photoreg.render.scene import VirtualScene
from photoreg.types import Intrinsics

Z_NEAR, Z_FAR = 0.01, 100.0
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: y down, z forward -> y up, z backward


class _FullFrame:
    """A G-buffer layer at full resolution: its `window_<name>` field placed in a zero frame, made when first read
    and kept in the instance."""

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, gb: "GBuffer | None", owner=None):
        if gb is None:
            return self
        layer = getattr(gb, "window_" + self.name)
        out = np.zeros(gb.coverage.shape + layer.shape[2:], np.float32)
        out[gb.box] = layer
        gb.__dict__[self.name] = out   # read from the instance from now on (a non-data descriptor)
        return out


@dataclass
class GBuffer:
    """Virtual layers; attributes are zero where coverage is 0. Depth, position, normal and albedo are kept for the
    window alone (`window_*`, what the voxel renderer reads) and made full-resolution when first read (four
    frame-sized arrays zeroed and filled each frame: on the 2-core CPU a G-buffer of TUM with the bunny took
    8.2-10.6 ms with the window's alone against 11.5-12.4)."""

    coverage: np.ndarray   # (H, W) float32 in [0, 1]: share of the pixel showing a virtual surface
    window: tuple[int, int, int, int]  # pixel box (x0, y0, x1, y1; x1, y1 exclusive) holding every covered pixel
    window_depth: np.ndarray     # (h, w) float32 camera z in metres, 0 = none, over the window
    window_position: np.ndarray  # (h, w, 3) float32 world point
    window_normal: np.ndarray    # (h, w, 3) float32 world unit normal, facing the camera
    window_albedo: np.ndarray    # (h, w, 3) float32 linear RGB

    @property
    def box(self) -> tuple[slice, slice]:
        """The window as (rows, columns) slices: the layers' only non-zero part."""
        x0, y0, x1, y1 = self.window
        return slice(y0, y1), slice(x0, x1)

    depth = _FullFrame()     # (H, W) float32 camera z in metres, 0 = none
    position = _FullFrame()  # (H, W, 3) float32 world point
    normal = _FullFrame()    # (H, W, 3) float32 world unit normal, facing the camera
    albedo = _FullFrame()    # (H, W, 3) float32 linear RGB


def _import_pyrender():
    """pyrender with an offscreen platform chosen (FACTS.md: np.infty alias under numpy 2)."""
    if "PYOPENGL_PLATFORM" not in os.environ:
        os.environ["PYOPENGL_PLATFORM"] = "egl" if Path("/dev/nvidia0").exists() else "osmesa"
    if not hasattr(np, "infty"):
        np.infty = np.inf
    import pyrender

    return pyrender


_OFFSCREEN: dict[tuple[int, int], tuple[object, bool]] = {}
_GL: list[ThreadPoolExecutor] = []   # the process's GL thread, made on first use
_GL_LOCK = threading.Lock()


def _on_gl(job, *args) -> Future:
    """Run job(*args) on the process's GL thread, where every OpenGL call goes: the offscreen renderers' contexts
    are made and current there, and pipelines in other threads take turns on it."""
    with _GL_LOCK:
        if not _GL:
            _GL.append(ThreadPoolExecutor(1, thread_name_prefix="photoreg-gl"))
    return _GL[0].submit(job, *args)


class _ContextPrograms:
    """A pyrender renderer's shader program cache, keyed by the shaders and their defines alone. pyrender's own
    (ShaderProgramCache) adds OpenGL.contextdata.getContext() to the key, which under OSMesa is a new ctypes pointer
    object at every call: every frame missed the cache, compiled its shader again and kept the old program (TUM with
    the bunny on the 2-core CPU: 300 G-buffers, 300 programs, 258 MB more resident memory). One OffscreenRenderer
    draws in one context, so the context adds nothing to the key of its cache."""

    def __init__(self, cache):
        self._cache, self._programs = cache, {}

    def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
        key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted((defines or {}).items())))
        if key not in self._programs:
            self._programs[key] = self._cache.get_program(vertex_shader, fragment_shader, geometry_shader, defines)
        return self._programs[key]

    def clear(self):
        self._programs = {}
        self._cache.clear()


def _single_sample(renderer) -> None:
    """Makes a pyrender Renderer draw offscreen into single-sample buffers. With framebuffer objects (EGL) it draws
    into 4x multisampled ones and blits them with GL_LINEAR, which averages the codes of neighbouring faces along
    their shared edges into the code of neither: the resolve drops those pixels (a quarter of TUM's bunny on an H200,
    the cube's top face on Mesa's EGL; OSMesa, without framebuffer objects, never did). The swap of pyrender's
    glRenderbufferStorageMultisample lasts one call on the GL thread, where every pyrender call runs."""
    import pyrender.renderer as module

    configure = renderer._configure_main_framebuffer

    def single() -> None:
        multisample = module.glRenderbufferStorageMultisample
        module.glRenderbufferStorageMultisample = lambda target, samples, fmt, w, h: module.glRenderbufferStorage(
            target, fmt, w, h)
        try:
            configure()
        finally:
            module.glRenderbufferStorageMultisample = multisample

    renderer._configure_main_framebuffer = single


def _offscreen(pr, width: int, height: int) -> tuple[object, bool]:
    """The process's offscreen renderer of this size and whether it may change its viewport, made once (on the GL
    thread) and never deleted: pyrender's EGL platform terminates the display, which every renderer of a process
    shares, when one renderer is deleted (the next pipeline's first frame then failed with EGL_NOT_INITIALIZED on an
    H100). EGL renders into framebuffer objects of any size; OSMesa would make a new context for every new viewport
    size (pyrender picks the platform from PYOPENGL_PLATFORM when the renderer is made)."""
    if (width, height) not in _OFFSCREEN:
        gl = pr.OffscreenRenderer(width, height)
        gl._renderer._program_cache = _ContextPrograms(gl._renderer._program_cache)
        _single_sample(gl._renderer)
        _OFFSCREEN[(width, height)] = (gl, os.environ.get("PYOPENGL_PLATFORM") == "egl")
    return _OFFSCREEN[(width, height)]


VIEWPORT_STEP = 128   # with EGL a viewport's sides are multiples of this (supersampled pixels)


def _pow2(n: int) -> int:
    """The smallest power of two >= n (at least 64)."""
    return max(64, 1 << (int(n) - 1).bit_length())


class GBufferRenderer:
    """Rasterises (backend 'pyrender': keeps its GL context across frames) or ray-traces ('raycast') one virtual
    scene for one camera model. `device`: where the draw is resolved or the rays traced (the pipeline's)."""

    def __init__(self, scene: VirtualScene, intr: Intrinsics, supersample: int = 2, device: str = "cpu",
                 backend: str = "pyrender"):
        if supersample < 1:
            raise ValueError(f"GBufferRenderer: supersample must be >= 1, got {supersample}")
        if backend not in GBUFFER_BACKENDS:
            raise ValueError(f"GBufferRenderer: backend must be one of {GBUFFER_BACKENDS}, got {backend!r}")
        self.backend = backend
        self.intr, self.s = intr.check("GBufferRenderer"), int(supersample)
        self.hi = intr.scaled(self.s)
        verts, faces, owner = scene.triangles()
        tri = verts[faces]                                            # (F, 3, 3)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        keep = length[:, 0] > 0                                       # degenerate faces cannot be hit
        albedo = np.stack([o.albedo for o in scene.objects])[owner[keep]]
        fa = scene.face_attributes()
        self.faces = Faces(tri[keep, 0], n[keep] / length[keep], albedo, device,   # on the resolve's device
                           tri[keep] if backend == "raycast" else None,
                           Varying(tri[keep], fa.source[keep], fa.smooth[keep], fa.uv[keep], fa.corners[keep],
                                   fa.normals[keep], fa.textures, device) if fa.varies()[keep].any() else None)
        if backend == "raycast":
            return
        self.pr = _import_pyrender()
        ids = np.arange(1, keep.sum() + 1)
        code = np.stack([ids & 255, (ids >> 8) & 255, (ids >> 16) & 255, np.full_like(ids, 255)], -1)
        self._triangles = tri[keep].reshape(-1, 3).astype(np.float32), np.repeat(code.astype(np.float32) / 255.0, 3, 0)
        self.gl, self.gl_windows = _on_gl(_offscreen, self.pr, self.hi.width, self.hi.height).result()
        self._views: dict = {}   # used on the GL thread alone

    def _view(self, size: tuple[int, int]):
        """(scene, camera, camera node, renderer) drawing a viewport of `size` pixels: with EGL one scene and the
        frame's renderer serve every size; with OSMesa, whose viewport is its context's, a renderer of that size
        (_offscreen) and a scene of its own (pyrender binds a mesh to the first context that draws it)."""
        key = None if self.gl_windows else size
        if key not in self._views:
            positions, colors = self._triangles
            scene = self.pr.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[1.0, 1.0, 1.0])
            scene.add(self.pr.Mesh([self.pr.Primitive(positions=positions, color_0=colors,
                                                      mode=self.pr.constants.GLTF.TRIANGLES)]))
            # pyrender's pixel centres sit at +0.5 (OpenGL); OpenCV's at integers (cx, cy are set per render)
            cam = self.pr.IntrinsicsCamera(self.hi.fx, self.hi.fy, self.hi.cx + 0.5, self.hi.cy + 0.5, Z_NEAR, Z_FAR)
            node = scene.add(cam, pose=np.eye(4))
            gl = self.gl if self.gl_windows else _offscreen(self.pr, *size)[0]
            self._views[key] = scene, cam, node, gl
        return self._views[key]

    def viewport(self, w: int, h: int) -> tuple[int, int]:
        """The viewport (width, height) that draws a window of w x h pixels (render), at most the supersampled frame:
        with EGL its sides rounded up to VIEWPORT_STEP, with OSMesa (a context per size) to powers of two. pyrender
        reads back and converts the whole viewport: TUM's windows round the bunny (some 300 x 320 pixels, 600 x 640
        supersampled) read 1024 x 960 as powers of two, 640 x 640 in steps."""
        full = (self.intr.width * self.s, self.intr.height * self.s)
        side = (lambda n: -(-n // VIEWPORT_STEP) * VIEWPORT_STEP) if self.gl_windows else _pow2
        return min(side(w * self.s), full[0]), min(side(h * self.s), full[1])

    def _draw(self, pose: np.ndarray, size: tuple[int, int], vx: int, vy: int) -> tuple[np.ndarray, np.ndarray]:
        """(colour, depth buffer) of the view from `pose` into a viewport of `size` whose corner is the supersampled
        pixel (vx, vy); on the GL thread."""
        scene, cam, node, gl = self._view(size)
        scene.set_pose(node, pose @ OPENCV_TO_OPENGL)
        gl.viewport_width, gl.viewport_height = size
        cam.cx, cam.cy = self.hi.cx + 0.5 - vx, self.hi.cy + 0.5 - vy
        return gl.render(scene, flags=self.pr.RenderFlags.FLAT)

    def render(self, pose_c2w: np.ndarray, real_depth: np.ndarray | None = None, tolerance: float = 0.005,
               window: tuple[int, int, int, int] | None = None) -> GBuffer:
        """G-buffer of the view from pose (4x4 camera-to-world, OpenCV); virtual surfaces farther than
        real_depth (H, W metres, 0 = unknown) + tolerance are hidden. With `window` (x0, y0, x1, y1; x1, y1
        exclusive) only that pixel box is read back and resolved (the objects must project inside it; the
        rest of the G-buffer is empty): the per-subsample work is most of the cost on the CPU."""
        pose = check_pose(pose_c2w, "GBufferRenderer.render")
        H, W, s = self.intr.height, self.intr.width, self.s
        x0, y0, x1, y1 = (0, 0, W, H) if window is None else window
        if not (0 <= x0 <= x1 <= W and 0 <= y0 <= y1 <= H):
            raise ValueError(f"GBufferRenderer.render: window {window} is not a pixel box of the {W}x{H} frame")
        h, w = y1 - y0, x1 - x0
        # Only the window is rasterised and read back, into a viewport of rounded sides at least its size (at most
        # the frame's; the window in its top-left corner; `viewport`): EGL resizes its framebuffer only when that
        # size changes, and OSMesa, which makes a context per size, gets a renderer per size of the few there
        # are (TUM with the bunny on this CPU: 18-25 ms a frame for the whole 1280 x 960 supersampled frame before).
        real = np.zeros((h, w), np.float32)   # 0: no real surface known
        if real_depth is not None:
            real_depth = np.asarray(real_depth, np.float32)
            if real_depth.shape != (H, W):
                raise ValueError(f"GBufferRenderer.render: real_depth is {real_depth.shape}, expected {(H, W)}")
            real = real_depth[y0:y1, x0:x1]
        if h == 0 or w == 0:   # nothing to draw
            empty = np.zeros((h, w, 3), np.float32)
            return GBuffer(np.zeros((H, W), np.float32), (x0, y0, x1, y1), np.zeros((h, w), np.float32), empty,
                           empty.copy(), empty.copy())
        if self.backend == "raycast":
            cover, depth, position, normal, albedo = trace(real, s, (x0 * s, y0 * s), self.hi, pose, self.faces,
                                                           tolerance, Z_NEAR, Z_FAR)
        else:
            color, zbuf = _on_gl(self._draw, pose, self.viewport(w, h), x0 * s, y0 * s).result()
            cover, depth, position, normal, albedo = resolve(color[:h * s, :w * s, :3], zbuf[:h * s, :w * s], real,
                                                             s, (x0 * s, y0 * s), self.hi, pose, self.faces, tolerance)
        coverage = np.zeros((H, W), np.float32)
        coverage[y0:y1, x0:x1] = cover
        return GBuffer(coverage, (x0, y0, x1, y1), depth, position, normal, albedo)
