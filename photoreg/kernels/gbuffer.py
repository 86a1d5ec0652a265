"""The virtual G-buffer's resolve (photoreg.render.gbuffer): one thread per window pixel over its s x s subsamples of
the supersampled draw. A subsample counts toward the pixel's coverage where the draw shows a face (depth buffer > 0)
that the real surface does not hide (real depth > 0 and finite, and the face farther than it + tolerance); it gives
the pixel its attributes where its flat colour decodes to a face index whose plane the subsample's ray meets at the
depth buffer's z (within 2 mm + 0.2%: MSAA blends indices at edges), the last such subsample in row-major order
winning. Plane hits in float64 (float32 out): the values of the numpy resolve it replaced, bit for bit (some forty
calls a frame; the G-buffer 0.4-1.7 ms faster a frame on an H100 and 4.5-6.3 -> 3.3-4.4 ms on the 2-core CPU, TUM
with the bunny: benchmarks/gpu.md, "The G-buffer's resolve in one kernel").
"""
from __future__ import annotations

import numpy as np

from photoreg.device import init_warp
from photoreg.kernels.packing import Packed, upload

wp = init_warp()


@wp.kernel
def _resolve(color: wp.array3d(dtype=wp.uint8), zbuf: wp.array2d(dtype=wp.float32), real: wp.array2d(dtype=wp.float32),
             s: int, u0: int, v0: int, fx: wp.float64, fy: wp.float64, cx: wp.float64, cy: wp.float64, rot: wp.mat33d,
             t: wp.vec3d, p0: wp.array(dtype=wp.vec3d), face_normal: wp.array(dtype=wp.vec3d),
             face_albedo: wp.array(dtype=wp.vec3), tolerance: wp.float32,
             coverage: wp.array2d(dtype=wp.float32), depth: wp.array2d(dtype=wp.float32),
             position: wp.array2d(dtype=wp.vec3), normal: wp.array2d(dtype=wp.vec3), albedo: wp.array2d(dtype=wp.vec3)):
    i, j = wp.tid()
    hits = int(0)
    shown = int(0)
    z_out = wp.float32(0.0)
    p_out = wp.vec3(0.0, 0.0, 0.0)
    n_out = wp.vec3(0.0, 0.0, 0.0)
    a_out = wp.vec3(0.0, 0.0, 0.0)
    rd = real[i, j]
    faces = p0.shape[0]
    for a in range(s):
        for b in range(s):
            v = i * s + a
            u = j * s + b
            zb = zbuf[v, u]
            if zb > wp.float32(0.0):
                if not (rd > wp.float32(0.0) and wp.isfinite(rd) and zb > rd + tolerance):
                    hits += 1
                    f = (int(color[v, u, 0]) | (int(color[v, u, 1]) << 8) | (int(color[v, u, 2]) << 16)) - 1
                    if f >= 0 and f < faces:
                        ray = rot * wp.vec3d((wp.float64(u + u0) - cx) / fx, (wp.float64(v + v0) - cy) / fy,
                                             wp.float64(1.0))
                        nf = face_normal[f]
                        den = wp.dot(nf, ray)
                        if den != wp.float64(0.0):
                            z = wp.dot(nf, p0[f] - t) / den
                            zd = wp.float64(zb)
                            if wp.isfinite(z) and wp.abs(z - zd) <= wp.float64(2e-3) + wp.float64(2e-3) * zd:
                                shown = 1
                                z_out = wp.float32(z)
                                p_out = wp.vec3(t + ray * z)
                                n_out = wp.vec3(nf * (-wp.sign(den)))
                                a_out = face_albedo[f]
    coverage[i, j] = wp.float32(0.0)
    if shown == 1:
        coverage[i, j] = wp.float32(hits) / wp.float32(s * s)
    depth[i, j] = z_out
    position[i, j] = p_out
    normal[i, j] = n_out
    albedo[i, j] = a_out


class Faces:
    """A scene's faces on a device, for resolve: a point of each face's plane, its unit normal, its albedo."""

    def __init__(self, p0: np.ndarray, normal: np.ndarray, albedo: np.ndarray, device: str):
        self.device = device
        self.p0 = wp.array(np.asarray(p0, np.float64), dtype=wp.vec3d, device=device)
        self.normal = wp.array(np.asarray(normal, np.float64), dtype=wp.vec3d, device=device)
        self.albedo = wp.array(np.asarray(albedo, np.float32), dtype=wp.vec3, device=device)


def resolve(color: np.ndarray, zbuf: np.ndarray, real: np.ndarray, s: int, origin: tuple[int, int],
            intr_hi, pose: np.ndarray, faces: Faces, tolerance: float) -> tuple[np.ndarray, ...]:
    """(coverage, depth, position, normal, albedo) of a window of h x w pixels from its draw: `color` (h*s, w*s, >=3)
    uint8 face codes, `zbuf` (h*s, w*s) float32, `real` (h, w) float32 real depth (0: unknown), the window's
    supersampled top-left pixel `origin` (u0, v0), the supersampled intrinsics `intr_hi`, camera-to-world `pose`."""
    h, w = real.shape
    dev = faces.device
    out = Packed([((h, w), wp.float32)] * 2 + [((h, w), wp.vec3)] * 3, dev)   # one read-back for the five
    pose = np.asarray(pose, np.float64)
    wp.launch(_resolve, dim=(h, w), device=dev,
              inputs=[*upload([color, zbuf, real], [wp.uint8, wp.float32, wp.float32], dev),
                      int(s), int(origin[0]), int(origin[1]), float(intr_hi.fx), float(intr_hi.fy), float(intr_hi.cx),
                      float(intr_hi.cy), wp.mat33d(*pose[:3, :3].ravel()), wp.vec3d(*pose[:3, 3]), faces.p0,
                      faces.normal, faces.albedo, float(np.float32(tolerance))],
              outputs=out.arrays)
    return tuple(out.numpy())
