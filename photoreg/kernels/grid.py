"""Dense SDF brick on the Warp device: its description, sampling functions, and the export kernels.

The brick is a wp.array3d indexed [ix, iy, iz]; voxel (ix, iy, iz) holds the signed distance in metres
(positive in free space, negative behind surfaces, clamped to +-trunc) at the world position
origin + (ix, iy, iz) * voxel_size (the voxel centre). Unobserved voxels hold +trunc, so every
consumer treats unknown space as empty. Samples outside the brick also read +trunc.

Empty-space skipping: the brick is tiled in cells of `cell` voxels (the fusion blocks); `empty[c]` is
the Chebyshev distance, in cells and capped at EMPTY_CAP, from cell c to the nearest cell holding any
voxel below +trunc. Within (d - 1) * cell - 1 voxels of any point of a cell at distance d every
trilinear sample reads +trunc, so marchers may jump that far (free_run).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from photoreg.device import init_warp
from photoreg.kernels.launch import launch_rows

wp = init_warp()

EMPTY_CAP = 8  # cap of the empty-space distance in cells; longer empty runs are still skipped in 7-cell jumps
# The brick's storage type: half precision (0.05% of trunc, a few hundredths of a millimetre at the usual 4 cm)
# halves its memory and the memory traffic of every march; kernels read it as float32.
SDF_DTYPE = wp.float16
SDF_NUMPY = np.float16


@dataclass
class DenseGrid:
    """A dense SDF brick exported from the fusion volume (see the module docstring for the layout).

    The array is live: later exports update it in place, or replace it when the brick grows, so
    take a fresh DenseGrid from the volume after each integration.
    """

    sdf: wp.array3d        # SDF_DTYPE (float16) metres, indexed [ix, iy, iz]
    origin: np.ndarray     # (3,) float64, world position of voxel (0, 0, 0)'s centre
    voxel_size: float      # metres
    trunc: float           # metres; |sdf| <= trunc, +trunc = free or unobserved
    shape: tuple[int, int, int]
    empty: wp.array3d      # uint8 (shape / cell), Chebyshev cell distance to the nearest non-empty cell
    cell: int              # voxels per cell edge

    @property
    def device(self) -> str:
        return str(self.sdf.device)

    def world_to_index(self, points: np.ndarray) -> np.ndarray:
        """Continuous voxel coordinates (N, 3) of world points (N, 3)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) / self.voxel_size


@wp.func
def sample_sdf(sdf: wp.array3d(dtype=SDF_DTYPE), origin: wp.vec3, inv_voxel: float, trunc: float,
               p: wp.vec3) -> float:
    """Trilinear SDF at world point p; +trunc (empty) outside the brick."""
    g = (p - origin) * inv_voxel
    fx = wp.floor(g[0])
    fy = wp.floor(g[1])
    fz = wp.floor(g[2])
    i = int(fx)
    j = int(fy)
    k = int(fz)
    if i < 0 or j < 0 or k < 0 or i >= sdf.shape[0] - 1 or j >= sdf.shape[1] - 1 or k >= sdf.shape[2] - 1:
        return trunc
    tx = g[0] - fx
    ty = g[1] - fy
    tz = g[2] - fz
    c00 = wp.lerp(float(sdf[i, j, k]), float(sdf[i + 1, j, k]), tx)
    c10 = wp.lerp(float(sdf[i, j + 1, k]), float(sdf[i + 1, j + 1, k]), tx)
    c01 = wp.lerp(float(sdf[i, j, k + 1]), float(sdf[i + 1, j, k + 1]), tx)
    c11 = wp.lerp(float(sdf[i, j + 1, k + 1]), float(sdf[i + 1, j + 1, k + 1]), tx)
    return wp.lerp(wp.lerp(c00, c10, ty), wp.lerp(c01, c11, ty), tz)


