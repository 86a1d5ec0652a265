"""Frame-to-model camera tracking (KinectFusion style) with Open3D point-to-plane odometry.

The current frame (every 2nd pixel) is aligned against the model depth ray-cast from the TSDF by
the project's Warp kernel at the previous pose (Open3D's own ray_cast crashed intermittently
here); the first frame defines the world. A failed alignment (low fitness, high error, implausible jump) keeps
the previous pose, is reported, and the frame is not fused.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import ReconstructionConfig
from ..types import Frame, Intrinsics


@dataclass
class TrackingStats:
    frames: int = 0
    failures: list = field(default_factory=list)   # [(frame index, reason)]
    fitness: list = field(default_factory=list)
    poses: dict = field(default_factory=dict)      # frame index -> 4x4 camera-to-world


class Tracker:
    """Tracks each new frame against the volume's ray-cast model."""

    def __init__(self, volume, intrinsics: Intrinsics, recon: ReconstructionConfig, step: int = 2,
                 min_fitness: float = 0.1, max_rmse: float = 0.04, max_jump_m: float = 0.3,
                 max_jump_deg: float = 30.0):
        import open3d as o3d

        self.o3d = o3d
        self.volume = volume
        self.intr = intrinsics
        self.recon = recon
        self.step = step  # pixel (step*r, step*c) of the frame is pixel (r, c) of the tracked images
        K = intrinsics.K.copy()
        K[:2] /= step
        self.K = o3d.core.Tensor(K, o3d.core.float64)
        self.limits = (min_fitness, max_rmse, max_jump_m, np.radians(max_jump_deg))
        self.pose: np.ndarray | None = None
        self.model = None   # RGBDImage ray-cast at self.pose after the last fusion
        self.stats = TrackingStats()
        od = o3d.t.pipelines.odometry
        self.criteria = [od.OdometryConvergenceCriteria(20), od.OdometryConvergenceCriteria(10),
                         od.OdometryConvergenceCriteria(5)]

    def _rgbd(self, depth: np.ndarray):
        o3d = self.o3d
        dev = self.volume.o3d_device
        d = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth, np.float32)[..., None], device=dev))
        return o3d.t.geometry.RGBDImage(d, d)

    def track(self, frame: Frame, prep) -> tuple[np.ndarray | None, list[str]]:
        """Pose of this frame (camera-to-world), or None with a reason when tracking failed."""
        self.stats.frames += 1
        if self.pose is None:
            self.pose = np.eye(4)
            self.stats.poses[frame.index] = self.pose.copy()
            return self.pose, []
        if self.model is None:
            self.update_model()
        od = self.o3d.t.pipelines.odometry
        src = self._rgbd(prep.depth[::self.step, ::self.step])
        try:
            res = od.rgbd_odometry_multi_scale(src, self.model, self.K, self.o3d.core.Tensor(np.eye(4)), 1.0,
                                               self.recon.depth_max, self.criteria, od.Method.PointToPlane)
            T = res.transformation.cpu().numpy()
            fitness, rmse = float(res.fitness), float(res.inlier_rmse)
        except RuntimeError as e:  # Open3D raises when too few correspondences
            T, fitness, rmse = np.eye(4), 0.0, float("inf")
            reason = f"odometry failed: {e}"
        else:
            reason = ""
        min_fit, max_rmse, max_t, max_r = self.limits
        angle = np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))
        if not reason:
            if fitness < min_fit:
                reason = f"low fitness {fitness:.2f}"
            elif rmse > max_rmse:
                reason = f"high residual {rmse * 1000:.1f} mm"
            elif np.linalg.norm(T[:3, 3]) > max_t or angle > max_r:
                reason = f"implausible jump ({np.linalg.norm(T[:3, 3]):.2f} m, {np.degrees(angle):.0f} deg)"
        self.stats.fitness.append(fitness)
        if reason:
            self.stats.failures.append((frame.index, reason))
            return None, [f"frame {frame.index}: tracking failed: {reason}"]
        self.pose = self.pose @ T
        self.stats.poses[frame.index] = self.pose.copy()
        self.model = None  # ray-cast again after this frame is fused
        return self.pose, []

    def update_model(self) -> None:
        from ..kernels.raycast import raycast_surface

        maps = raycast_surface(self.volume.dense_grid(), self.intr, self.pose, self.recon.depth_min,
                               self.recon.depth_max, stride=self.step)
        self.model = self._rgbd(maps.depth)

    def report(self) -> dict:
        s = self.stats
        return {"frames": s.frames, "failures": [{"frame": i, "reason": r} for i, r in s.failures],
                "median_fitness": float(np.median(s.fitness)) if s.fitness else None}


def ate_rmse(est: dict, gt: dict) -> tuple[float, np.ndarray]:
    """Absolute trajectory error (TUM): RMSE of camera positions after the best rigid alignment
    (Horn/Umeyama without scale) of the estimate onto ground truth, over frames present in both.
    Returns (rmse metres, 4x4 alignment)."""
    keys = sorted(set(est) & set(gt))
    if len(keys) < 3:
        raise ValueError(f"ATE needs at least 3 frames with both poses, got {len(keys)}")
    P = np.stack([est[k][:3, 3] for k in keys])
    Q = np.stack([gt[k][:3, 3] for k in keys])
    mp, mq = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    t = mq - R @ mp
    err = (P @ R.T + t) - Q
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = R, t
    return float(np.sqrt((err**2).sum(1).mean())), A
