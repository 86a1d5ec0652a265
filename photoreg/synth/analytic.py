"""Exact ray casting of a few primitives (a room seen from inside, solid boxes, spheres) in numpy:
ground-truth depth, normals and visibility for testing and timing reconstruction without a renderer."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from photoreg.types import Intrinsics


@dataclass
class PrimitiveScene:
    """Axis-aligned boxes and spheres in world metres; `room` is a box whose inside is the free space."""

    room: tuple[np.ndarray, np.ndarray] | None = None
    boxes: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    spheres: list[tuple[np.ndarray, float]] = field(default_factory=list)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of rays o + t d (t > 0, d need not be unit): t (N,) (inf = miss) and the unit
        world normal at the hit (N, 3), facing the incoming ray."""
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        o = np.broadcast_to(o, d.shape)
        t_best = np.full(len(d), np.inf)
        n_best = np.zeros(d.shape)

        def keep(t, n):
            better = (t > 1e-9) & (t < t_best)
            t_best[better] = t[better]
            n_best[better] = n[better]

        with np.errstate(divide="ignore", invalid="ignore"):
            if self.room is not None:  # leave the room through the nearest wall ahead
                lo, hi = (np.asarray(c, dtype=np.float64) for c in self.room)
                t_axis = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf))
                axis = np.argmin(t_axis, axis=1)
                n = np.zeros(d.shape)
                n[np.arange(len(d)), axis] = -np.sign(d[np.arange(len(d)), axis])
                keep(t_axis[np.arange(len(d)), axis], n)
            for lo, hi in self.boxes:  # slab test, entering face
                t0, t1 = (np.asarray(lo) - o) / d, (np.asarray(hi) - o) / d
                near, far = np.minimum(t0, t1), np.maximum(t0, t1)
                near = np.where(np.isnan(near), -np.inf, near)
                far = np.where(np.isnan(far), np.inf, far)
                t_in, t_out = near.max(axis=1), far.min(axis=1)
                axis = near.argmax(axis=1)
                n = np.zeros(d.shape)
                n[np.arange(len(d)), axis] = -np.sign(d[np.arange(len(d)), axis])
                keep(np.where((t_in <= t_out) & (t_in > 0), t_in, np.inf), n)
            for centre, radius in self.spheres:
                oc = o - np.asarray(centre)
                a = np.einsum("ij,ij->i", d, d)
                b = np.einsum("ij,ij->i", oc, d)
                disc = b * b - a * (np.einsum("ij,ij->i", oc, oc) - radius * radius)
                t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
                t = np.where((disc >= 0) & (t > 0), t, np.inf)
                p = o + d * np.where(np.isfinite(t), t, 0.0)[:, None]
                keep(t, (p - np.asarray(centre)) / radius)
        return t_best, n_best

    def render_depth(self, intr: Intrinsics, pose_c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth (H, W) float32 camera z (0 = miss) and world normals (H, W, 3) float32 of a pinhole view."""
        u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
        ray_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], -1)
        d = ray_cam.reshape(-1, 3) @ np.asarray(pose_c2w)[:3, :3].T  # t along d = camera z
        t, n = self.intersect(np.asarray(pose_c2w)[:3, 3], d)
        depth = np.where(np.isfinite(t), t, 0.0).reshape(intr.height, intr.width)
        return depth.astype(np.float32), n.reshape(intr.height, intr.width, 3).astype(np.float32)


def box_room() -> PrimitiveScene:
    """A 2 x 2 x 2 m room (floor z = 0, world z up) with a box and a sphere on the floor; the floor's
    centre has nothing within 0.6 m above it."""
    return PrimitiveScene(
        room=(np.array([-1.0, -1.0, 0.0]), np.array([1.0, 1.0, 2.0])),
        boxes=[(np.array([0.5, -0.9, 0.0]), np.array([0.9, -0.5, 0.4]))],
        spheres=[(np.array([-0.55, 0.55, 0.2]), 0.2)])
