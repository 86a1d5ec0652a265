"""Radiance transfer R(x) by visibility rays through dense SDF bricks, projected onto SH.

R(x)_i = (1/pi) * integral V(x, w) max(n.w, 0) Y_i(w) dw (DESIGN.md), by quadrature over a fixed set
of D equal-area directions covering the whole sphere: R_i = (1/pi) (4 pi / D) sum_{n.w_d > 0} V_d (n.w_d) Y_i(w_d).

Two passes, so that visibility against several grids shares one projection, and a third on request:
1. occlusion: one thread per (point, direction) marches the ray from x + n * offset and writes bit
   flags per direction: REAL when the real-geometry grid blocks it, VIRTUAL when the optional second
   grid (the voxelised virtual objects, photoreg.render.scene) blocks it, so one pass serves both; on
   request also the distance at which real geometry blocks it (where the bounce light comes from:
   photoreg.lighting.bounce);
2. projection: one thread per point (CPU) or per (point, coefficient) (GPU) sums the hemisphere directions whose
   flags under `mask` are clear (mask REAL -> R_TR; REAL | VIRTUAL -> R_TRV), plus the visible fraction;
3. observed bounce (observed_bounce, after a pass with hit distances): one thread per point sums its blocked
   rays' weights, times the fused luminance of the map cell each ray hits where the map holds it.
shaded_pass replaces pass 2 where only the shading under one lighting is wanted (the voxel renderer): one thread per
point sums its clear rays' weighted radiance: F.R_TR and F.R_TRV without the SH vectors (the two projections, a
thread per point and coefficient, took 90 of the voxel renderer's 315 ms a frame on the 2-core CPU, ICL-NUIM with the
bunny at 5 bands).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photoreg.device import init_warp
from photoreg.kernels.grid import SDF_DTYPE, DenseGrid, free_run, ray_box, sample_sdf
from photoreg.kernels.launch import launch_rows
from photoreg.kernels.packing import upload
from photoreg.lighting.exposure import CELL_BITS, CELL_OFFSET
from photoreg.lighting.sh import bands_of, fibonacci_sphere, sh_basis

wp = init_warp()

REAL = wp.constant(1)
VIRTUAL = wp.constant(2)


@dataclass
class TransferResult:
    """Per-point transfer and visibility; numpy copies plus the Warp arrays they came from."""

    transfer: np.ndarray           # (N, B*B) float32, R_i
    visible_fraction: np.ndarray   # (N,) float32, unoccluded share of the hemisphere's directions (0: no normal)
    transfer_wp: wp.array2d
    visible_fraction_wp: wp.array
    occlusion_wp: wp.array2d       # (N, D) uint8 bit flags per direction (REAL, VIRTUAL)
    transfer_rv: np.ndarray | None = None          # (N, B*B) R_TRV (real + virtual occluding), with a virtual grid
    visible_fraction_rv: np.ndarray | None = None  # (N,) visible fraction under real + virtual geometry
    # (N, D) float32 distance at which real geometry blocks each ray (-1: it does not), with hit_distances
    hit_distance_wp: wp.array2d | None = None


def make_direction_set(rays: int, bands: int, seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """2 * rays spherical-Fibonacci directions over the whole sphere (about `rays` in any hemisphere),
    randomly rotated when seed is given, and their SH table: dirs (D, 3) and Y (D, bands^2), float32."""
    if rays < 1 or bands < 1:
        raise ValueError(f"make_direction_set: rays and bands must be >= 1, got {rays}, {bands}")
    dirs = fibonacci_sphere(2 * rays, rotation_seed=seed)
    return dirs.astype(np.float32), sh_basis(dirs, bands).astype(np.float32)


@wp.func
def ray_hit(sdf: wp.array3d(dtype=SDF_DTYPE), empty: wp.array3d(dtype=wp.uint8), cell: int, origin: wp.vec3,
            voxel: float, trunc: float, o: wp.vec3, w: wp.vec3, length: float, min_step: float) -> float:
    """The first t in [0, length] at which the SDF on o + t w turns negative, interpolated linearly between the
    last two samples (the surface, to a fraction of a step); -1 when it never does (SDF-sized steps, >= min_step,
    jumping across empty cells)."""
    inv_voxel = 1.0 / voxel
    hi = origin + wp.vec3(float(sdf.shape[0] - 1), float(sdf.shape[1] - 1), float(sdf.shape[2] - 1)) * voxel
    span = ray_box(o, w, origin, hi)
    t = wp.max(span[0], 0.0)
    t_end = wp.min(span[1], length)
    band = 0.999 * trunc
    t_prev = float(-1.0)
    s_prev = float(0.0)
    while t <= t_end:
        p = o + w * t
        s = sample_sdf(sdf, origin, inv_voxel, trunc, p)
        if s < 0.0:
            if t_prev >= 0.0:
                return t_prev + (t - t_prev) * s_prev / (s_prev - s)
            return t
        step = wp.max(s, min_step)
        if s >= band:
            step = wp.max(step, free_run(empty, origin, inv_voxel, voxel, cell, p))
        t_prev = t
        s_prev = s
        t = t + step
    return -1.0


@wp.func
def ray_blocked(sdf: wp.array3d(dtype=SDF_DTYPE), empty: wp.array3d(dtype=wp.uint8), cell: int, origin: wp.vec3,
                voxel: float, trunc: float, o: wp.vec3, w: wp.vec3, length: float, min_step: float) -> bool:
    """True when the SDF turns negative on o + t w, 0 <= t <= length (ray_hit's march)."""
    return ray_hit(sdf, empty, cell, origin, voxel, trunc, o, w, length, min_step) >= 0.0


@wp.kernel
def _occlusion(sdf: wp.array3d(dtype=SDF_DTYPE), empty: wp.array3d(dtype=wp.uint8), cell: int, origin: wp.vec3,
               voxel: float, trunc: float, points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
               dirs: wp.array(dtype=wp.vec3), offset: float, ray_length: float, min_step: float,
               has_virtual: int, vsdf: wp.array3d(dtype=SDF_DTYPE), vempty: wp.array3d(dtype=wp.uint8), vcell: int,
               vorigin: wp.vec3, vvoxel: float, vtrunc: float, vmin_step: float, want_hits: int, row0: int,
               occ: wp.array2d(dtype=wp.uint8), hits: wp.array2d(dtype=wp.float32)):
    t, k = wp.tid()
    i = row0 + t
    n = normals[i]
    w = dirs[k]
    bits = int(0)
    t_hit = float(-1.0)
    if wp.dot(n, w) > 0.0:
        o = points[i] + n * offset
        t_hit = ray_hit(sdf, empty, cell, origin, voxel, trunc, o, w, ray_length, min_step)
        if t_hit >= 0.0:
            bits = REAL
        if has_virtual != 0:
            if ray_blocked(vsdf, vempty, vcell, vorigin, vvoxel, vtrunc, o, w, ray_length, vmin_step):
                bits = bits | VIRTUAL
    occ[i, k] = wp.uint8(bits)
    if want_hits != 0:
        hits[i, k] = t_hit


MAX_COEFFS = 64              # B*B of the most bands a session allows (lighting.bands <= 8)
_Coeffs = wp.types.vector(length=MAX_COEFFS, dtype=wp.float32)


@wp.kernel
def _project(normals: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), ytab: wp.array2d(dtype=wp.float32),
             occ: wp.array2d(dtype=wp.uint8), mask: int, scale: float, group: int, row0: int,
             transfer: wp.array2d(dtype=wp.float32), visible: wp.array(dtype=wp.float32)):
    t, g = wp.tid()
    i = row0 + t
    k0 = g * group
    k1 = wp.min(k0 + group, ytab.shape[1])
    n = normals[i]
    acc = _Coeffs()    # a group's sums (a group of one keeps its sum in `one`: no local array read on a GPU)
    one = float(0.0)
    n_hemi = int(0)
    n_vis = int(0)
    for d in range(dirs.shape[0]):
        c = wp.dot(n, dirs[d])
        if c > 0.0:
            n_hemi += 1
            if (int(occ[i, d]) & mask) == 0:
                n_vis += 1
                if group == 1:
                    one += c * ytab[d, k0]
                else:
                    for k in range(k0, k1):
                        acc[k - k0] = acc[k - k0] + c * ytab[d, k]
    if group == 1:
        transfer[i, k0] = one * scale
    else:
        for k in range(k0, k1):
            transfer[i, k] = acc[k - k0] * scale
    if g == 0:
        frac = float(0.0)
        if n_hemi > 0:
            frac = float(n_vis) / float(n_hemi)
        visible[i] = frac


