"""The virtual G-buffer's resolve (photoreg.render.gbuffer): one thread per window pixel over its s x s subsamples of
the supersampled draw. A subsample counts toward the pixel's coverage where the draw shows a face (depth buffer > 0)
that the real surface does not hide (real depth > 0 and finite, and the face farther than it + tolerance); it gives
the pixel its attributes where its flat colour decodes to a face index whose plane the subsample's ray meets at the
depth buffer's z (within 2 mm + 0.2%: a code blended or rounded into another face's gives nothing; the draw is
single-sample, photoreg.render.gbuffer._single_sample), the last such subsample in row-major order winning. Plane
hits in float64 (float32 out): the values of the numpy resolve it replaced, bit for bit (some forty calls a frame; the
G-buffer 0.4-1.7 ms faster a frame on an H100 and 4.5-6.3 -> 3.3-4.4 ms on the 2-core CPU, TUM with the bunny:
benchmarks/gpu.md, "The G-buffer's resolve in one kernel").

`trace` makes the same G-buffer without a draw: each subsample's ray meets the scene's faces in a Warp mesh (BVH), the
nearest face that faces the camera (pyrender culls back faces) standing for the rasterised one; coverage, depth test
and attributes as in the resolve, from that face's plane.

Both name each pixel's face; where its albedo varies (objects.albedo = "texture": a texture image, or vertex or face
colours) or its normal does (objects.smooth) `Varying.apply` replaces the face's one albedo and normal with their
means where the pixel's subsample rays meet the face's plane (filtered over the pixel, as a supersampled render sees
it), on the device before the one read-back.
"""
from __future__ import annotations

import numpy as np

from photoreg.device import init_warp
from photoreg.kernels.packing import Packed, upload

wp = init_warp()


@wp.func
def _subsample_ray(u: int, v: int, fx: wp.float64, fy: wp.float64, cx: wp.float64, cy: wp.float64,
                   rot: wp.mat33d) -> wp.vec3d:
    """World direction of supersampled pixel (u, v)'s ray, camera z = 1 (camera-to-world rotation rot)."""
    return rot * wp.vec3d((wp.float64(u) - cx) / fx, (wp.float64(v) - cy) / fy, wp.float64(1.0))


@wp.func
def _hidden(z: wp.float32, rd: wp.float32, tolerance: wp.float32) -> bool:
    """Whether the real surface at depth rd (0 or non-finite: unknown) hides a virtual face at depth z."""
    return rd > wp.float32(0.0) and wp.isfinite(rd) and z > rd + tolerance


@wp.kernel
def _resolve(color: wp.array3d(dtype=wp.uint8), zbuf: wp.array2d(dtype=wp.float32), real: wp.array2d(dtype=wp.float32),
             s: int, u0: int, v0: int, fx: wp.float64, fy: wp.float64, cx: wp.float64, cy: wp.float64, rot: wp.mat33d,
             t: wp.vec3d, p0: wp.array(dtype=wp.vec3d), face_normal: wp.array(dtype=wp.vec3d),
             face_albedo: wp.array(dtype=wp.vec3), tolerance: wp.float32,
             coverage: wp.array2d(dtype=wp.float32), depth: wp.array2d(dtype=wp.float32),
             position: wp.array2d(dtype=wp.vec3), normal: wp.array2d(dtype=wp.vec3), albedo: wp.array2d(dtype=wp.vec3),
             face: wp.array2d(dtype=wp.int32)):
    i, j = wp.tid()
    hits = int(0)
    shown = int(0)
    f_out = int(-1)
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
                if not _hidden(zb, rd, tolerance):
                    hits += 1
                    f = (int(color[v, u, 0]) | (int(color[v, u, 1]) << 8) | (int(color[v, u, 2]) << 16)) - 1
                    if f >= 0 and f < faces:
                        ray = _subsample_ray(u + u0, v + v0, fx, fy, cx, cy, rot)
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
                                f_out = f
    coverage[i, j] = wp.float32(0.0)
    if shown == 1:
        coverage[i, j] = wp.float32(hits) / wp.float32(s * s)
    depth[i, j] = z_out
    position[i, j] = p_out
    normal[i, j] = n_out
    albedo[i, j] = a_out
    face[i, j] = wp.int32(f_out)


BACK_FACES = 8   # back faces a subsample's ray may pass (culled, as pyrender draws) before it gives up


