"""The lighting samples' pixel checks on the device: one thread per (strided) ray-cast map pixel.

The GPU's path to what the host computes with preprocess.strided_box and lighting.samples.agreement (why the
checks exist: that module's docstring), with the same flags and radiance to float rounding
(tests/test_pipeline.py). For the map pixel (r, c), at image pixel (r * stride, c * stride):
- radiance: the linear colour (the 8-bit sRGB frame through io.images' table, on the device: a quarter of the
  float colour's bytes to upload) averaged over an odd box (lighting.sample_box; stride | 1 by default) centred
  there, mirrored at the image border (OpenCV's BORDER_REFLECT); a box of 1 is the pixel's own;
- CANDIDATE: the whole box is usable (colour neither saturated nor black, depth valid; or clipped, where the
  usable map says so: lighting.censored) and the ray cast found a surface there;
- CLIPPED: a candidate whose box holds clipped pixels alone (its radiance is a lower bound);
- AGREES: the fused surface agrees with the frame's depth map: depth within `max_gap` metres, normal within the
  angle of `min_cos` of the depth map's (central differences over `step` pixels, float64 like the host's; none
  where a neighbour is missing or off the image).
On an H100 the samples of a held frame took 1.4 ms this way against 2.4 ms on the host (TUM, stride 4; the box
filter of the whole image and the checks of the candidates drawn); on the CPU, Warp's scalar code is no faster
than OpenCV's and numpy's at stride 4 and 2-2.5x slower at stride 1, so the CPU keeps the host path
(Pipeline.sample_kernel).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from photoreg.device import init_warp
from photoreg.io.images import SRGB_TO_LINEAR
from photoreg.kernels.launch import launch_rows
from photoreg.kernels.packing import Packed, upload
from photoreg.types import Intrinsics

wp = init_warp()

CANDIDATE = wp.constant(1)
AGREES = wp.constant(2)
CLIPPED = wp.constant(4)


@dataclass
class SampleMaps:
    """Per map pixel (h, w) at image pixels (r * stride, c * stride)."""

    radiance: np.ndarray   # (h, w, 3) float32 linear colour, box-averaged (module docstring); 0 without a surface
    flags: np.ndarray      # (h, w) uint8: CANDIDATE | AGREES | CLIPPED bits


@wp.func
def _mirror(i: int, n: int) -> int:
    """OpenCV's BORDER_REFLECT index (fedcba|abcdefgh|hgfedcb) for reaches shorter than the image."""
    j = i
    if j < 0:
        j = -j - 1
    if j >= n:
        j = 2 * n - 1 - j
    return j


@wp.func
def _back_project(depth: wp.array2d(dtype=wp.float32), r: int, c: int, fx: wp.float64, fy: wp.float64,
                  cx: wp.float64, cy: wp.float64) -> wp.vec3d:
    """Camera-frame point of pixel (r, c) (z 0 where the pixel is off the image or without depth)."""
    z = wp.float64(0.0)
    if r >= 0 and r < depth.shape[0] and c >= 0 and c < depth.shape[1]:
        z = wp.float64(depth[r, c])
        if not wp.isfinite(z):
            z = wp.float64(0.0)
    return wp.vec3d((wp.float64(c) - cx) / fx * z, (wp.float64(r) - cy) / fy * z, z)


