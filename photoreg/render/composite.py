"""Differential-rendering layers and the compositor (DESIGN.md 'Differential rendering').

Renderers fill `Layers`; `composite` alone blends them with the camera frame, in linear RGB:
  real pixels:    out = cam + rho_hat (F.R_TRV - F.R_TR) = cam * ratio,
                  ratio = 1 + (F.R_TRV - F.R_TR) / max(F.R_TR, eps)   (rho_hat = cam / max(F.R_TR, eps))
  virtual pixels: albedo * F.R_TRV at the virtual point, blended by the anti-aliased coverage alpha.
One ambient bounce (`bounce`): a blocked direction is not black but shows the occluder's mean radiance,
so renderers add L_occluder * (blocked cosine-weighted share) to F.R: the real surface near the objects
lights a virtual cube's sides, and the object (its mean radiance as the camera sees it) lights the floor
beside it. On the demo this cut the composite si-RMSE from 0.096 to 0.085 (real bounce alone: 0.096).
The ratio is clipped to [0, 1]: a virtual object takes away more light than it reflects.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Callable

import cv2
import numpy as np

from photoreg.kernels.grid import DenseGrid
from photoreg.kernels.raycast import SurfaceMaps
from photoreg.lighting import sh
from photoreg.lighting.parametric import ParametricLight, parametric_light, traced_light
from photoreg.render.gbuffer import GBuffer
from photoreg.render.scene import VirtualScene

EPS_REL = 1e-2  # eps = this share of the mean F.R_TR over the shaded real points (per channel)
VIRTUAL_COVERAGE = 0.5  # a pixel shows the virtual surface, not the real one, from this coverage up


@dataclass
class RenderInput:
    """What a renderer may use for one frame."""

    camera: np.ndarray              # (H, W, 3) linear camera frame
    F: np.ndarray                   # (3, B*B) SH lighting in the solver's units
    gain: float                     # exposure gain: camera = gain * rho * F.R
    grid: DenseGrid                 # real geometry (fused TSDF)
    virtual: DenseGrid              # virtual objects' SDF
    maps: SurfaceMaps               # real surface at the lighting stride
    gbuffer: GBuffer                # virtual surface at full resolution (depth-tested)
    bounds: np.ndarray              # (2, 3) world box of the virtual objects
    directions: Callable[[int], tuple[np.ndarray, np.ndarray]]  # bands -> (dirs, Y) ray set
    offset: float                   # ray start offset along the normal, metres
    ray_length: float               # metres
    light_rays: int = 0             # rays over the dominant light's disc (0: the light stays in F's SH)
    scene: VirtualScene | None = None  # the placed objects (renderers that work per object need it)
    sun: dict | None = None         # the light traced from its shadows (SolveDiagnostics.sun), when found
    surface: SurfaceMaps | None = None  # real surface at every pixel (stride 1) of a window: refine_seam (None: none)
    surface_origin: tuple[int, int] = (0, 0)  # the window's top-left pixel (x, y) in the frame

    @cached_property
    def light(self) -> ParametricLight:
        """The frame's parametric light (one per frame, shared by the renderers): the traced light when the
        solve found one (its direction and strength come from the shadows), else a lobe fitted to F along F's
        band 1, an estimate's best observed band (its higher bands pulled a free fit 25 deg off on the demo).
        The frames that hold one estimate (lighting.every, lighting.asynchronous) share one fit (_light)."""
        F = np.ascontiguousarray(self.F, np.float64)
        sun = None if self.sun is None else (tuple(self.sun["direction"]), tuple(self.sun["irradiance"]),
                                             float(self.sun["angle"]))
        return _light(F.tobytes(), F.shape, sun)


@lru_cache(maxsize=8)
def _light(F: bytes, shape: tuple[int, int], sun: tuple | None) -> ParametricLight:
    """RenderInput.light of the lighting F (its float64 bytes and shape) and the traced light (direction, irradiance,
    angle) or None, made once for the frames that hold the same estimate (the lobe fit took 1.4-1.7 ms a frame).
    Shared: read it, do not change it."""
    F = np.frombuffer(F, np.float64).reshape(shape)
    if sun is not None:
        return traced_light(F, np.array(sun[0]), np.array(sun[1]), sun[2])
    return parametric_light(F, sh.dominant_direction(F))


@dataclass
class Layers:
    """A renderer's output: virtual colour (not premultiplied), its alpha, and the ratio on real surfaces."""

    colour: np.ndarray              # (H, W, 3) linear
    alpha: np.ndarray               # (H, W) in [0, 1]
    ratio: np.ndarray               # (H, W, 3): real pixel gets cam * ratio (1 = unchanged)
    notes: list[str] = field(default_factory=list)
    region: tuple[int, int, int, int] | None = None  # box (x0, y0, x1, y1) outside which alpha = 0, ratio = 1
                                                     # (None: anywhere): the compositor blends only inside it


