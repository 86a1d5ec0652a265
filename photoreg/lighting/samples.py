"""Which ray-cast samples the lighting may trust: the fused surface must agree with this frame's depth.

The ray-cast TSDF normal is wrong where the volume is thin or half observed (the image border of the
first frames, the floor just behind an object's silhouette): measured on data/demo, 3-8% of the floor
samples had normals tilted by more than 18 degrees, and with the normal-distribution weights they
dragged the lighting by tens of degrees. The box-averaged radiance of a sample is wrong where its box
straddles a depth edge (colour from two surfaces). Both are caught here by comparing, at each sample
pixel, the ray-cast surface with the frame's own depth map: the depth must match and the normal of
the depth map (central differences over `step` pixels) must lie within `max_angle_deg` of the ray-cast
normal. Pixels where the depth map gives no normal (holes, image border) are not trusted. On a GPU
photoreg.kernels.samples makes the same checks at every map pixel in one kernel.
"""
from __future__ import annotations

import math

import numpy as np

from ..types import Intrinsics


def depth_normals(depth: np.ndarray, intr: Intrinsics, rows: np.ndarray, cols: np.ndarray, step: int) -> np.ndarray:
    """Camera-frame unit normals (*rows.shape, 3) of the depth map at the pixels (rows, cols) (integer arrays
    of one shape), facing the camera; zero where a neighbour `step` pixels away is missing or off the image."""
    h, w = depth.shape
    r, c = np.asarray(rows), np.asarray(cols)
    # the four neighbours (right, left, below, above) gathered at once: 1.7x faster than one by one
    rr = np.stack([r, r, r + step, r - step])
    cc = np.stack([c + step, c - step, c, c])
    inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
    z = np.where(inside, depth[np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1)], 0.0)
    z = np.where(np.isfinite(z), z, 0.0)
    x, y = (cc - intr.cx) / intr.fx * z, (rr - intr.cy) / intr.fy * z
    ax, ay, az = x[0] - x[1], y[0] - y[1], z[0] - z[1]   # along the row
    bx, by, bz = x[2] - x[3], y[2] - y[3], z[2] - z[3]   # along the column
    # their cross product, negated: x-right, y-down a x b points away from the camera; flipped to face it
    n = np.stack([az * by - ay * bz, ax * bz - az * bx, ay * bx - ax * by], axis=-1)
    norm = np.sqrt(np.einsum("...i,...i->...", n, n))[..., None]
    ok = (z > 0).all(axis=0) & (norm[..., 0] > 0)
    return np.where(ok[..., None], n / np.maximum(norm, 1e-30), 0.0)


def agreement(depth: np.ndarray, intr: Intrinsics, pose: np.ndarray, rows: np.ndarray, cols: np.ndarray,
              surface_depth: np.ndarray, surface_normal: np.ndarray, step: int, max_angle_deg: float,
              max_depth_gap: float) -> np.ndarray:
    """Bool per pixel (rows, cols): the ray-cast surface there (camera z `surface_depth`, world normal
    `surface_normal` (..., 3)) agrees with the frame's depth map (HxW metres, 0 invalid) within
    `max_depth_gap` metres and `max_angle_deg` in normal direction (depth-map normals over `step` pixels)."""
    z = depth[rows, cols]
    n_depth = depth_normals(depth, intr, rows, cols, step)
    n_surface = surface_normal @ np.asarray(pose, dtype=np.float64)[:3, :3]  # world -> camera
    cos = (n_depth * n_surface).sum(axis=-1)
    return (np.abs(z - surface_depth) <= max_depth_gap) & (z > 0) & (cos >= math.cos(math.radians(max_angle_deg)))
