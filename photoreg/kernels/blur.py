"""Motion blur of a composite's layers along each pixel's image motion (photoreg.render.motion_blur).

A pixel's motion b over the shutter comes from the depth of the surface it shows: back-projected, moved into the
previous frame's camera (rotation and translation from this camera to that one), projected, and the displacement
scaled by the shutter's share of the frame interval. The blur averages, at ceil |b| + 1 instants spread evenly along
b (at most `max_samples`), bilinear samples of the frame's factor (1 - alpha) ratio and of the objects' term
alpha colour, and blends them with the pixel's camera colour: out = camera * mean(factor) + mean(term), clamped at 0.
A sample off the box takes the layers' identity (factor 1, term 0), as outside the renderer's region.
"""
from __future__ import annotations

import numpy as np

from photoreg.device import init_warp
from photoreg.kernels.launch import launch_rows
from photoreg.types import Intrinsics

wp = init_warp()


@wp.func
def _motion(depth: wp.array2d(dtype=wp.float32), r: int, c: int, fill: float, x0: int, y0: int, k: wp.vec4,
            rot: wp.mat33, trans: wp.vec3, share: float) -> wp.vec2:
    """Image motion (pixels) over the shutter of pixel (r, c) of the box whose top-left pixel is (x0, y0); k = fx, fy,
    cx, cy; an unknown depth (0 or not finite) reads as `fill`; 0 where the surface lies behind the previous camera."""
    z = depth[r, c]
    if not (z > 0.0 and z < 1.0e30):
        z = fill
    px = float(c + x0)
    py = float(r + y0)
    p = rot * wp.vec3((px - k[2]) / k[0] * z, (py - k[3]) / k[1] * z, z) + trans
    if p[2] <= 1.0e-6:
        return wp.vec2(0.0, 0.0)
    return share * wp.vec2(px - (k[0] * p[0] / p[2] + k[2]), py - (k[1] * p[1] / p[2] + k[3]))


@wp.kernel
def _lengths(depth: wp.array2d(dtype=wp.float32), fill: float, x0: int, y0: int, k: wp.vec4, rot: wp.mat33,
             trans: wp.vec3, share: float, row0: int, out: wp.array2d(dtype=wp.float32)):
    i, j = wp.tid()
    r = i + row0
    out[r, j] = wp.length(_motion(depth, r, j, fill, x0, y0, k, rot, trans, share))


@wp.func
def _tap(alpha: wp.array2d(dtype=wp.float32), ratio: wp.array2d(dtype=wp.vec3), colour: wp.array2d(dtype=wp.vec3),
         r: int, c: int):
    """(the frame's factor (1 - alpha) ratio, the objects' term alpha colour) at pixel (r, c) of the box; off it the
    identity (1, 0)."""
    if r < 0 or c < 0 or r >= alpha.shape[0] or c >= alpha.shape[1]:
        return wp.vec3(1.0), wp.vec3(0.0)
    return (1.0 - alpha[r, c]) * ratio[r, c], alpha[r, c] * colour[r, c]


@wp.func
def _sample(alpha: wp.array2d(dtype=wp.float32), ratio: wp.array2d(dtype=wp.vec3), colour: wp.array2d(dtype=wp.vec3),
            x: float, y: float):
    """_tap's two layers, bilinear at pixel position (x, y) of the box."""
    xf = wp.floor(x)
    yf = wp.floor(y)
    wx = x - xf
    wy = y - yf
    c = int(xf)
    r = int(yf)
    f00, o00 = _tap(alpha, ratio, colour, r, c)
    f01, o01 = _tap(alpha, ratio, colour, r, c + 1)
    f10, o10 = _tap(alpha, ratio, colour, r + 1, c)
    f11, o11 = _tap(alpha, ratio, colour, r + 1, c + 1)
    f = (f00 * (1.0 - wx) + f01 * wx) * (1.0 - wy) + (f10 * (1.0 - wx) + f11 * wx) * wy
    o = (o00 * (1.0 - wx) + o01 * wx) * (1.0 - wy) + (o10 * (1.0 - wx) + o11 * wx) * wy
    return f, o


