"""Motion blur of a composite's two layers along each pixel's image motion (photoreg.render.motion_blur).

Each pixel averages `n` bilinear samples of the frame's factor and of the objects' term spread evenly along its motion
vector, then blends them with its camera colour: out = camera * mean(frame) + mean(objects), clamped at 0. A sample
off the box takes the layers' identity (factor 1, term 0), as cv2.remap's constant border would.
"""
from __future__ import annotations

import numpy as np

from photoreg.device import init_warp
from photoreg.kernels.launch import launch_rows

wp = init_warp()


@wp.func
def _tap(a: wp.array2d(dtype=wp.vec3), r: int, c: int, border: wp.vec3) -> wp.vec3:
    if r < 0 or c < 0 or r >= a.shape[0] or c >= a.shape[1]:
        return border
    return a[r, c]


@wp.func
def _bilinear(a: wp.array2d(dtype=wp.vec3), x: float, y: float, border: wp.vec3) -> wp.vec3:
    x0 = wp.floor(x)
    y0 = wp.floor(y)
    fx = x - x0
    fy = y - y0
    c = int(x0)
    r = int(y0)
    top = _tap(a, r, c, border) * (1.0 - fx) + _tap(a, r, c + 1, border) * fx
    bottom = _tap(a, r + 1, c, border) * (1.0 - fx) + _tap(a, r + 1, c + 1, border) * fx
    return top * (1.0 - fy) + bottom * fy


@wp.kernel
def _blur(camera: wp.array2d(dtype=wp.vec3), frame: wp.array2d(dtype=wp.vec3), objects: wp.array2d(dtype=wp.vec3),
          motion: wp.array2d(dtype=wp.vec2), n: int, row0: int, out: wp.array2d(dtype=wp.vec3)):
    i, j = wp.tid()
    r = i + row0
    b = motion[r, j]
    f = wp.vec3(0.0)
    o = wp.vec3(0.0)
    for k in range(n):
        u = (float(k) + 0.5) / float(n) - 0.5
        x = float(j) + u * b[0]
        y = float(r) + u * b[1]
        f += _bilinear(frame, x, y, wp.vec3(1.0))
        o += _bilinear(objects, x, y, wp.vec3(0.0))
    v = (wp.cw_mul(camera[r, j], f) + o) / float(n)
    out[r, j] = wp.vec3(wp.max(v[0], 0.0), wp.max(v[1], 0.0), wp.max(v[2], 0.0))


def blur_layers(camera: np.ndarray, frame: np.ndarray, objects: np.ndarray, motion: np.ndarray, n: int,
                device: str) -> np.ndarray:
    """(h, w, 3) float32 composite of a box: `camera`, the frame's factor `frame` and the objects' term `objects`
    (each (h, w, 3) linear), the layers averaged over `n` samples along `motion` (h, w, 2: x, y pixels) on `device`
    (the CPU's launch split over threads, kernels.launch)."""
    h, w = camera.shape[:2]
    images = [wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=wp.vec3, device=device)
              for a in (camera, frame, objects)]
    vectors = wp.array(np.ascontiguousarray(motion, dtype=np.float32), dtype=wp.vec2, device=device)
    out = wp.empty((h, w), dtype=wp.vec3, device=device)
    launch_rows(_blur, (h, w), inputs=[*images, vectors, int(n)], outputs=[out], device=device)
    return out.numpy()