def _project_group(device: str, K: int) -> int:
    """Coefficients one _project thread sums: all of a point's on the CPU (each direction's cosine and test made once,
    not K times: 64 -> 21 ms of CPU a frame for TUM's 5848 samples at 5 bands), one on a GPU (K times the threads)."""
    return K if wp.get_device(device).is_cpu else 1


@wp.kernel
def _shade(normals: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), radiance: wp.array(dtype=wp.vec4),
           occ: wp.array2d(dtype=wp.uint8), row0: int, out: wp.array2d(dtype=wp.float32)):
    i = row0 + wp.tid()
    n = normals[i]
    lit = wp.vec3(0.0, 0.0, 0.0)
    lit_rv = wp.vec3(0.0, 0.0, 0.0)
    seen = float(0.0)
    seen_rv = float(0.0)
    for d in range(dirs.shape[0]):
        c = wp.dot(n, dirs[d])
        if c > 0.0:
            bits = int(occ[i, d])
            if (bits & REAL) == 0:
                r = radiance[d]
                lit += c * wp.vec3(r[0], r[1], r[2])
                seen += c * r[3]
                if (bits & VIRTUAL) == 0:
                    lit_rv += c * wp.vec3(r[0], r[1], r[2])
                    seen_rv += c * r[3]
    for k in range(3):
        out[i, k] = lit[k]
        out[i, 3 + k] = lit_rv[k]
    out[i, 6] = wp.clamp(1.0 - seen, 0.0, 1.0)
    out[i, 7] = wp.clamp(1.0 - seen_rv, 0.0, 1.0)