@wp.kernel
def _trace(mesh: wp.uint64, real: wp.array2d(dtype=wp.float32), s: int, u0: int, v0: int, fx: wp.float64,
           fy: wp.float64, cx: wp.float64, cy: wp.float64, rot: wp.mat33d, t: wp.vec3d, near: wp.float64,
           far: wp.float64, p0: wp.array(dtype=wp.vec3d), face_normal: wp.array(dtype=wp.vec3d),
           face_albedo: wp.array(dtype=wp.vec3), tolerance: wp.float32,
           coverage: wp.array2d(dtype=wp.float32), depth: wp.array2d(dtype=wp.float32),
           position: wp.array2d(dtype=wp.vec3), normal: wp.array2d(dtype=wp.vec3), albedo: wp.array2d(dtype=wp.vec3),
           face: wp.array2d(dtype=wp.int32)):
    i, j = wp.tid()
    hits = int(0)
    f_out = int(-1)
    z_out = wp.float32(0.0)
    p_out = wp.vec3(0.0, 0.0, 0.0)
    n_out = wp.vec3(0.0, 0.0, 0.0)
    a_out = wp.vec3(0.0, 0.0, 0.0)
    rd = real[i, j]
    for a in range(s):
        for b in range(s):
            ray = _subsample_ray(j * s + b + u0, i * s + a + v0, fx, fy, cx, cy, rot)
            length = wp.length(ray)
            d = wp.vec3(ray / length)
            start = wp.vec3(t + ray * near)           # from the near plane, as the draw clips
            reach = wp.float32((far - near) * length)
            for k in range(BACK_FACES):
                q = wp.mesh_query_ray(mesh, start, d, reach)
                if not q.result:
                    break
                nf = face_normal[q.face]
                den = wp.dot(nf, ray)
                if den < wp.float64(0.0):   # the front of the face: the draw's nearest fragment
                    z = wp.dot(nf, p0[q.face] - t) / den
                    if wp.isfinite(z) and not _hidden(wp.float32(z), rd, tolerance):
                        hits += 1
                        z_out = wp.float32(z)
                        p_out = wp.vec3(t + ray * z)
                        n_out = wp.vec3(nf)
                        a_out = face_albedo[q.face]
                        f_out = q.face
                    break
                step = q.t + wp.float32(1e-5)        # a back face: culled, the ray goes on past it
                start = start + d * step
                reach = reach - step
    coverage[i, j] = wp.float32(hits) / wp.float32(s * s)
    depth[i, j] = z_out
    position[i, j] = p_out
    normal[i, j] = n_out
    albedo[i, j] = a_out
    face[i, j] = wp.int32(f_out)


@wp.func
def _texel(texels: wp.array(dtype=wp.vec3), offset: int, w: int, h: int, x: int, y: int) -> wp.vec3:
    """Texel (x, y) of a w x h texture stored row by row from `offset`, the coordinates wrapped (repeat)."""
    return texels[offset + ((y % h) + h) % h * w + ((x % w) + w) % w]


@wp.func
def _lookup(texels: wp.array(dtype=wp.vec3), n: wp.vec3i, uv: wp.vec2) -> wp.vec3:
    """Bilinear lookup of texture n = (offset, width, height) at `uv`: texel centres at half-integers, v up (the
    image's row 0 on top), repeating."""
    x = uv[0] * wp.float32(n[1]) - 0.5
    y = (1.0 - uv[1]) * wp.float32(n[2]) - 0.5
    x0 = wp.floor(x)
    y0 = wp.floor(y)
    fx = x - x0
    fy = y - y0
    xi = int(x0)
    yi = int(y0)
    top = _texel(texels, n[0], n[1], n[2], xi, yi) * (1.0 - fx) + _texel(texels, n[0], n[1], n[2], xi + 1, yi) * fx
    low = _texel(texels, n[0], n[1], n[2], xi, yi + 1) * (1.0 - fx) + _texel(texels, n[0], n[1], n[2], xi + 1,
                                                                              yi + 1) * fx
    return top * (1.0 - fy) + low * fy


NO_TEXTURE = wp.constant(-1)       # a face's albedo source: its object's one albedo ...
CORNER_COLOURS = wp.constant(-2)   # ... or colours at its corners (vertex or face colours); >= 0: a texture


