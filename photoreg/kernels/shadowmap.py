"""Shadow-map kernels: an orthographic depth map of a triangle mesh seen from a directional light, its
filtered lookup (PCF; PCSS with a blocker search and a penumbra from the light's angular radius), and the
light's visibility through the real geometry's SDF (to protect shadows the real scene already has).

Light frame: unit d points towards the light; u, v complete an orthonormal basis. Texel (i, j) of the map
is the ray from corner + (i + 0.5) texel u + (j + 0.5) texel v along -d; its value is the distance t to the
first triangle hit (FAR where none). A world point q has map coordinates x = (q - corner).u / texel,
y = (q - corner).v / texel and light depth z = -(q - corner).d; it is behind a blocker where depth < z.
Each lookup tap compares against the receiver's plane at the tap (receiver-plane depth bias), so tilted
receivers do not shadow themselves across a wide filter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photoreg.device import init_warp
from photoreg.kernels.grid import SDF_DTYPE, DenseGrid
from photoreg.kernels.launch import launch_rows
from photoreg.kernels.transfer import ray_blocked

wp = init_warp()

FAR = wp.constant(1.0e30)
GOLDEN_ANGLE = wp.constant(2.399963229728653)


@dataclass
class ShadowMap:
    """Orthographic light-space depth map of the virtual objects (see the module docstring)."""

    depth: wp.array2d      # (res, res) float32 distance from the light plane along -d, FAR = no blocker
    corner: np.ndarray     # (3,) world point of the map's corner on the light plane
    u: np.ndarray          # (3,) unit map x axis
    v: np.ndarray          # (3,) unit map y axis
    d: np.ndarray          # (3,) unit direction towards the light
    texel: float           # metres per texel
    z_min: float           # smallest light depth of any blocker (the top of the objects)


@wp.kernel
def _depth_map(mesh: wp.uint64, corner: wp.vec3, u: wp.vec3, v: wp.vec3, d: wp.vec3, texel: float, max_t: float,
               row0: int, depth: wp.array2d(dtype=wp.float32)):
    t0, j = wp.tid()
    i = row0 + t0
    start = corner + u * ((float(i) + 0.5) * texel) + v * ((float(j) + 0.5) * texel)
    hit = wp.mesh_query_ray(mesh, start, -d, max_t)
    t = FAR
    if hit.result:
        t = hit.t
    depth[i, j] = t


@wp.func
def _vogel(k: int, count: int) -> wp.vec2:
    """k-th of `count` points spread evenly over the unit disc (golden-angle spiral)."""
    r = wp.sqrt((float(k) + 0.5) / float(count))
    a = float(k) * GOLDEN_ANGLE
    return wp.vec2(r * wp.cos(a), r * wp.sin(a))


@wp.func
def _texel_depth(depth: wp.array2d(dtype=wp.float32), i: int, j: int) -> float:
    if i < 0 or j < 0 or i >= depth.shape[0] or j >= depth.shape[1]:
        return FAR
    return depth[i, j]


@wp.func
def _closer(depth: wp.array2d(dtype=wp.float32), x: float, y: float, z: float) -> float:
    """Bilinearly weighted share of the 4 texels around (x, y) that hold a blocker closer than z."""
    fx = x - 0.5
    fy = y - 0.5
    i = int(wp.floor(fx))
    j = int(wp.floor(fy))
    tx = fx - float(i)
    ty = fy - float(j)
    b00 = wp.where(_texel_depth(depth, i, j) < z, 1.0, 0.0)
    b10 = wp.where(_texel_depth(depth, i + 1, j) < z, 1.0, 0.0)
    b01 = wp.where(_texel_depth(depth, i, j + 1) < z, 1.0, 0.0)
    b11 = wp.where(_texel_depth(depth, i + 1, j + 1) < z, 1.0, 0.0)
    return wp.lerp(wp.lerp(b00, b10, tx), wp.lerp(b01, b11, tx), ty)


@wp.kernel
def _lookup(depth: wp.array2d(dtype=wp.float32), corner: wp.vec3, u: wp.vec3, v: wp.vec3, d: wp.vec3, texel: float,
            z_min: float, points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3), offset: float,
            tan_angle: float, pcss: int, samples: int, min_radius: float, max_radius: float, bias: float,
            row0: int, shadow: wp.array(dtype=wp.float32), penumbra: wp.array(dtype=wp.float32)):
    i = row0 + wp.tid()
    n = normals[i]
    rel = points[i] + n * offset - corner
    x = wp.dot(rel, u) / texel
    y = wp.dot(rel, v) / texel
    z = -wp.dot(rel, d) - bias
    # receiver plane: light depth changes by gu (gv) per texel along u (v)
    gu = float(0.0)
    gv = float(0.0)
    nd = wp.dot(n, d)
    if wp.abs(nd) > 1.0e-3:
        nd_c = wp.sign(nd) * wp.max(wp.abs(nd), 0.1)
        gu = wp.clamp(wp.dot(n, u) / nd_c, -10.0, 10.0) * texel
        gv = wp.clamp(wp.dot(n, v) / nd_c, -10.0, 10.0) * texel
    radius = min_radius
    if pcss != 0:
        search = wp.clamp(wp.max(z - z_min, 0.0) * tan_angle / texel, min_radius, max_radius)
        total = float(0.0)
        count = int(0)
        for k in range(samples):
            o = _vogel(k, samples) * search
            b = _texel_depth(depth, int(wp.floor(x + o[0])), int(wp.floor(y + o[1])))
            if b < z + gu * o[0] + gv * o[1]:
                total += b
                count += 1
        if count == 0:
            shadow[i] = 0.0
            penumbra[i] = 0.0
            return
        radius = wp.clamp((z - total / float(count)) * tan_angle / texel, min_radius, max_radius)
    acc = float(0.0)
    for k in range(samples):
        o = _vogel(k, samples) * radius
        acc += _closer(depth, x + o[0], y + o[1], z + gu * o[0] + gv * o[1])
    shadow[i] = acc / float(samples)
    penumbra[i] = radius * texel


@wp.kernel
def _real_visibility(sdf: wp.array3d(dtype=SDF_DTYPE), empty: wp.array3d(dtype=wp.uint8), cell: int,
                     origin: wp.vec3, voxel: float, trunc: float, points: wp.array(dtype=wp.vec3),
                     normals: wp.array(dtype=wp.vec3), d: wp.vec3, u: wp.vec3, v: wp.vec3, tan_angle: float,
                     offset: float, length: float, min_step: float, samples: int, row0: int,
                     vis: wp.array(dtype=wp.float32)):
    i = row0 + wp.tid()
    n = normals[i]
    o = points[i] + n * offset
    free = int(0)
    for k in range(samples):
        s = _vogel(k, samples) * tan_angle
        w = wp.normalize(d + u * s[0] + v * s[1])
        if wp.dot(n, w) > 0.0 or wp.length(n) == 0.0:
            if not ray_blocked(sdf, empty, cell, origin, voxel, trunc, o, w, length, min_step):
                free += 1
    vis[i] = float(free) / float(samples)


def _vec3s(a: np.ndarray, device: str, what: str) -> wp.array:
    a = np.ascontiguousarray(np.asarray(a, np.float32).reshape(-1, 3))
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has non-finite values")
    return wp.array(a, dtype=wp.vec3, device=device)


def depth_map(vertices: np.ndarray, faces: np.ndarray, corner, u, v, d, texel: float, resolution: int,
              max_t: float, device: str) -> ShadowMap:
    """Ray-cast the (res, res) light-space depth map of the triangles (world vertices (V, 3), faces (F, 3))
    in the light frame (corner, u, v, d, texel) with a wp.Mesh; rays end at max_t."""
    if resolution < 1 or not texel > 0:
        raise ValueError(f"depth_map: need resolution >= 1 and texel > 0, got {resolution}, {texel}")
    pts = _vec3s(vertices, device, "depth_map vertices")
    idx = wp.array(np.ascontiguousarray(np.asarray(faces, np.int32).reshape(-1)), dtype=wp.int32, device=device)
    mesh = wp.Mesh(points=pts, indices=idx)
    depth = wp.empty((resolution, resolution), dtype=wp.float32, device=device)
    launch_rows(_depth_map, (resolution, resolution), device=device,
                inputs=[mesh.id, wp.vec3(*corner), wp.vec3(*u), wp.vec3(*v), wp.vec3(*d), float(texel), float(max_t)],
                outputs=[depth])
    wp.synchronize_device(device)
    z = -(np.asarray(vertices, np.float64) - corner) @ d
    return ShadowMap(depth, np.asarray(corner, np.float64), np.asarray(u, np.float64), np.asarray(v, np.float64),
                     np.asarray(d, np.float64), float(texel), float(z.min()))


def shadow_lookup(smap: ShadowMap, points: np.ndarray, normals: np.ndarray, tan_angle: float, offset: float,
                  pcss: bool = True, samples: int = 32, min_radius: float = 1.0, max_radius: float = 32.0,
                  bias_texels: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Shadow (N,) in [0, 1] (share of the light blocked by the mapped mesh) and filter radius (N,) in metres
    at world points (N, 3) with normals (N, 3), looked up from p + n * offset. PCF filters a disc of
    min_radius texels; PCSS searches blockers over the disc the light's cone (tan_angle) opens between the
    receiver and the top of the mesh, and filters over the penumbra (z_r - z_blocker) tan_angle, both clamped
    to [min_radius, max_radius] texels."""
    device = str(smap.depth.device)
    p = _vec3s(points, device, "shadow_lookup points")
    n = _vec3s(normals, device, "shadow_lookup normals")
    if p.shape != n.shape:
        raise ValueError(f"shadow_lookup: points {p.shape} and normals {n.shape} differ in count")
    N = p.shape[0]
    shadow = wp.zeros(N, dtype=wp.float32, device=device)
    pen = wp.zeros(N, dtype=wp.float32, device=device)
    launch_rows(_lookup, (N,), device=device,
                inputs=[smap.depth, wp.vec3(*smap.corner), wp.vec3(*smap.u), wp.vec3(*smap.v), wp.vec3(*smap.d),
                        smap.texel, smap.z_min, p, n, float(offset), float(tan_angle), int(pcss), int(samples),
                        float(min_radius), float(max_radius), float(bias_texels * smap.texel)],
                outputs=[shadow, pen])
    return shadow.numpy(), pen.numpy()


def real_light_visibility(grid: DenseGrid, points: np.ndarray, normals: np.ndarray, d, u, v, tan_angle: float,
                          offset: float, length: float, samples: int = 8, min_step_voxels: float = 0.5) -> np.ndarray:
    """Share (N,) of `samples` rays spread over the light's disc (axis d, radius tan_angle in the u, v plane)
    that leave p + n * offset without the real SDF blocking them within `length` (rays below the surface's
    tangent plane count as blocked)."""
    device = grid.device
    p = _vec3s(points, device, "real_light_visibility points")
    n = _vec3s(normals, device, "real_light_visibility normals")
    vis = wp.zeros(p.shape[0], dtype=wp.float32, device=device)
    launch_rows(_real_visibility, (p.shape[0],), device=device,
                inputs=[grid.sdf, grid.empty, int(grid.cell), wp.vec3(*grid.origin), float(grid.voxel_size),
                        float(grid.trunc), p, n, wp.vec3(*d), wp.vec3(*u), wp.vec3(*v), float(tan_angle),
                        float(offset), float(length), float(min_step_voxels * grid.voxel_size), int(samples)],
                outputs=[vis])
    return vis.numpy()