@wp.kernel
def _any_blocked(sdf: wp.array3d(dtype=SDF_DTYPE), empty: wp.array3d(dtype=wp.uint8), cell: int, origin: wp.vec3,
                 voxel: float, trunc: float, points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
                 dirs: wp.array(dtype=wp.vec3), offset: float, ray_length: float, min_step: float, row0: int,
                 hit: wp.array(dtype=wp.uint8)):
    t, d = wp.tid()
    i = row0 + t
    if hit[i] != wp.uint8(0):   # another of its rays is blocked (on the CPU a point's rays run in order: the first)
        return
    n = normals[i]
    w = dirs[d]
    if wp.dot(n, w) > 0.0:
        if ray_blocked(sdf, empty, cell, origin, voxel, trunc, points[i] + n * offset, w, ray_length, min_step):
            hit[i] = wp.uint8(1)


KEY_OFFSET = wp.constant(CELL_OFFSET)
KEY_SPAN = wp.constant(1 << CELL_BITS)


@wp.func
def cell_key(p: wp.vec3, cell: float) -> wp.int64:
    """The key of the world cell of `cell` metres holding p, as photoreg.lighting.exposure packs its map's keys:
    per axis floor(p / cell) + KEY_OFFSET, clamped to [0, KEY_SPAN), packed x, y, z."""
    key = wp.int64(0)
    for a in range(3):
        c = wp.int64(wp.floor(p[a] / cell)) + wp.int64(KEY_OFFSET)
        key = key * wp.int64(KEY_SPAN) + wp.clamp(c, wp.int64(0), wp.int64(KEY_SPAN) - wp.int64(1))
    return key


@wp.func
def find_key(keys: wp.array(dtype=wp.int64), key: wp.int64) -> int:
    """Index of `key` in the sorted `keys` (binary search), -1 when absent."""
    lo = int(0)
    hi = keys.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    if lo < keys.shape[0]:
        if keys[lo] == key:
            return lo
    return -1


@wp.kernel
def _observed_bounce(hits: wp.array2d(dtype=wp.float32), points: wp.array(dtype=wp.vec3),
                     normals: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), offset: float, scale: float,
                     cell: float, keys: wp.array(dtype=wp.int64), lum: wp.array(dtype=wp.float32), row0: int,
                     out: wp.array2d(dtype=wp.float32)):
    i = row0 + wp.tid()
    n = normals[i]
    o = points[i] + n * offset
    seen = float(0.0)
    unseen = float(0.0)
    for d in range(dirs.shape[0]):
        h = hits[i, d]
        if h >= 0.0:
            w = dirs[d]
            c = wp.max(wp.dot(n, w), 0.0) * scale
            j = find_key(keys, cell_key(o + w * h, cell))
            if j >= 0:
                seen += c * lum[j]
            else:
                unseen += c
    out[i, 0] = seen
    out[i, 1] = unseen


