"""Which ray-cast samples the lighting may trust: the fused surface must agree with this frame's depth.

The ray-cast TSDF normal is wrong where the volume is thin or half observed (the image border of the
first frames, the floor just behind an object's silhouette): measured on data/demo, 3-8% of the floor
samples had normals tilted by more than 18 degrees, and with the normal-distribution weights they
dragged the lighting by tens of degrees. The box-averaged radiance of a sample is wrong where its box
straddles a depth edge (colour from two surfaces). Both are caught here by comparing, at each sample
pixel, the ray-cast surface with the frame's own depth map: the depth must match and the normal of
the depth map (central differences over `step` pixels) must lie within `max_angle_deg` of the ray-cast
normal. Pixels where the depth map gives no normal (holes, image border) are not trusted.
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

    def point(rr, cc):
        inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        z = np.where(inside, depth[np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1)], 0.0)
        z = np.where(np.isfinite(z), z, 0.0)
        p = np.stack([(cc - intr.cx) / intr.fx * z, (rr - intr.cy) / intr.fy * z, z], axis=-1)
        return p, z > 0

    (px1, ok1), (px0, ok0) = point(r, c + step), point(r, c - step)
    (py1, ok2), (py0, ok3) = point(r + step, c), point(r - step, c)
    n = np.cross(px1 - px0, py1 - py0)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = ok0 & ok1 & ok2 & ok3 & (norm[..., 0] > 0)
    n = np.where(ok[..., None], n / np.maximum(norm, 1e-30), 0.0)
    return -n  # x-right, y-down cross product points away from the camera; flip to face it


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
