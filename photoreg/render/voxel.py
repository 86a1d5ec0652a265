"""Renderers of the registry: `voxel` (differential rendering with voxel visibility, Gruber et al. 2012)
and `none` (the object shaded by the unoccluded lighting, no shadows either way)."""
from __future__ import annotations

import numpy as np

from photoreg.kernels.transfer import radiance_transfer
from photoreg.lighting import sh
from photoreg.render.composite import Layers, RenderInput, near_objects, shade, shadow_ratio, upsample_ratio


def _virtual_colour(inp: RenderInput, transfer: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """albedo * F.R * gain at covered pixels (camera units), zero elsewhere."""
    colour = np.zeros(inp.camera.shape, np.float32)
    colour[covered] = inp.gbuffer.albedo[covered] * np.maximum(shade(inp.F, transfer), 0.0) * inp.gain
    return colour


def render_voxel(inp: RenderInput) -> Layers:
    """R_TR / R_TRV in one ray pass at the real surface near the objects (lighting stride, interpolated
    back), and R_TRV at the virtual pixels with real geometry occluding (real shadows on the object)."""
    dirs, Y = inp.directions(sh.bands_of(inp.F.shape[1]))
    maps, gb = inp.maps, inp.gbuffer
    near = near_objects(maps, inp.bounds, inp.ray_length)
    real = radiance_transfer(inp.grid, maps.vertex[near], maps.normal[near], dirs, Y, inp.offset, inp.ray_length,
                             virtual=inp.virtual)
    ratio_s = np.ones(maps.vertex.shape, np.float32)
    ratio_s[near] = shadow_ratio(shade(inp.F, real.transfer), shade(inp.F, real.transfer_rv))
    ratio = upsample_ratio(ratio_s, near, maps.stride, inp.camera.shape[:2])
    covered = gb.coverage > 0
    virt = radiance_transfer(inp.grid, gb.position[covered], gb.normal[covered], dirs, Y, inp.offset,
                             inp.ray_length, virtual=inp.virtual)
    return Layers(_virtual_colour(inp, virt.transfer_rv, covered), gb.coverage, ratio)


def render_none(inp: RenderInput) -> Layers:
    """The object lit by the unoccluded lighting; real pixels unchanged (the 'no shadow' baseline)."""
    covered = inp.gbuffer.coverage > 0
    transfer = sh.unoccluded_transfer(inp.gbuffer.normal[covered], sh.bands_of(inp.F.shape[1]))
    return Layers(_virtual_colour(inp, transfer, covered), inp.gbuffer.coverage,
                  np.ones(inp.camera.shape, np.float32))