@wp.kernel
def _sample_maps(srgb: wp.array2d(dtype=wp.vec3ub), table: wp.array(dtype=wp.float32),
                 usable: wp.array2d(dtype=wp.uint8),
                 depth: wp.array2d(dtype=wp.float32), surface_depth: wp.array2d(dtype=wp.float32),
                 surface_normal: wp.array2d(dtype=wp.vec3), world_to_cam: wp.mat33d, fx: wp.float64,
                 fy: wp.float64, cx: wp.float64, cy: wp.float64, stride: int, half: int, step: int,
                 min_cos: wp.float64, max_gap: wp.float32, row0: int,
                 radiance: wp.array2d(dtype=wp.vec3), flags: wp.array2d(dtype=wp.uint8)):
    tr, tc = wp.tid()
    r = row0 + tr
    y, x = r * stride, tc * stride
    zs = surface_depth[r, tc]
    if zs <= 0.0:   # no surface: no sample (a third of TUM's pixels), no box to average
        radiance[r, tc] = wp.vec3(0.0, 0.0, 0.0)
        flags[r, tc] = wp.uint8(0)
        return
    h, w = srgb.shape[0], srgb.shape[1]
    total = wp.vec3(0.0, 0.0, 0.0)
    whole = int(1)
    clipped = CLIPPED
    for dy in range(-half, half + 1):
        yy = _mirror(y + dy, h)
        for dx in range(-half, half + 1):
            xx = _mirror(x + dx, w)
            p = srgb[yy, xx]
            total = total + wp.vec3(table[int(p[0])], table[int(p[1])], table[int(p[2])])
            u = usable[yy, xx]
            if u == wp.uint8(0):
                whole = 0
            if u != wp.uint8(2):
                clipped = 0
    k = 2 * half + 1
    radiance[r, tc] = total / float(k * k)
    out = int(0)
    if whole == 1:
        out = CANDIDATE | clipped
        z = depth[y, x]
        if wp.abs(z - zs) <= max_gap and z > 0.0:
            # the depth map's normal: cross product of the row and column differences, negated to face the camera
            right = _back_project(depth, y, x + step, fx, fy, cx, cy)
            left = _back_project(depth, y, x - step, fx, fy, cx, cy)
            below = _back_project(depth, y + step, x, fx, fy, cx, cy)
            above = _back_project(depth, y - step, x, fx, fy, cx, cy)
            a, b = right - left, below - above
            n = wp.vec3d(a[2] * b[1] - a[1] * b[2], a[0] * b[2] - a[2] * b[0], a[1] * b[0] - a[0] * b[1])
            norm = wp.length(n)
            zero = wp.float64(0.0)
            if right[2] > zero and left[2] > zero and below[2] > zero and above[2] > zero and norm > zero:
                ns = surface_normal[r, tc]
                cam = world_to_cam @ wp.vec3d(wp.float64(ns[0]), wp.float64(ns[1]), wp.float64(ns[2]))
                if wp.dot(n / norm, cam) >= min_cos:
                    out = out | AGREES
    flags[r, tc] = wp.uint8(out)


@lru_cache(maxsize=None)
def _table(device: str):
    """io.images.SRGB_TO_LINEAR on `device` (uploaded once)."""
    return wp.array(SRGB_TO_LINEAR, dtype=wp.float32, device=device)


def sample_maps(colour: np.ndarray, usable: np.ndarray, depth: np.ndarray, intr: Intrinsics, pose: np.ndarray,
                maps, max_angle_deg: float, max_gap: float, device: str, box: int = 0,
                clipped: np.ndarray | None = None) -> SampleMaps:
    """Box radiance and CANDIDATE / AGREES / CLIPPED flags (module docstring) at the pixels of the ray-cast `maps`
    (photoreg.kernels.raycast.SurfaceMaps, on `device`) of a frame: `colour` (H, W, 3) uint8 sRGB (the radiance is
    io.images.srgb_to_linear's, no lighting.denoise), `usable` (H, W) bool, `depth` (H, W) float32 metres (0
    invalid), camera-to-world `pose`; an odd `box` of pixels (0: stride | 1); `clipped` (H, W) bool
    (lighting.censored; None: none) the pixels a box may also hold. The depth map's normal spans max(2, stride)
    pixels."""
    codes = np.ascontiguousarray(usable).view(np.uint8)   # 0 unusable, 1 usable, 2 clipped
    if clipped is not None:
        codes = codes + 2 * np.ascontiguousarray(clipped).view(np.uint8)
    st = maps.stride
    h, w = maps.depth.shape
    box = box or (st | 1)
    if box // 2 >= min(depth.shape):
        raise ValueError(f"sample_maps: a {box}-pixel box does not fit a {depth.shape[1]}x{depth.shape[0]} frame")
    rot = np.asarray(pose, dtype=np.float64)[:3, :3]
    # the frame's arrays one by one: contiguous already (packing them would copy 2.4 MB more on the host)
    colour_wp, codes_wp, depth_wp = upload([colour, codes, depth], [wp.vec3ub, wp.uint8, wp.float32], device,
                                           pack=False)
    out = Packed([((h, w), wp.vec3), ((h, w), wp.uint8)], device)   # radiance, flags: one read-back
    launch_rows(_sample_maps, (h, w), device=device,
                inputs=[colour_wp, _table(device), codes_wp, depth_wp, maps.depth_wp, maps.normal_wp,
                        wp.mat33d(*rot.T.ravel()), float(intr.fx), float(intr.fy),
                        float(intr.cx), float(intr.cy), st, box // 2, max(2, st),
                        math.cos(math.radians(max_angle_deg)), float(max_gap)],
                outputs=out.arrays)
    return SampleMaps(*out.numpy())