@wp.kernel
def _blur(camera: wp.array2d(dtype=wp.vec3), alpha: wp.array2d(dtype=wp.float32), ratio: wp.array2d(dtype=wp.vec3),
          colour: wp.array2d(dtype=wp.vec3), depth: wp.array2d(dtype=wp.float32), fill: float, x0: int, y0: int,
          k: wp.vec4, rot: wp.mat33, trans: wp.vec3, share: float, max_samples: int, row0: int,
          out: wp.array2d(dtype=wp.vec3)):
    i, j = wp.tid()
    r = i + row0
    b = _motion(depth, r, j, fill, x0, y0, k, rot, trans, share)
    n = wp.min(max_samples, int(wp.ceil(wp.length(b))) + 1)
    f = wp.vec3(0.0)
    o = wp.vec3(0.0)
    for s in range(n):
        u = (float(s) + 0.5) / float(n) - 0.5
        frame_u, objects_u = _sample(alpha, ratio, colour, float(j) + u * b[0], float(r) + u * b[1])
        f += frame_u
        o += objects_u
    v = (wp.cw_mul(camera[r, j], f) + o) / float(n)
    out[r, j] = wp.vec3(wp.max(v[0], 0.0), wp.max(v[1], 0.0), wp.max(v[2], 0.0))


def _camera_motion(intr: Intrinsics, pose: np.ndarray, previous: np.ndarray, share: float) -> list:
    """The kernels' camera inputs: (fx, fy, cx, cy), the rotation and translation from this camera to the previous
    one (poses camera-to-world), the shutter's share of the frame interval."""
    rot = previous[:3, :3].T @ pose[:3, :3]
    trans = previous[:3, :3].T @ (pose[:3, 3] - previous[:3, 3])
    return [wp.vec4(intr.fx, intr.fy, intr.cx, intr.cy), wp.mat33(*rot.astype(np.float32).ravel()),
            wp.vec3(*trans.astype(np.float32)), float(share)]


def _on(a: np.ndarray, device: str, dtype=wp.float32) -> wp.array:
    """A (h, w) or (h, w, 3) host array as a float32 (h, w) Warp array of `dtype` on `device`."""
    return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=dtype, device=device)


def motion_lengths(depth: np.ndarray, fill: float, origin: tuple[int, int], intr: Intrinsics, pose: np.ndarray,
                   previous: np.ndarray, share: float, device: str) -> np.ndarray:
    """(h, w) length in pixels of each pixel's motion over the shutter, for the box of depth `depth` (metres; `fill`
    where unknown: 0 or not finite) whose top-left pixel is `origin` (x, y), the camera at `pose` now and at
    `previous` a frame before."""
    h, w = depth.shape
    out = wp.empty((h, w), dtype=wp.float32, device=device)
    launch_rows(_lengths, (h, w), inputs=[_on(depth, device), float(fill), int(origin[0]), int(origin[1]),
                                          *_camera_motion(intr, pose, previous, share)], outputs=[out], device=device)
    return out.numpy()


def blur_layers(camera: np.ndarray, alpha: np.ndarray, ratio: np.ndarray, colour: np.ndarray, depth: np.ndarray,
                fill: float, origin: tuple[int, int], intr: Intrinsics, pose: np.ndarray, previous: np.ndarray,
                share: float, max_samples: int, device: str) -> np.ndarray:
    """(h, w, 3) float32 composite of a box (top-left pixel `origin`, x and y): `camera` (h, w, 3 linear) under the
    layers `alpha` (h, w), `ratio` and `colour` (h, w, 3), blurred along each pixel's motion (module docstring; the
    depth `fill` where unknown) on `device` (the CPU's launch split over threads, kernels.launch)."""
    h, w = alpha.shape
    out = wp.empty((h, w), dtype=wp.vec3, device=device)
    launch_rows(_blur, (h, w), inputs=[_on(camera, device, wp.vec3), _on(alpha, device), _on(ratio, device, wp.vec3),
                                       _on(colour, device, wp.vec3), _on(depth, device), float(fill), int(origin[0]),
                                       int(origin[1]), *_camera_motion(intr, pose, previous, share), int(max_samples)],
                outputs=[out], device=device)
    return out.numpy()