def shade(F: np.ndarray, transfer: np.ndarray) -> np.ndarray:
    """Lambertian shading without albedo, F.R: transfer (N, K) with K <= F's count -> (N, 3)."""
    K = F.shape[1]
    if transfer.shape[1] < K:
        raise ValueError(f"shade: transfer has {transfer.shape[1]} coefficients, lighting {K}")
    return transfer[:, :K] @ F.T


def bounce(shading: np.ndarray, real_radiance: np.ndarray,
           virtual_radiance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-unit shading without albedo under real (R_TR) and real+virtual (R_TRV) occlusion, with one
    ambient bounce, from a ray pass's rows (kernels.transfer.shaded_pass: the lighting's shading under each and the
    blocked shares): directions blocked by real geometry show `real_radiance` (3,), those blocked only by the
    virtual objects `virtual_radiance` (3,); returns (S_TR, S_TRV), each (N, 3)."""
    b_tr, b_trv = shading[:, 6:7], shading[:, 7:8]
    s_tr = shading[:, :3] + b_tr * real_radiance
    return s_tr, shading[:, 3:6] + b_tr * real_radiance + np.maximum(b_trv - b_tr, 0.0) * virtual_radiance


def shadow_ratio(s_tr: np.ndarray, s_trv: np.ndarray) -> np.ndarray:
    """1 + (F.R_TRV - F.R_TR) / max(F.R_TR, eps) in [0, 1], eps guarding where F.R_TR is tiny."""
    if len(s_tr) == 0:
        return np.ones_like(s_tr)
    eps = EPS_REL * np.maximum(np.abs(s_tr).mean(axis=0), 1e-12)
    return np.clip(1.0 + (s_trv - s_tr) / np.maximum(s_tr, eps), 0.0, 1.0).astype(np.float32)


def at_stride(image: np.ndarray, maps: SurfaceMaps) -> np.ndarray:
    """A full-resolution image sampled at the maps' pixels (r * stride, c * stride): shape of maps.depth."""
    h, w = maps.depth.shape
    return image[::maps.stride, ::maps.stride][:h, :w]


def box_distance2(maps: SurfaceMaps, bounds: np.ndarray) -> np.ndarray:
    """Squared distance (float32, stride maps' shape) of each stride pixel's real surface to the objects' box: per
    axis (v clipped to the box - v)^2, summed x, y, z in that order, over the vertex map's channels split apart (the
    same values as broadcasting over its last axis of 3, whose inner loops of 3 took 9x as long; strided views of
    the channels 2x: stride 1 at 640x480, 0.8 against 1.7 and 7.6 ms on the 2-core CPU)."""
    lo, hi = np.asarray(bounds, np.float32)   # float32 like the maps: no float64 copies of a full frame
    d2 = None
    for axis, v in enumerate(cv2.split(maps.vertex)):
        gap = np.clip(v, lo[axis], hi[axis])
        gap -= v
        gap *= gap
        d2 = gap if d2 is None else cv2.add(d2, gap, dst=d2)
    return d2


def near_objects(maps: SurfaceMaps, distance2: np.ndarray, reach: float) -> np.ndarray:
    """Stride pixels whose real surface lies within `reach` of the objects' box (`distance2`: box_distance2 of the
    maps): with reach = ray_length, the only ones a virtual object can shadow."""
    return maps.valid & (distance2 <= np.float32(reach) ** 2)