def _as_warp(device: str, *inputs: tuple) -> list[wp.array]:
    """Warp arrays on `device` of the inputs (array, Warp dtype, name, inner): vec rows (inner = 3 or 4: (..., inner),
    flattened to (N,)) or 2-D floats (inner None), numpy or Warp. Numpy ones are checked finite and uploaded in one copy
    (packing.upload); Warp ones must already be on `device` with the dtype."""
    out, host = [], []
    for a, dtype, what, inner in inputs:
        if isinstance(a, wp.array):
            if str(a.device) != device:
                raise ValueError(f"{what} lives on {a.device}, expected {device}")
            if a.dtype != dtype:
                raise ValueError(f"{what} has dtype {a.dtype}, expected {dtype}")
            if inner is None and a.ndim != 2:
                raise ValueError(f"{what} must be 2-D, got {a.shape}")
            out.append(a.flatten() if inner is not None else a)
            continue
        a = np.asarray(a, dtype=np.float32)
        if inner is not None:
            if a.shape[-1:] != (inner,):
                raise ValueError(f"{what} must be (..., {inner}), got {a.shape}")
            a = a.reshape(-1, inner)
        elif a.ndim != 2:
            raise ValueError(f"{what} must be 2-D, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what} has non-finite values")
        host.append((len(out), a, dtype))
        out.append(None)
    for (i, _, _), arr in zip(host, upload([a for _, a, _ in host], [dt for _, _, dt in host], device)):
        out[i] = arr
    return out


def _checked_rays(grid: DenseGrid, points, normals, dirs, offset: float, ray_length: float, device: str | None,
                  min_step_voxels: float, virtual: DenseGrid | None, *more: tuple) -> list:
    """Validated [device, points, normals, dirs] Warp arrays for a ray pass over `grid` (ValueError otherwise), then
    those of `more` inputs (_as_warp's), all uploaded together."""
    device = grid.device if device is None else str(wp.get_device(device))
    if device != grid.device:
        raise ValueError(f"radiance_transfer: grid lives on {grid.device}, asked to run on {device}")
    if virtual is not None and virtual.device != device:
        raise ValueError(f"radiance_transfer: virtual grid lives on {virtual.device}, expected {device}")
    if not (offset >= 0 and ray_length > 0 and min_step_voxels > 0):
        raise ValueError(f"radiance_transfer: need offset >= 0, ray_length > 0, min_step_voxels > 0 "
                         f"(got {offset}, {ray_length}, {min_step_voxels})")
    p, n, w, *rest = _as_warp(device, (points, wp.vec3, "points", 3), (normals, wp.vec3, "normals", 3),
                              (dirs, wp.vec3, "dirs", 3), *more)
    if p.shape != n.shape:
        raise ValueError(f"points {p.shape} and normals {n.shape} differ in count")
    return [device, p, n, w, *rest]


def _occlusion_pass(grid: DenseGrid, p, n, w, offset: float, ray_length: float, device: str, min_step_voxels: float,
                    virtual: DenseGrid | None, threads: int | None, hits: wp.array2d | None = None) -> wp.array2d:
    """(N, D) uint8 REAL / VIRTUAL flags of the checked rays (pass 1 of the module docstring); with `hits` (N, D)
    float32 also the distance at which real geometry blocks each ray (-1: not blocked or outside the hemisphere)."""
    occ = wp.zeros((p.shape[0], w.shape[0]), dtype=wp.uint8, device=device)
    v = grid if virtual is None else virtual  # a stand-in when there is no virtual grid (never marched)
    out = hits if hits is not None else wp.zeros((1, 1), dtype=wp.float32, device=device)  # never written
    launch_rows(_occlusion, occ.shape, device=device, threads=threads,
                inputs=[grid.sdf, grid.empty, int(grid.cell), wp.vec3(*grid.origin), float(grid.voxel_size),
                        float(grid.trunc), p, n, w, float(offset), float(ray_length),
                        float(min_step_voxels * grid.voxel_size), int(virtual is not None), v.sdf, v.empty,
                        int(v.cell), wp.vec3(*v.origin), float(v.voxel_size), float(v.trunc),
                        float(min_step_voxels * v.voxel_size), int(hits is not None)],
                outputs=[occ, out])
    return occ


