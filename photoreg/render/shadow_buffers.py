"""Shadow-map buffers of Neural Shadow Mapping (Datta et al. 2022): the per-pixel network input.

Receivers are the front-most surface per pixel of the ray-cast real surface (SurfaceMaps, at its stride)
and the virtual G-buffer sampled at the same pixels (virtual where its coverage is at least half).
Channels (CHANNELS), all float32, zero where no receiver:
  view depth       camera z of the receiver, metres
  normal x, y, z   world unit normal (the world's up is +z in every recording, so it carries floor/wall)
  emitter depth    the shadow map's depth at the receiver's projection (nearest texel): the light depth
                   of the virtual surface nearest the light on the receiver's light ray, capped at the
                   receiver's own depth (only the virtual objects are in the map; empty texels read the
                   receiver itself, as a map of the whole scene would)
  receiver depth   the receiver's own light depth (pixel-to-emitter distance)
  cosine + size    n . d plus the light's angular radius in radians (the emitter size as a DC offset)
Light depth is photoreg.kernels.shadowmap's: metres along -d from the map's light plane, which sits just
above the objects (fit_shadow_map), so an unoccluded receiver reads emitter depth = receiver depth.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photoreg.kernels.raycast import SurfaceMaps
from photoreg.kernels.shadowmap import ShadowMap
from photoreg.lighting.parametric import ParametricLight
from photoreg.render.composite import VIRTUAL_COVERAGE, at_stride
from photoreg.render.gbuffer import GBuffer

CHANNELS = ("view_depth", "normal_x", "normal_y", "normal_z", "emitter_depth", "receiver_depth", "cosine_size")
SM_RESOLUTION = 256     # shadow-map texels per side (the map is fitted to the objects' footprint)


@dataclass
class ShadowBuffers:
    data: np.ndarray      # (len(CHANNELS), h, w) float32, the network input
    valid: np.ndarray     # (h, w) bool: a receiver exists
    virtual: np.ndarray   # (h, w) bool: the receiver is a virtual surface
    normal: np.ndarray    # (h, w, 3) float32 world normals of the receivers (0 where none)


def map_depths(smap: ShadowMap, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(receiver light depth, map depth at its nearest texel capped at it), each (N,) float32, of world points
    (N, 3); outside the map or over an empty texel the map depth is the receiver's own."""
    rel = np.asarray(points, np.float64) - smap.corner
    own = -(rel @ smap.d)
    depth = smap.depth.numpy()
    i = np.floor(rel @ smap.u / smap.texel).astype(np.int64)
    j = np.floor(rel @ smap.v / smap.texel).astype(np.int64)
    inside = (i >= 0) & (j >= 0) & (i < depth.shape[0]) & (j < depth.shape[1])
    blocker = np.full(len(own), np.inf)
    blocker[inside] = depth[i[inside], j[inside]]
    return own.astype(np.float32), np.minimum(blocker, own).astype(np.float32)


def receivers(maps: SurfaceMaps, gbuffer: GBuffer) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Front-most receiver per stride pixel: depth (h, w), position (h, w, 3), normal (h, w, 3), valid, virtual."""
    s = maps.stride
    h, w = maps.depth.shape
    cov, gdepth = at_stride(gbuffer.coverage, maps), at_stride(gbuffer.depth, maps)
    if cov.shape != (h, w):
        raise ValueError(f"shadow_buffers: G-buffer {gbuffer.coverage.shape} does not match maps {maps.depth.shape} "
                         f"at stride {s}")
    virtual = (cov >= VIRTUAL_COVERAGE) & (gdepth > 0)
    valid = virtual | maps.valid
    depth = np.where(virtual, gdepth, maps.depth).astype(np.float32)
    pos = np.where(virtual[..., None], at_stride(gbuffer.position, maps), maps.vertex).astype(np.float32)
    nrm = np.where(virtual[..., None], at_stride(gbuffer.normal, maps), maps.normal).astype(np.float32)
    depth[~valid], pos[~valid], nrm[~valid] = 0.0, 0.0, 0.0
    return depth, pos, nrm, valid, virtual


def shadow_buffers(maps: SurfaceMaps, gbuffer: GBuffer, light: ParametricLight, smap: ShadowMap) -> ShadowBuffers:
    """The network input for one frame at the maps' stride (module docstring), with the shadow map of the
    virtual objects from light.direction (photoreg.render.shadowmap.fit_shadow_map)."""
    depth, pos, nrm, valid, virtual = receivers(maps, gbuffer)
    d = np.asarray(light.direction, np.float32)
    e_px, e_sm = map_depths(smap, pos[valid])
    data = np.zeros((len(CHANNELS),) + depth.shape, np.float32)
    data[0] = depth
    data[1:4] = np.moveaxis(nrm, -1, 0)
    data[4][valid] = e_sm
    data[5][valid] = e_px
    data[6][valid] = nrm[valid] @ d + np.float32(light.angle)
    return ShadowBuffers(data=data, valid=valid, virtual=virtual, normal=nrm)
