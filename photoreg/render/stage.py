"""The render stage of the pipeline: virtual scene, its SDF and G-buffer renderer built once per run
(bad objects fail here, before any frame), then per frame G-buffer -> renderer layers -> composite."""
from __future__ import annotations

import numpy as np

from photoreg.config import Session
from photoreg.kernels.grid import DenseGrid
from photoreg.kernels.raycast import SurfaceMaps, raycast_surface
from photoreg.kernels.transfer import make_direction_set
from photoreg.render.composite import Layers, RenderInput, composite
from photoreg.render.gbuffer import GBufferRenderer
from photoreg.render.registry import get_renderer
from photoreg.render.scene import load_scene, voxel_grid
from photoreg.types import Intrinsics

SUPERSAMPLE = 2  # G-buffer subsamples per pixel edge (anti-aliased object edges)


class RenderStage:
    """Inserts the session's objects into frames; `last` holds the latest frame's Layers and `last_input`
    its RenderInput (to run other renderers on the same frame: the renderer contract test, benchmarks)."""

    def __init__(self, session: Session, intrinsics: Intrinsics, device: str):
        self.session, self.intrinsics = session, intrinsics
        self.renderer = get_renderer(session.render.shadows)
        self.scene = load_scene(session.objects)
        self.virtual = voxel_grid(self.scene, session.reconstruction.voxel_size, device)
        self.gbuffer = GBufferRenderer(self.scene, intrinsics, SUPERSAMPLE)
        self._dirs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.last: Layers | None = None
        self.last_input: RenderInput | None = None

    def directions(self, bands: int) -> tuple[np.ndarray, np.ndarray]:
        """The ray set for `bands`, made once (same rays and seed as the lighting solve)."""
        if bands not in self._dirs:
            self._dirs[bands] = make_direction_set(self.session.lighting.rays, bands, seed=0)
        return self._dirs[bands]

    def __call__(self, camera: np.ndarray, sensor_depth: np.ndarray, grid: DenseGrid, maps: SurfaceMaps,
                 pose: np.ndarray, F: np.ndarray, gain: float = 1.0, sun: dict | None = None) -> np.ndarray:
        """Composite (H, W, 3 linear) of one frame: camera linear image, sensor depth (metres, 0 invalid),
        real grid and its stride maps, pose (camera-to-world), lighting F (3, B*B), exposure gain and the
        traced light (SolveDiagnostics.sun) when the solve found one."""
        rc, lc = self.session.reconstruction, self.session.lighting
        surface = raycast_surface(grid, self.intrinsics, pose, rc.depth_min, rc.depth_max, stride=1)
        real_depth = np.where(surface.depth > 0, surface.depth, np.nan_to_num(sensor_depth)).astype(np.float32)
        gb = self.gbuffer.render(pose, real_depth, tolerance=0.5 * rc.voxel_size)
        inp = RenderInput(camera=camera, F=np.asarray(F, np.float64), gain=float(gain), grid=grid,
                          virtual=self.virtual, maps=maps, gbuffer=gb, bounds=self.scene.bounds,
                          directions=self.directions, offset=lc.ray_offset_voxels * rc.voxel_size,
                          ray_length=lc.ray_length, light_rays=self.session.render.light_rays,
                          scene=self.scene, sun=sun, surface=surface)
        self.last_input, self.last = inp, self.renderer(inp)
        return composite(camera, self.last)