@wp.kernel
def _varying(face: wp.array2d(dtype=wp.int32), s: int, u0: int, v0: int, fx: wp.float64, fy: wp.float64,
             cx: wp.float64, cy: wp.float64, rot: wp.mat33d, t: wp.vec3d, source: wp.array(dtype=wp.int32),
             smooth: wp.array(dtype=wp.int32), p0: wp.array(dtype=wp.vec3d), e1: wp.array(dtype=wp.vec3d),
             e2: wp.array(dtype=wp.vec3d), uv0: wp.array(dtype=wp.vec2), uv1: wp.array(dtype=wp.vec2),
             uv2: wp.array(dtype=wp.vec2), c0: wp.array(dtype=wp.vec3), c1: wp.array(dtype=wp.vec3),
             c2: wp.array(dtype=wp.vec3), m0: wp.array(dtype=wp.vec3), m1: wp.array(dtype=wp.vec3),
             m2: wp.array(dtype=wp.vec3), texels: wp.array(dtype=wp.vec3), info: wp.array(dtype=wp.vec3i),
             normal_out: wp.array2d(dtype=wp.vec3), albedo: wp.array2d(dtype=wp.vec3)):
    i, j = wp.tid()
    f = face[i, j]
    if f < 0:
        return
    k = source[f]
    if k == NO_TEXTURE and smooth[f] == 0:
        return
    a = e1[f]
    b = e2[f]
    normal = wp.cross(a, b)
    d00 = wp.dot(a, a)
    d01 = wp.dot(a, b)
    d11 = wp.dot(b, b)
    den = d00 * d11 - d01 * d01
    if den <= wp.float64(0.0):
        return
    total = wp.vec3(0.0, 0.0, 0.0)
    shading = wp.vec3(0.0, 0.0, 0.0)
    count = int(0)
    for r in range(s):   # the pixel's subsample rays on the face's plane: its footprint, as the draw's subsamples
        for c in range(s):
            ray = _subsample_ray(j * s + c + u0, i * s + r + v0, fx, fy, cx, cy, rot)
            along = wp.dot(normal, ray)
            if along != wp.float64(0.0):
                d = t + ray * (wp.dot(normal, p0[f] - t) / along) - p0[f]
                b1 = wp.float32((d11 * wp.dot(d, a) - d01 * wp.dot(d, b)) / den)   # barycentrics (may lie outside)
                b2 = wp.float32((d00 * wp.dot(d, b) - d01 * wp.dot(d, a)) / den)
                if k == CORNER_COLOURS:
                    total += c0[f] * (1.0 - b1 - b2) + c1[f] * b1 + c2[f] * b2
                elif k >= 0:
                    total += _lookup(texels, info[k], uv0[f] * (1.0 - b1 - b2) + uv1[f] * b1 + uv2[f] * b2)
                shading += m0[f] * (1.0 - b1 - b2) + m1[f] * b1 + m2[f] * b2
                count += 1
    if count > 0 and k != NO_TEXTURE:
        albedo[i, j] = total / wp.float32(count)
    if count > 0 and smooth[f] != 0 and wp.length(shading) > 0.0:
        normal_out[i, j] = wp.normalize(shading)


class Varying:
    """Faces whose albedo or normal varies over them, on a device, for the G-buffer (`apply`): each face's albedo
    source (a texture's index, NO_TEXTURE or CORNER_COLOURS) and whether it is smooth, its first vertex and edges
    (barycentrics), its corners' texture coordinates, linear colours and unit normals; the textures' linear RGB
    texels in one array, with each one's (offset, width, height) (a black texel alone where there are none)."""

    def __init__(self, triangles: np.ndarray, source: np.ndarray, smooth: np.ndarray, uv: np.ndarray,
                 corners: np.ndarray, normals: np.ndarray, textures: list[np.ndarray], device: str):
        tri = np.asarray(triangles, np.float64)
        uv, corners, normals = (np.asarray(a, np.float32) for a in (uv, corners, normals))
        textures = textures or [np.zeros((1, 1, 3), np.float32)]
        sizes = [t.shape[0] * t.shape[1] for t in textures]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        parts = [(np.asarray(source, np.int32), wp.int32), (np.asarray(smooth, np.int32), wp.int32),
                 (tri[:, 0], wp.vec3d), (tri[:, 1] - tri[:, 0], wp.vec3d), (tri[:, 2] - tri[:, 0], wp.vec3d),
                 *[(uv[:, c], wp.vec2) for c in range(3)], *[(corners[:, c], wp.vec3) for c in range(3)],
                 *[(normals[:, c], wp.vec3) for c in range(3)],
                 (np.concatenate([t.reshape(-1, 3) for t in textures]).astype(np.float32), wp.vec3),
                 (np.array([[o, t.shape[1], t.shape[0]] for o, t in zip(offsets, textures)], np.int32), wp.vec3i)]
        self.arrays = [wp.array(np.ascontiguousarray(a), dtype=dtype, device=device) for a, dtype in parts]

    def apply(self, face: wp.array, view: list, normal: wp.array, albedo: wp.array) -> None:
        """Overwrites, at the pixels whose `face` varies, `albedo` with its mean where the pixel's s x s subsample
        rays (`view`: _view's arguments) meet that face's plane (the texture's bilinear lookups, or the corners'
        colours interpolated) and, on smooth faces, `normal` with the mean of the corners' normals interpolated
        there, made unit: filtered over the pixel's footprint, as a supersampled render averages it."""
        wp.launch(_varying, dim=face.shape, device=face.device, inputs=[face, *view, *self.arrays],
                  outputs=[normal, albedo])


