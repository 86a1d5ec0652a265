"""Radiance transfer R(x) by visibility rays through dense SDF bricks, projected onto SH.

R(x)_i = (1/pi) * integral V(x, w) max(n.w, 0) Y_i(w) dw (DESIGN.md), by quadrature over a fixed set
of D equal-area directions covering the whole sphere: R_i = (1/pi) (4 pi / D) sum_{n.w_d > 0} V_d (n.w_d) Y_i(w_d).

Two passes, so that visibility against several grids shares one projection:
1. occlusion: one thread per (point, direction) marches the ray from x + n * offset and writes bit
   flags per direction: REAL when the real-geometry grid blocks it, VIRTUAL when the optional second
   grid (the voxelised virtual objects, photoreg.render.scene) blocks it, so one pass serves both;
2. projection: one thread per (point, coefficient) sums the hemisphere directions whose flags under
   `mask` are clear (mask REAL -> R_TR; REAL | VIRTUAL -> R_TRV), plus the visible fraction.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photoreg.device import init_warp
from photoreg.kernels.grid import SDF_DTYPE, DenseGrid, free_run, ray_box, sample_sdf
from photoreg.kernels.launch import launch_rows
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


def make_direction_set(rays: int, bands: int, seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """2 * rays spherical-Fibonacci directions over the whole sphere (about `rays` in any hemisphere),
    randomly rotated when seed is given, and their SH table: dirs (D, 3) and Y (D, bands^2), float32."""
    if rays < 1 or bands < 1:
        raise ValueError(f"make_direction_set: rays and bands must be >= 1, got {rays}, {bands}")
    dirs = fibonacci_sphere(2 * rays, rotation_seed=seed)
    return dirs.astype(np.float32), sh_basis(dirs, bands).astype(np.float32)


@wp.func
def ray_blocked(sdf: wp.array3d(dtype=SDF_DTYPE), empty: wp.array3d(dtype=wp.uint8), cell: int, origin: wp.vec3,
                voxel: float, trunc: float, o: wp.vec3, w: wp.vec3, length: float, min_step: float) -> bool:
    """True when the SDF turns negative on o + t w, 0 <= t <= length (SDF-sized steps, >= min_step,
    jumping across empty cells)."""
    inv_voxel = 1.0 / voxel
    hi = origin + wp.vec3(float(sdf.shape[0] - 1), float(sdf.shape[1] - 1), float(sdf.shape[2] - 1)) * voxel
    span = ray_box(o, w, origin, hi)
    t = wp.max(span[0], 0.0)
    t_end = wp.min(span[1], length)
    band = 0.999 * trunc
    while t <= t_end:
        p = o + w * t
        s = sample_sdf(sdf, origin, inv_voxel, trunc, p)
        if s < 0.0:
            return True
        step = wp.max(s, min_step)
        if s >= band:
            step = wp.max(step, free_run(empty, origin, inv_voxel, voxel, cell, p))
        t = t + step
    return False


@wp.kernel
def _occlusion(sdf: wp.array3d(dtype=SDF_DTYPE), empty: wp.array3d(dtype=wp.uint8), cell: int, origin: wp.vec3,
               voxel: float, trunc: float, points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
               dirs: wp.array(dtype=wp.vec3), offset: float, ray_length: float, min_step: float,
               has_virtual: int, vsdf: wp.array3d(dtype=SDF_DTYPE), vempty: wp.array3d(dtype=wp.uint8), vcell: int,
               vorigin: wp.vec3, vvoxel: float, vtrunc: float, vmin_step: float, row0: int,
               occ: wp.array2d(dtype=wp.uint8)):
    t, k = wp.tid()
    i = row0 + t
    n = normals[i]
    w = dirs[k]
    bits = int(0)
    if wp.dot(n, w) > 0.0:
        o = points[i] + n * offset
        if ray_blocked(sdf, empty, cell, origin, voxel, trunc, o, w, ray_length, min_step):
            bits = REAL
        if has_virtual != 0:
            if ray_blocked(vsdf, vempty, vcell, vorigin, vvoxel, vtrunc, o, w, ray_length, vmin_step):
                bits = bits | VIRTUAL
    occ[i, k] = wp.uint8(bits)


@wp.kernel
def _project(normals: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), ytab: wp.array2d(dtype=wp.float32),
             occ: wp.array2d(dtype=wp.uint8), mask: int, scale: float, row0: int,
             transfer: wp.array2d(dtype=wp.float32), visible: wp.array(dtype=wp.float32)):
    t, k = wp.tid()
    i = row0 + t
    n = normals[i]
    acc = float(0.0)
    n_hemi = int(0)
    n_vis = int(0)
    for d in range(dirs.shape[0]):
        c = wp.dot(n, dirs[d])
        if c > 0.0:
            n_hemi += 1
            if (int(occ[i, d]) & mask) == 0:
                n_vis += 1
                acc += c * ytab[d, k]
    transfer[i, k] = acc * scale
    if k == 0:
        frac = float(0.0)
        if n_hemi > 0:
            frac = float(n_vis) / float(n_hemi)
        visible[i] = frac


@wp.kernel
def _any_blocked(sdf: wp.array3d(dtype=SDF_DTYPE), empty: wp.array3d(dtype=wp.uint8), cell: int, origin: wp.vec3,
                 voxel: float, trunc: float, points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
                 dirs: wp.array(dtype=wp.vec3), offset: float, ray_length: float, min_step: float, row0: int,
                 hit: wp.array(dtype=wp.uint8)):
    i = row0 + wp.tid()
    n = normals[i]
    o = points[i] + n * offset
    for d in range(dirs.shape[0]):
        w = dirs[d]
        if wp.dot(n, w) > 0.0:
            if ray_blocked(sdf, empty, cell, origin, voxel, trunc, o, w, ray_length, min_step):
                hit[i] = wp.uint8(1)
                break


def _as_warp(a, dtype, device: str, what: str, inner: int | None):
    """A 1-D vec3 (inner=3) or 2-D float (inner=None) Warp array on `device` from numpy or Warp input."""
    if isinstance(a, wp.array):
        if str(a.device) != device:
            raise ValueError(f"{what} lives on {a.device}, expected {device}")
        if a.dtype != dtype:
            raise ValueError(f"{what} has dtype {a.dtype}, expected {dtype}")
        if inner is None and a.ndim != 2:
            raise ValueError(f"{what} must be 2-D, got {a.shape}")
        return a.flatten() if inner is not None else a
    a = np.asarray(a, dtype=np.float32)
    if inner is not None:
        if a.shape[-1] != inner:
            raise ValueError(f"{what} must be (..., {inner}), got {a.shape}")
        a = a.reshape(-1, inner)
    elif a.ndim != 2:
        raise ValueError(f"{what} must be 2-D, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has non-finite values")
    return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device)


def _checked_rays(grid: DenseGrid, points, normals, dirs, offset: float, ray_length: float, device: str | None,
                  min_step_voxels: float, virtual: DenseGrid | None):
    """Validated (device, points, normals, dirs) Warp arrays for a ray pass over `grid` (ValueError otherwise)."""
    device = grid.device if device is None else str(wp.get_device(device))
    if device != grid.device:
        raise ValueError(f"radiance_transfer: grid lives on {grid.device}, asked to run on {device}")
    if virtual is not None and virtual.device != device:
        raise ValueError(f"radiance_transfer: virtual grid lives on {virtual.device}, expected {device}")
    if not (offset >= 0 and ray_length > 0 and min_step_voxels > 0):
        raise ValueError(f"radiance_transfer: need offset >= 0, ray_length > 0, min_step_voxels > 0 "
                         f"(got {offset}, {ray_length}, {min_step_voxels})")
    p = _as_warp(points, wp.vec3, device, "points", 3)
    n = _as_warp(normals, wp.vec3, device, "normals", 3)
    w = _as_warp(dirs, wp.vec3, device, "dirs", 3)
    if p.shape != n.shape:
        raise ValueError(f"points {p.shape} and normals {n.shape} differ in count")
    return device, p, n, w


def _occlusion_pass(grid: DenseGrid, p, n, w, offset: float, ray_length: float, device: str, min_step_voxels: float,
                    virtual: DenseGrid | None, threads: int | None) -> wp.array2d:
    """(N, D) uint8 REAL / VIRTUAL flags of the checked rays (pass 1 of the module docstring)."""
    occ = wp.zeros((p.shape[0], w.shape[0]), dtype=wp.uint8, device=device)
    v = grid if virtual is None else virtual  # a stand-in when there is no virtual grid (never marched)
    launch_rows(_occlusion, occ.shape, device=device, threads=threads,
                inputs=[grid.sdf, grid.empty, int(grid.cell), wp.vec3(*grid.origin), float(grid.voxel_size),
                        float(grid.trunc), p, n, w, float(offset), float(ray_length),
                        float(min_step_voxels * grid.voxel_size), int(virtual is not None), v.sdf, v.empty,
                        int(v.cell), wp.vec3(*v.origin), float(v.voxel_size), float(v.trunc),
                        float(min_step_voxels * v.voxel_size)],
                outputs=[occ])
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
    by `grid` within ray_length; the same march as the occlusion pass, stopping at a point's first hit. With
    the virtual objects' grid: the points whose R_TRV can differ from R_TR (their VIRTUAL flags)."""
    device, p, n, w = _checked_rays(grid, points, normals, dirs, offset, ray_length, device, min_step_voxels, None)
    hit = wp.zeros(p.shape[0], dtype=wp.uint8, device=device)
    launch_rows(_any_blocked, hit.shape, device=device, threads=threads,
                inputs=[grid.sdf, grid.empty, int(grid.cell), wp.vec3(*grid.origin), float(grid.voxel_size),
                        float(grid.trunc), p, n, w, float(offset), float(ray_length),
                        float(min_step_voxels * grid.voxel_size)],
                outputs=[hit])
    return hit.numpy().astype(bool)