@wp.func
def free_run(empty: wp.array3d(dtype=wp.uint8), origin: wp.vec3, inv_voxel: float, voxel: float, cell: int,
             p: wp.vec3) -> float:
    """Distance from p (metres) over which every SDF sample is certainly +trunc; 0 near surfaces."""
    g = (p - origin) * (inv_voxel / float(cell))
    i = int(wp.floor(g[0]))
    j = int(wp.floor(g[1]))
    k = int(wp.floor(g[2]))
    if i < 0 or j < 0 or k < 0 or i >= empty.shape[0] or j >= empty.shape[1] or k >= empty.shape[2]:
        return 0.0
    d = int(empty[i, j, k])
    if d < 2:
        return 0.0
    return float((d - 1) * cell - 1) * voxel


@wp.func
def ray_box(o: wp.vec3, d: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> wp.vec2:
    """Parametric interval [t0, t1] of the ray o + t d inside the box [lo, hi] (t0 > t1: missed)."""
    t0 = float(-1.0e30)
    t1 = float(1.0e30)
    for a in range(3):
        if wp.abs(d[a]) < 1.0e-12:
            if o[a] < lo[a] or o[a] > hi[a]:
                return wp.vec2(1.0, -1.0)
        else:
            inv = 1.0 / d[a]
            ta = (lo[a] - o[a]) * inv
            tb = (hi[a] - o[a]) * inv
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
    return wp.vec2(t0, t1)


@wp.kernel
def _clear_cells(keys: wp.array2d(dtype=wp.int32), lo_cell: wp.vec3i, occupied: wp.array3d(dtype=wp.uint8)):
    m = wp.tid()
    i = keys[m, 0] - lo_cell[0]
    j = keys[m, 1] - lo_cell[1]
    k = keys[m, 2] - lo_cell[2]
    if i >= 0 and j >= 0 and k >= 0 and i < occupied.shape[0] and j < occupied.shape[1] and k < occupied.shape[2]:
        occupied[i, j, k] = wp.uint8(0)


@wp.kernel
def _scatter_blocks(keys: wp.array2d(dtype=wp.int32), bufs: wp.array(dtype=wp.int32),
                    found: wp.array(dtype=wp.bool), tsdf: wp.array2d(dtype=wp.float32),
                    weight: wp.array2d(dtype=wp.float32), res: int, lo_cell: wp.vec3i, trunc: float,
                    min_weight: float, row0: int, sdf: wp.array3d(dtype=SDF_DTYPE),
                    occupied: wp.array3d(dtype=wp.uint8)):
    # One thread per voxel column along z (the brick's fastest axis; a thread per voxel costs ~4x more
    # on one CPU core). Open3D stores a block z-major: local index (z * res + y) * res + x.
    tm, x, y = wp.tid()
    m = row0 + tm
    if not found[m]:
        return
    ci = keys[m, 0] - lo_cell[0]
    cj = keys[m, 1] - lo_cell[1]
    ck = keys[m, 2] - lo_cell[2]
    if ci < 0 or cj < 0 or ck < 0 or ci >= occupied.shape[0] or cj >= occupied.shape[1] or ck >= occupied.shape[2]:
        return
    b = bufs[m]
    ix = ci * res + x
    iy = cj * res + y
    any_surface = int(0)
    for z in range(res):
        lin = (z * res + y) * res + x
        value = trunc
        if weight[b, lin] >= min_weight:
            value = tsdf[b, lin] * trunc
        sdf[ix, iy, ck * res + z] = SDF_DTYPE(value)
        if value < trunc:
            any_surface = 1
    if any_surface != 0:
        occupied[ci, cj, ck] = wp.uint8(1)  # every writer stores the same value: no atomics needed


@wp.kernel
def _copy_into(src: wp.array3d(dtype=Any), offset: wp.vec3i, dst: wp.array3d(dtype=Any)):
    i, j, k = wp.tid()
    dst[i + offset[0], j + offset[1], k + offset[2]] = src[i, j, k]


@wp.kernel
def _distance_pass(src: wp.array3d(dtype=wp.uint8), axis: int, n: int, cap: int, occupancy: int,
                   dst: wp.array3d(dtype=wp.uint8)):
    # one axis of the separable capped Chebyshev distance transform: dst(p) = min(cap, min over t of
    # max(|t|, d(p + t e_axis))), d = src, or with occupancy != 0 0 where src is set and cap elsewhere;
    # n = src.shape[axis]; outside the brick is empty
    i, j, k = wp.tid()
    p = i
    if axis == 1:
        p = j
    elif axis == 2:
        p = k
    d = int(src[i, j, k])
    if occupancy != 0:
        d = wp.where(d != 0, 0, cap)
    d = wp.min(d, cap)
    t = int(1)
    while t < d:   # max(t, .) >= t: no offset of t or more improves on d
        for side in range(2):
            q = p - t + 2 * t * side
            if q >= 0 and q < n:
                a = i
                b = j
                c = k
                if axis == 0:
                    a = q
                elif axis == 1:
                    b = q
                else:
                    c = q
                v = int(src[a, b, c])
                if occupancy != 0:
                    v = wp.where(v != 0, 0, cap)
                d = wp.min(d, wp.max(t, v))
        t += 1
    dst[i, j, k] = wp.uint8(d)


def scatter_blocks(keys, bufs, found, tsdf, weight, block_resolution: int, lo_block, trunc: float,
                   min_weight: float, sdf, occupied) -> None:
    """Write whole Open3D blocks into the brick: keys (M, 3) int32 block coordinates, bufs (M,) their
    buffer indices, found (M,) bool; tsdf/weight (capacity, res^3) float32 (normalised tsdf, weight);
    lo_block = block coordinate of the brick's first block (= cell). Voxels below min_weight become
    +trunc; `occupied` (uint8 per cell) records whether a written block holds anything below +trunc."""
    n = keys.shape[0]
    if n == 0:
        return
    r3 = block_resolution ** 3
    if tsdf.shape[1] != r3 or weight.shape != tsdf.shape:
        raise ValueError(f"tsdf/weight must be (capacity, {r3}), got {tsdf.shape} and {weight.shape}")
    lo = wp.vec3i(*(int(v) for v in lo_block))
    wp.launch(_clear_cells, dim=n, inputs=[keys, lo, occupied], device=sdf.device)
    # on the CPU split over threads by blocks (kernels.launch): a block's voxels are its own, and a block touched by
    # two frames since the last export writes the same values twice
    launch_rows(_scatter_blocks, (n, block_resolution, block_resolution),
                inputs=[keys, bufs, found, tsdf, weight, int(block_resolution), lo, float(trunc), float(min_weight)],
                outputs=[sdf, occupied], device=str(sdf.device))


def copy_into(src, dst, offset) -> None:
    """dst[offset + idx] = src[idx] for every element of src (growing a brick keeps what it held)."""
    off = [int(v) for v in offset]
    if any(o < 0 or o + s > d for o, s, d in zip(off, src.shape, dst.shape)):
        raise ValueError(f"brick of shape {src.shape} at offset {off} does not fit in {dst.shape}")
    if dst.device.is_cpu and src.device.is_cpu:  # numpy views of CPU arrays: a 54M-voxel brick in 40 ms, not 1 s
        dst.numpy()[tuple(slice(o, o + s) for o, s in zip(off, src.shape))] = src.numpy()
        return
    wp.launch(_copy_into, dim=src.shape, inputs=[src, wp.vec3i(*off), dst], device=dst.device)


def update_empty_distance(occupied, empty) -> None:
    """Recompute the capped Chebyshev distance field `empty` from the cell occupancy (uint8, same shape): one pass
    per axis (the Chebyshev distance to a set is the minimum over its offsets of their largest component), 3
    launches where the 26-neighbour dilation took EMPTY_CAP, each reading at most 2 (EMPTY_CAP - 1) cells against 26
    (TUM's 25 x 25 x 15 cells on the 2-core CPU: 1.1 ms against 3.6). Not split over CPU threads (kernels.launch):
    a room's brick has a few thousand cells, where the split costs more than it saves."""
    tmp = wp.empty_like(empty)
    for axis, (src, dst) in enumerate(((occupied, empty), (empty, tmp), (tmp, empty))):
        wp.launch(_distance_pass, dim=occupied.shape, inputs=[src, axis, int(occupied.shape[axis]), EMPTY_CAP,
                                                              int(axis == 0)], outputs=[dst], device=occupied.device)