class Faces:
    """A scene's faces on a device, for resolve and trace: a point of each face's plane, its unit normal (the
    triangle's winding: counter-clockwise seen from the front), its albedo; with `triangles` (F, 3, 3) also their
    Warp mesh (trace's); with `varying` the albedo and normal of the faces over which they vary, per pixel."""

    def __init__(self, p0: np.ndarray, normal: np.ndarray, albedo: np.ndarray, device: str,
                 triangles: np.ndarray | None = None, varying: Varying | None = None):
        self.device = device
        self.varying = varying
        self.p0 = wp.array(np.asarray(p0, np.float64), dtype=wp.vec3d, device=device)
        self.normal = wp.array(np.asarray(normal, np.float64), dtype=wp.vec3d, device=device)
        self.albedo = wp.array(np.asarray(albedo, np.float32), dtype=wp.vec3, device=device)
        self.mesh = None
        if triangles is not None:
            points = wp.array(np.asarray(triangles, np.float32).reshape(-1, 3), dtype=wp.vec3, device=device)
            self.mesh = wp.Mesh(points=points, indices=wp.array(np.arange(points.shape[0], dtype=np.int32),
                                                                 dtype=wp.int32, device=device))


def _view(s: int, origin: tuple[int, int], intr_hi, pose: np.ndarray) -> list:
    """The kernels' view arguments: s, the window's supersampled origin, the supersampled intrinsics, the pose's
    rotation and translation (float64)."""
    pose = np.asarray(pose, np.float64)
    return [int(s), int(origin[0]), int(origin[1]), float(intr_hi.fx), float(intr_hi.fy), float(intr_hi.cx),
            float(intr_hi.cy), wp.mat33d(*pose[:3, :3].ravel()), wp.vec3d(*pose[:3, 3])]


def _layers(kernel, h: int, w: int, faces: Faces, view: list, inputs: list) -> tuple[np.ndarray, ...]:
    """Launches a G-buffer kernel over h x w pixels (`inputs`, `view` (_view's) among them) and reads back
    (coverage, depth, position, normal, albedo) in one copy, the varying faces' albedo and normals (Varying) made on
    the device first."""
    out = Packed([((h, w), wp.float32)] * 2 + [((h, w), wp.vec3)] * 3, faces.device)
    face = wp.empty((h, w), dtype=wp.int32, device=faces.device)
    wp.launch(kernel, dim=(h, w), device=faces.device, inputs=inputs, outputs=[*out.arrays, face])
    if faces.varying is not None:
        faces.varying.apply(face, view, out.arrays[3], out.arrays[4])
    return tuple(out.numpy())


def resolve(color: np.ndarray, zbuf: np.ndarray, real: np.ndarray, s: int, origin: tuple[int, int],
            intr_hi, pose: np.ndarray, faces: Faces, tolerance: float) -> tuple[np.ndarray, ...]:
    """(coverage, depth, position, normal, albedo) of a window of h x w pixels from its draw: `color` (h*s, w*s, >=3)
    uint8 face codes, `zbuf` (h*s, w*s) float32, `real` (h, w) float32 real depth (0: unknown), the window's
    supersampled top-left pixel `origin` (u0, v0), the supersampled intrinsics `intr_hi`, camera-to-world `pose`."""
    h, w = real.shape
    view = _view(s, origin, intr_hi, pose)
    return _layers(_resolve, h, w, faces, view,
                   [*upload([color, zbuf, real], [wp.uint8, wp.float32, wp.float32], faces.device), *view, faces.p0,
                    faces.normal, faces.albedo, float(np.float32(tolerance))])


def trace(real: np.ndarray, s: int, origin: tuple[int, int], intr_hi, pose: np.ndarray, faces: Faces,
          tolerance: float, near: float, far: float) -> tuple[np.ndarray, ...]:
    """(coverage, depth, position, normal, albedo) of a window of h x w pixels as resolve gives them, from rays instead
    of a draw: `real` (h, w) float32 real depth (0: unknown), the window's supersampled top-left pixel `origin`
    (u0, v0), the supersampled intrinsics `intr_hi`, camera-to-world `pose`, faces made with their triangles, the
    draw's clipping planes `near`, `far` (camera z, metres)."""
    if faces.mesh is None:
        raise ValueError("gbuffer.trace: the Faces were made without their triangles (no mesh to trace)")
    h, w = real.shape
    (real_dev,) = upload([real], [wp.float32], faces.device, pack=False)
    view = _view(s, origin, intr_hi, pose)
    return _layers(_trace, h, w, faces, view,
                   [faces.mesh.id, real_dev, *view, float(near), float(far), faces.p0, faces.normal, faces.albedo,
                    float(np.float32(tolerance))])