def radiance_transfer(grid: DenseGrid, points, normals, dirs, ytable, offset: float, ray_length: float,
                      device: str | None = None, min_step_voxels: float = 0.5,
                      virtual: DenseGrid | None = None, threads: int | None = None) -> TransferResult:
    """R_TR and visible fraction at world points (N, 3) with unit world normals (N, 3; zero = skip),
    numpy or Warp (vec3, any shape: flattened), over the direction set from make_direction_set.
    With `virtual` (the virtual objects' SDF grid) the same ray pass also gives R_TRV (transfer_rv).
    On the CPU the launches are split over `threads` threads (photoreg.kernels.launch)."""
    device, p, n, w = _checked_rays(grid, points, normals, dirs, offset, ray_length, device, min_step_voxels, virtual)
    y = _as_warp(ytable, wp.float32, device, "ytable", None)
    if y.shape[0] != w.shape[0]:
        raise ValueError(f"ytable has {y.shape[0]} rows for {w.shape[0]} directions")
    bands_of(y.shape[1])
    N, D, K = p.shape[0], w.shape[0], y.shape[1]
    occ = _occlusion_pass(grid, p, n, w, offset, ray_length, device, min_step_voxels, virtual, threads)
    transfer = wp.zeros((N, K), dtype=wp.float32, device=device)
    visible = wp.zeros(N, dtype=wp.float32, device=device)
    transfer_rv = visible_rv = None
    launch_rows(_project, (N, K), device=device, threads=threads, inputs=[n, w, y, occ, REAL, 4.0 / D],
                outputs=[transfer, visible])
    if virtual is not None:
        trv = wp.zeros((N, K), dtype=wp.float32, device=device)
        vrv = wp.zeros(N, dtype=wp.float32, device=device)
        launch_rows(_project, (N, K), device=device, threads=threads, inputs=[n, w, y, occ, REAL | VIRTUAL, 4.0 / D],
                    outputs=[trv, vrv])
        transfer_rv, visible_rv = trv.numpy(), vrv.numpy()
    return TransferResult(transfer=transfer.numpy(), visible_fraction=visible.numpy(), transfer_wp=transfer,
                          visible_fraction_wp=visible, occlusion_wp=occ, transfer_rv=transfer_rv,
                          visible_fraction_rv=visible_rv)
