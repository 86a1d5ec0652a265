"""The render stage of the pipeline: virtual scene, its SDF and G-buffer renderer built once per run
(bad objects fail here, before any frame), then per frame G-buffer -> renderer layers -> composite."""
from __future__ import annotations

import time

import numpy as np

from photoreg.config import SHUTTER_CAMERA, Session
from photoreg.kernels.grid import DenseGrid
from photoreg.kernels.raycast import SurfaceMaps, raycast_surface
from photoreg.kernels.transfer import make_direction_set
from photoreg.render.composite import Layers, RenderInput, composite
from photoreg.render.gbuffer import GBufferRenderer
from photoreg.render.motion_blur import blurred_composite, motion
from photoreg.render.registry import get_renderer
from photoreg.render.scene import load_scene, voxel_grid
from photoreg.types import Intrinsics

SUPERSAMPLE = 2  # G-buffer subsamples per pixel edge (anti-aliased object edges)


class RenderStage:
    """Inserts the session's objects into frames; `last` holds the latest frame's Layers and `last_input`
    its RenderInput (to run other renderers on the same frame: the renderer contract test, benchmarks)."""

    def __init__(self, session: Session, intrinsics: Intrinsics, device: str):
        self.session, self.intrinsics, self.device = session, intrinsics, device
        self.stride = session.render.stride
        self.renderer = get_renderer(session.render.shadows)
        self.scene = load_scene(session.objects)
        self.virtual = voxel_grid(self.scene, session.reconstruction.voxel_size, device)
        self.gbuffer = GBufferRenderer(self.scene, intrinsics, SUPERSAMPLE, device, session.render.gbuffer)
        lo, hi = self.scene.bounds   # the objects' box's corners (window)
        self._corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        self._dirs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.last: Layers | None = None
        self.last_input: RenderInput | None = None
        # box outside which the latest composite is the camera frame: its Layers.region, grown by the motion blur
        self.region: tuple[int, int, int, int] | None = None
        self._previous: tuple[float, np.ndarray] | None = None  # (timestamp, pose) of the latest frame rendered
        self.in_view = False   # whether a pixel of the latest frame shows an object (after the real occlusion)

    def directions(self, bands: int) -> tuple[np.ndarray, np.ndarray]:
        """The ray set for `bands`, made once (same rays and seed as the lighting solve)."""
        if bands not in self._dirs:
            self._dirs[bands] = make_direction_set(self.session.lighting.rays, bands, seed=0)
        return self._dirs[bands]

    def window(self, pose: np.ndarray) -> tuple[int, int, int, int]:
        """Pixel box (x0, y0, x1, y1) (x1, y1 exclusive; empty when x1 <= x0 or y1 <= y0) holding the projection
        of the objects' bounding box, widened by one render stride and a pixel (the reach of the seam band,
        composite.refine_seam); the whole frame when a corner of that box is not in front of the camera."""
        W, H = self.intrinsics.width, self.intrinsics.height
        cam = (self._corners - pose[:3, 3]) @ pose[:3, :3]          # world -> camera (pose is camera-to-world)
        if not np.all(cam[:, 2] > self.session.reconstruction.depth_min):
            return 0, 0, W, H
        uv = cam[:, :2] / cam[:, 2:] @ np.diag([self.intrinsics.fx, self.intrinsics.fy]) + [self.intrinsics.cx,
                                                                                             self.intrinsics.cy]
        m = self.stride + 1
        x0, y0 = np.clip(np.floor(uv.min(axis=0)).astype(int) - m, 0, [W, H])
        x1, y1 = np.clip(np.ceil(uv.max(axis=0)).astype(int) + m + 1, 0, [W, H])
        return int(x0), int(y0), int(x1), int(y1)

    def __call__(self, camera: np.ndarray, sensor_depth: np.ndarray, grid: DenseGrid, maps: SurfaceMaps | None,
                 pose: np.ndarray, F: np.ndarray, gain: float = 1.0, sun: dict | None = None,
                 timings: dict[str, float] | None = None, timestamp: float | None = None,
                 shutter: float | None = None) -> np.ndarray:
        """Composite (H, W, 3 linear) of one frame: camera linear image, sensor depth (metres, 0 invalid),
        real grid and the frame's ray-cast maps (used when at the render stride, render.stride; else, or with
        None, the stage casts its own), pose (camera-to-world), lighting F (3, B*B), exposure gain and the
        traced light (SolveDiagnostics.sun) when the solve found one. `timings`: gets the ms of its parts,
        'render gbuffer' (the surface ray casts: the window's at every pixel, the render stride's when the frame's
        maps are at another; and the G-buffer), 'render shadows' (the renderer) and 'render composite' (host time;
        each part ends on its own read-back, so a device's work lands in it). `timestamp` (seconds): the frame's
        time, which with the previous frame's gives the camera's motion the insertion is blurred by over the shutter
        time: render.shutter where it is a number, else `shutter` seconds (Frame.shutter; None: sharp)
        (render.motion_blur; `region` then grows)."""
        t0 = time.perf_counter()
        rc, lc = self.session.reconstruction, self.session.lighting
        x0, y0, x1, y1 = self.window(pose)
        if maps is None or maps.stride != self.stride:
            maps = raycast_surface(grid, self.intrinsics, pose, rc.depth_min, rc.depth_max, stride=self.stride,
                                   normal_smoothing=rc.normal_smoothing_voxels)
        real_depth = np.zeros(sensor_depth.shape, np.float32)   # the G-buffer reads its window alone
        surface = None
        if x1 > x0 and y1 > y0:   # the real surface at every pixel of the window: what hides the objects, the seam
            surface = raycast_surface(grid, self.intrinsics.cropped(x0, y0, x1, y1), pose, rc.depth_min,
                                      rc.depth_max, stride=1, normal_smoothing=rc.normal_smoothing_voxels)
            real_depth[y0:y1, x0:x1] = np.where(surface.depth > 0, surface.depth,
                                                np.nan_to_num(sensor_depth[y0:y1, x0:x1]))
        gb = self.gbuffer.render(pose, real_depth, tolerance=0.5 * rc.voxel_size, window=(x0, y0, x1, y1))
        self.in_view = bool((gb.coverage[gb.box] > 0).any())
        inp = RenderInput(camera=camera, F=np.asarray(F, np.float64), gain=float(gain), grid=grid,
                          virtual=self.virtual, maps=maps, gbuffer=gb, bounds=self.scene.bounds,
                          directions=self.directions, offset=lc.ray_offset_voxels * rc.voxel_size,
                          ray_length=lc.ray_length, light_rays=self.session.render.light_rays,
                          scene=self.scene, sun=sun, surface=surface, surface_origin=(x0, y0))
        t1 = time.perf_counter()
        self.last_input, self.last = inp, self.renderer(inp)
        for k in self.scene.containing(pose[:3, 3]):
            self.last.notes.append(f"the camera is inside object {k} ({self.scene.objects[k].source}): the frame shows "
                                   "the object from within (check its position and scale)")
        t2 = time.perf_counter()
        if self.session.render.shutter != SHUTTER_CAMERA:   # the session's overrides the frame's own
            shutter = self.session.render.shutter
        m = None if timestamp is None or shutter is None else motion(pose, timestamp, self._previous, shutter)
        if timestamp is not None:
            self._previous = (timestamp, np.array(pose, dtype=np.float64))
        if m is None:
            out, self.region = composite(camera, self.last), self.last.region
        else:   # the surface each pixel shows: the objects' where they cover it, else the sensor's
            depth = np.array(sensor_depth, dtype=np.float32)
            box, cover = gb.box, gb.coverage[gb.box] > 0.5
            depth[box][cover] = gb.window_depth[cover]
            out, self.region = blurred_composite(camera, self.last, depth, self.intrinsics, m, self.device)
        if timings is not None:
            for part, ms in (("gbuffer", t1 - t0), ("shadows", t2 - t1), ("composite", time.perf_counter() - t2)):
                timings["render " + part] = ms * 1000.0
        return out