def visibility(grid: DenseGrid, points, normals, dirs, offset: float, ray_length: float, device: str | None = None,
               min_step_voxels: float = 0.5, threads: int | None = None) -> np.ndarray:
    """(N, D) bool: ray d from points[i] + normals[i] * offset is in the normal's hemisphere and leaves the real
    geometry unblocked within ray_length (the occlusion pass alone, for arbitrary directions such as a light's)."""
    device, p, n, w = _checked_rays(grid, points, normals, dirs, offset, ray_length, device, min_step_voxels, None)
    occ = _occlusion_pass(grid, p, n, w, offset, ray_length, device, min_step_voxels, None, threads).numpy()
    return (n.numpy() @ w.numpy().T > 0) & (occ == 0)


def any_blocked(grid: DenseGrid, points, normals, dirs, offset: float, ray_length: float, device: str | None = None,
                min_step_voxels: float = 0.5, threads: int | None = None) -> np.ndarray:
    """(N,) bool: some ray of `dirs` in the normal's hemisphere from points[i] + normals[i] * offset is blocked
    by `grid` within ray_length; the same march as the occlusion pass, a point's rays skipped once one is found
    blocked. With the virtual objects' grid: the points whose R_TRV can differ from R_TR (their VIRTUAL flags)."""
    device, p, n, w = _checked_rays(grid, points, normals, dirs, offset, ray_length, device, min_step_voxels, None)
    hit = wp.zeros(p.shape[0], dtype=wp.uint8, device=device)
    # a thread per ray, not per point marching its rays in turn: a point's hundred-odd marches one after another
    # left the GPU's threads waiting on memory (TUM with the bunny: some 2500 points near it)
    launch_rows(_any_blocked, (p.shape[0], w.shape[0]), device=device, threads=threads,
                inputs=[grid.sdf, grid.empty, int(grid.cell), wp.vec3(*grid.origin), float(grid.voxel_size),
                        float(grid.trunc), p, n, w, float(offset), float(ray_length),
                        float(min_step_voxels * grid.voxel_size)],
                outputs=[hit])
    return hit.numpy().astype(bool)


