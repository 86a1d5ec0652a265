"""Tiny analytic RGB-D scenes for end-to-end tests: a floor and a box under a distant light plus ambient,
written as native recordings (with poses, intrinsics and the matching ground-truth lighting)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from photoreg.io.images import linear_to_srgb
from photoreg.io.native import NativeWriter
from photoreg.lighting import sh
from photoreg.synth.cameras import look_at  # noqa: F401  (re-exported for tests that build poses)
from photoreg.types import Intrinsics

BOX = (np.array([-0.15, -0.1, 0.0]), np.array([0.15, 0.2, 0.25]))   # axis-aligned box on the floor, metres
LIGHT = np.array([0.5, -0.3, 0.8]) / np.linalg.norm([0.5, -0.3, 0.8])
AMBIENT, SUN = 0.25, 0.9   # shading = AMBIENT + SUN * max(n.LIGHT, 0)


def render(k: Intrinsics, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Analytic ray cast of the floor (z = 0) and BOX, Lambertian, unshadowed: 8-bit sRGB colour and
    depth in metres (camera z)."""
    u, v = np.meshgrid(np.arange(k.width), np.arange(k.height))
    d = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones(u.shape)], -1) @ pose[:3, :3].T  # t = camera z
    o = pose[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(d[..., 2] < 0, -o[2] / d[..., 2], np.inf)
        t0, t1 = (BOX[0] - o) / d, (BOX[1] - o) / d
        near, far = np.minimum(t0, t1), np.maximum(t0, t1)
    t_box = np.where((near.max(-1) <= far.min(-1)) & (near.max(-1) > 0), near.max(-1), np.inf)
    normal = np.zeros(d.shape)
    normal[..., 2] = 1.0
    hit_box = t_box < t_floor
    axis = near.argmax(-1)
    sign = -np.sign(np.take_along_axis(d, axis[..., None], -1)[..., 0])
    normal[hit_box] = 0.0
    normal[hit_box, axis[hit_box]] = sign[hit_box]
    t = np.minimum(t_box, t_floor)
    albedo = np.where(hit_box[..., None], [0.7, 0.3, 0.2], [0.5, 0.5, 0.5])
    shade = AMBIENT + SUN * np.clip(normal @ LIGHT, 0, None)
    color = linear_to_srgb((albedo * shade[..., None]).astype(np.float32))
    depth = np.where(np.isfinite(t), t, 0.0).astype(np.float32)
    return color, depth


def ground_truth_sh(bands: int = 3) -> np.ndarray:
    """SH of the scene's radiance (constant AMBIENT plus a SUN * pi delta along LIGHT), grey, (3, B*B):
    the transfer convention of DESIGN.md turns it into exactly the shading `render` uses (unoccluded)."""
    f = math.pi * SUN * sh.sh_basis(LIGHT[None], bands)[0]
    f[0] += AMBIENT / sh.sh_basis(np.array([[0.0, 0.0, 1.0]]), 1)[0, 0]
    return np.tile(f, (3, 1))


def write_recording(root: Path, k: Intrinsics, n: int, with_gt: bool = True) -> Path:
    """A native recording: the camera orbits the box at 1.2 m, 30 frames/s; lighting_gt.json when with_gt."""
    w = NativeWriter(root, k, source="tests/scenes.py")
    for i in range(n):
        a = -0.3 + 0.6 * i / max(n - 1, 1)
        pose = look_at(np.array([1.2 * np.sin(a), -1.2 * np.cos(a), 0.8]), np.array([0.0, 0.0, 0.1]))
        color, depth = render(k, pose)
        w.write_frame(i, 100.0 + i / 30, color, depth, pose)
    if with_gt:
        w.write_lighting_gt(ground_truth_sh())
    w.finish()
    return root