def stride_box(near: np.ndarray, stride: int, shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1; exclusive) of a full-resolution (H, W) `shape` that holds every pixel whose
    bilinear taps include a `near` stride sample (upsample_ratio's reach); None when no sample is near."""
    H, W = shape
    rows = np.flatnonzero(near.any(axis=1))   # the rows and columns holding one: 0.2 ms at stride 1 at 640x480,
    if len(rows) == 0:                         # np.nonzero's index of every near pixel 0.8
        return None
    cols = np.flatnonzero(near.any(axis=0))
    return (int(max((cols[0] - 1) * stride, 0)), int(max((rows[0] - 1) * stride, 0)),
            int(min((cols[-1] + 1) * stride + 1, W)), int(min((rows[-1] + 1) * stride + 1, H)))


def darkened(ratio_s: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The `mask`'s stride samples whose ratio (stride maps, (h, w, 3)) is not 1 in some channel (the renderers' ratios
    lie in [0, 1]: the samples they darken): the only ones the interpolation (upsample_ratio) and the composite's region
    (stride_box) need, since bilinear taps all 1 give 1 exactly (TUM with the bunny, the voxel renderer: a box of some
    215 x 190 pixels against the near samples' 340 x 280, the composite 1.74 against 2.29 ms on an H100's host)."""
    return mask & (ratio_s != 1.0).any(axis=-1)


def changed_box(inp: RenderInput, shadowed: np.ndarray) -> tuple[int, int, int, int] | None:
    """The box (Layers.region) of what a renderer's layers change: the G-buffer's window (the objects' pixels), the
    seam's (inp.surface's window, where refine_seam and set_seam write) and the pixels interpolated from the
    `shadowed` stride samples (darkened's)."""
    seam = None
    if inp.surface is not None:
        (x0, y0), (h, w) = inp.surface_origin, inp.surface.depth.shape
        seam = (x0, y0, x0 + w, y0 + h)
    return union_box(inp.gbuffer.window, seam, stride_box(shadowed, inp.maps.stride, inp.camera.shape[:2]))


def union_box(*boxes: tuple[int, int, int, int] | None) -> tuple[int, int, int, int] | None:
    """The smallest box (x0, y0, x1, y1) holding every given box; empty ones (x1 <= x0 or y1 <= y0) and None
    hold nothing."""
    boxes = [b for b in boxes if b is not None and b[2] > b[0] and b[3] > b[1]]
    if not boxes:
        return None
    return (min(b[0] for b in boxes), min(b[1] for b in boxes), max(b[2] for b in boxes), max(b[3] for b in boxes))


def upsample_ratio(ratio_s: np.ndarray, near: np.ndarray, stride: int, shape: tuple[int, int],
                   window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Bilinear full-resolution ratio from samples at pixels (r*stride, c*stride), computed only inside
    stride_box of the `near` samples (1 elsewhere); with `window` (x0, y0, x1, y1) only that box of the (H, W)
    `shape` (the same values there)."""
    H, W = shape
    wx0, wy0, wx1, wy1 = (0, 0, W, H) if window is None else window
    out = np.ones((wy1 - wy0, wx1 - wx0, ratio_s.shape[-1]), np.float32)
    box = stride_box(near, stride, shape)
    if box is None:
        return out
    x0, y0, x1, y1 = max(box[0], wx0), max(box[1], wy0), min(box[2], wx1), min(box[3], wy1)
    if x1 <= x0 or y1 <= y0:
        return out
    # output pixel (x, y) samples the stride map at ((x0 + x) / stride, (y0 + y) / stride): an affine map, no
    # coordinate arrays (the same values as cv2.remap over np.mgrid's, half its time)
    to_stride = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0]]) / stride
    out[y0 - wy0:y1 - wy0, x0 - wx0:x1 - wx0] = cv2.warpAffine(
        np.asarray(ratio_s, np.float32), to_stride, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE).reshape(y1 - y0, x1 - x0, -1)
    return out


def seam_band(inp: RenderInput, near: np.ndarray) -> np.ndarray | None:
    """The real pixels, as a mask over inp.surface's window, whose bilinear taps of the interpolated ratio
    (upsample_ratio of the `near` stride samples) include a sample the objects hide (coverage >= VIRTUAL_COVERAGE
    there): that sample's real surface lies under or behind an object, and its ratio, dark there, drew a seam
    along the object's silhouette (demo frame 20 with the true lighting: the pixels just outside the object 10%
    darker than the path tracer's, composite si-RMSE 0.038 against 0.029 for the path-traced object pasted).
    None without inp.surface or where no such pixel is."""
    if inp.surface is None:
        return None
    hidden = near & (at_stride(inp.gbuffer.coverage, inp.maps) >= VIRTUAL_COVERAGE)
    if not hidden.any():
        return None
    (x0, y0), (h, w) = inp.surface_origin, inp.surface.depth.shape
    shown = upsample_ratio(np.where(hidden, 0.0, 1.0)[..., None].astype(np.float32), near, inp.maps.stride,
                           inp.camera.shape[:2], window=(x0, y0, x0 + w, y0 + h))[..., 0]
    band = (shown < 1.0) & (inp.gbuffer.coverage[y0:y0 + h, x0:x0 + w] < 1.0) & inp.surface.valid
    return band if band.any() else None


def set_seam(ratio: np.ndarray, inp: RenderInput, band: np.ndarray, values: np.ndarray) -> None:
    """Write `values` (N, 3), one per pixel of seam_band's `band`, into the full-resolution ratio, in place."""
    (x0, y0), (h, w) = inp.surface_origin, inp.surface.depth.shape
    ratio[y0:y0 + h, x0:x0 + w][band] = values


def refine_seam(ratio: np.ndarray, inp: RenderInput, near: np.ndarray,
                ratio_at: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> None:
    """Replace, in place, the interpolated full-resolution ratio by ratio_at(points, normals) -> (N, 3) at the
    seam_band pixels (needs inp.surface: without it nothing changes; pixels outside its window keep the
    interpolated ratio)."""
    band = seam_band(inp, near)
    if band is not None:
        set_seam(ratio, inp, band, ratio_at(inp.surface.vertex[band], inp.surface.normal[band]))


def layers_of(image: np.ndarray, camera: np.ndarray, mask: np.ndarray) -> Layers:
    """The Layers that composite into `image` (H, W, 3 linear) over `camera` with the objects covering the bool `mask`:
    their colour on the mask, elsewhere the ratio image / camera (1 where the camera is black). Turns an independent
    renderer's insert render into layers (benchmarks of the motion blur, render.motion_blur)."""
    alpha = mask.astype(np.float32)
    safe = camera > 1e-6
    ratio = np.where(safe, image / np.where(safe, camera, 1.0), 1.0)
    ratio[mask] = 1.0
    return Layers(np.where(mask[..., None], image, 0.0).astype(np.float32), alpha, ratio.astype(np.float32))


def composite(camera: np.ndarray, layers: Layers) -> np.ndarray:
    """The one blend: (1 - alpha) * cam * ratio + alpha * colour, linear float32, finite; outside
    layers.region the camera frame itself (the full-frame blend was most of the render stage's host time
    on an H100)."""
    out = np.array(camera, dtype=np.float32)
    if not np.isfinite(out).all():
        np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    H, W = out.shape[:2]
    x0, y0, x1, y1 = layers.region if layers.region is not None else (0, 0, W, H)
    if x1 > x0 and y1 > y0:
        box = slice(y0, y1), slice(x0, x1)
        # alpha as three channels: numpy's broadcast of an (h, w, 1) view over (h, w, 3) ones took 3 of the blend's
        # 3.3 ms on TUM with the bunny (a 325 x 297 box), this 0.6 (the same products: the same bits)
        a = cv2.merge([layers.alpha[box]] * 3)
        # (1 - a) * cam * ratio + a * colour, in that order, in place (no temporaries)
        blend = np.subtract(1.0, a, dtype=np.float32)
        blend *= out[box]
        blend *= layers.ratio[box]
        blend += np.multiply(a, layers.colour[box], out=a)
        if not np.isfinite(blend).all():
            np.nan_to_num(blend, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
        out[box] = blend
    return out