def radiance_transfer(grid: DenseGrid, points, normals, dirs, ytable, offset: float, ray_length: float,
                      device: str | None = None, min_step_voxels: float = 0.5,
                      virtual: DenseGrid | None = None, threads: int | None = None,
                      hit_distances: bool = False) -> TransferResult:
    """R_TR and visible fraction at world points (N, 3) with unit world normals (N, 3; zero = skip),
    numpy or Warp (vec3, any shape: flattened), over the direction set from make_direction_set.
    With `virtual` (the virtual objects' SDF grid) the same ray pass also gives R_TRV (transfer_rv); with
    `hit_distances` the distance along each ray from points + normals * offset to the real surface that
    blocks it (hit_distance_wp; observed_bounce reads it). On the CPU the launches are split over `threads`
    threads (photoreg.kernels.launch)."""
    device, p, n, w, y = _checked_rays(grid, points, normals, dirs, offset, ray_length, device, min_step_voxels,
                                       virtual, (ytable, wp.float32, "ytable", None))
    if y.shape[0] != w.shape[0]:
        raise ValueError(f"ytable has {y.shape[0]} rows for {w.shape[0]} directions")
    bands_of(y.shape[1])
    N, D, K = p.shape[0], w.shape[0], y.shape[1]
    if K > MAX_COEFFS:
        raise ValueError(f"ytable has {K} coefficients, more than {MAX_COEFFS} ({MAX_COEFFS ** 0.5:g} bands)")
    scale = 4.0 / D
    hits = wp.empty((N, D), dtype=wp.float32, device=device) if hit_distances else None  # every ray writes
    occ = _occlusion_pass(grid, p, n, w, offset, ray_length, device, min_step_voxels, virtual, threads, hits)
    transfer = wp.zeros((N, K), dtype=wp.float32, device=device)
    visible = wp.zeros(N, dtype=wp.float32, device=device)
    transfer_rv = visible_rv = None
    group = _project_group(device, K)
    dim = (N, -(-K // group))
    launch_rows(_project, dim, device=device, threads=threads, inputs=[n, w, y, occ, REAL, scale, group],
                outputs=[transfer, visible])
    if virtual is not None:
        trv = wp.zeros((N, K), dtype=wp.float32, device=device)
        vrv = wp.zeros(N, dtype=wp.float32, device=device)
        launch_rows(_project, dim, device=device, threads=threads,
                    inputs=[n, w, y, occ, REAL | VIRTUAL, scale, group], outputs=[trv, vrv])
        transfer_rv, visible_rv = trv.numpy(), vrv.numpy()
    return TransferResult(transfer=transfer.numpy(), visible_fraction=visible.numpy(), transfer_wp=transfer,
                          visible_fraction_wp=visible, occlusion_wp=occ, transfer_rv=transfer_rv,
                          visible_fraction_rv=visible_rv, hit_distance_wp=hits)


def shaded_pass(grid: DenseGrid, virtual: DenseGrid, points, normals, dirs, weighted, offset: float,
                ray_length: float, min_step_voxels: float = 0.5, threads: int | None = None) -> np.ndarray:
    """(N, 8) float32 per point of one ray pass over `dirs` through the real `grid` and the virtual objects' grid
    `virtual`, given per direction (D, 4) `weighted`: its radiance times its quadrature weight over pi, L_d dw_d / pi,
    in columns 0-2, and in column 3 the weight dw_d / pi where the ray counts toward the blocked share (0 where not).
    Per point: columns 0-2 the shading, the sum over the rays clear of real geometry of max(n.w, 0) L_d dw_d / pi;
    3-5 the same over the rays clear of both grids; 6 and 7 the blocked shares, 1 - the sum over those rays of
    max(n.w, 0) times column 3, clipped to [0, 1]. For D equal-area directions over the sphere (dw / pi = 4 / D) and
    L_d = F.Y(w_d), that is F.R_TR, F.R_TRV and sh.blocked_share of radiance_transfer's R_TR and R_TRV (by
    linearity), in one thread per point."""
    device, p, n, w, table = _checked_rays(grid, points, normals, dirs, offset, ray_length, None, min_step_voxels,
                                           virtual, (weighted, wp.vec4, "shaded_pass: the weighted radiance", 4))
    if table.shape[0] != w.shape[0]:
        raise ValueError(f"shaded_pass: the weighted radiance has {table.shape[0]} rows for {w.shape[0]} directions")
    occ = _occlusion_pass(grid, p, n, w, offset, ray_length, device, min_step_voxels, virtual, threads)
    out = wp.empty((p.shape[0], 8), dtype=wp.float32, device=device)   # every row written
    launch_rows(_shade, (p.shape[0],), device=device, threads=threads,
                inputs=[n, w, table, occ], outputs=[out])
    return out.numpy()


def observed_bounce(tr: TransferResult, points, normals, dirs, offset: float, cell: float, keys: np.ndarray,
                    luminance: np.ndarray, threads: int | None = None) -> np.ndarray:
    """(N, 2) per point of a radiance_transfer(..., hit_distances=True) pass over `dirs` from points + normals *
    offset: the sum over its rays that real geometry blocks of (1/pi) max(n.w, 0) dw (dw = 4 pi / D) times the
    luminance of the cell the ray hits, where the sorted cell keys `keys` (cell_key's, cells of `cell` metres)
    hold it with `luminance`; and the same sum of weights alone over the other blocked rays."""
    if tr.hit_distance_wp is None:
        raise ValueError("observed_bounce needs the hit distances of the transfer pass (hit_distances=True)")
    hits = tr.hit_distance_wp
    device = str(hits.device)
    p, n, w = _as_warp(device, (points, wp.vec3, "points", 3), (normals, wp.vec3, "normals", 3),
                       (dirs, wp.vec3, "dirs", 3))
    if p.shape[0] != hits.shape[0] or n.shape[0] != hits.shape[0] or w.shape[0] != hits.shape[1]:
        raise ValueError(f"observed_bounce: {p.shape[0]} points, {n.shape[0]} normals and {w.shape[0]} directions "
                         f"for hit distances of shape {hits.shape}")
    k, lum = upload([np.asarray(keys, np.int64), np.asarray(luminance, np.float32)], [wp.int64, wp.float32], device)
    out = wp.zeros((hits.shape[0], 2), dtype=wp.float32, device=device)
    launch_rows(_observed_bounce, (hits.shape[0],), device=device, threads=threads,
                inputs=[hits, p, n, w, float(offset), 4.0 / hits.shape[1], float(cell), k, lum], outputs=[out])
    return out.numpy().astype(np.float64)
