"""Frame-to-model camera tracking (KinectFusion style) with Open3D point-to-plane odometry.

The current frame (every step-th pixel: TRACK_WIDTH across, every 4th of a 640x480 frame) is aligned against the
model depth ray-cast from the TSDF by the project's Warp kernel at the previous pose (Open3D's own ray_cast crashed
intermittently here); the first frame with depth (MIN_START_DEPTH) defines the world. Frames that come further
apart than the recording's (a live stream's dropped frames, --frames A:B:S) move the camera further than
point-to-plane odometry converges from a standing start. The alignment starts from guesses:
  1. the motion predicted at constant velocity (the last two tracked frames' motion, scaled to the time since),
     or no motion without a velocity. Where that alignment fails, or is doubtful (it corrected its guess by more
     than DOUBT_DEG / DOUBT_M, or fits worse than DOUBT_FIT of the recent frames' median), also:
  2. the motion that ORB features matched between this frame's colour and the last tracked frame's, with that
     frame's depth under them, give (OpenCV's PnP with RANSAC): it does not need the motion to be small;
  3. no motion, after a prediction.
An alignment that lands within AGREE_DEG / AGREE_M of the matched motion settles it; else the best fit (Open3D's
fitness) of those tried wins. A frame none of them aligns (low fitness, high error, a correction of its guess too
large to be plausible) keeps the previous pose, is reported, and is not fused. After such a failure the camera may
have gone anywhere, and point-to-plane alignment of a room's planes can fit a wrong pose well (ICL-NUIM after 3 s
covered: fitness 0.98, 1 m off), so until a frame tracks again only an alignment that the matched features confirm
is taken.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..config import ReconstructionConfig
from ..device import open3d_message
from ..types import Frame, Intrinsics

# Pixels across the tracked images. TUM and ICL-NUIM (benchmarks/tracking.md): 160 (every 4th pixel) tracked as well
# as 320 (every 2nd; TUM 11.9-16.3 mm against 13.8-16.2, ICL-NUIM 11.7-12.4 against 11.6-12.2) with the pose stage
# at 14-21 ms against 35-48 on a 2-core CPU, most of it the model's ray cast; 128 and 107 lost on ICL-NUIM (12.7 and
# 14.2 mm at every frame)
TRACK_WIDTH = 160
MAX_PREDICT_S = 1.0   # no velocity guess across a longer gap since the last tracked frame, nor from an older motion
DOUBT_DEG, DOUBT_M = 5.0, 0.03   # an alignment that corrects its guess by more asks the matched features
DOUBT_FIT = 0.9       # as does one that fits worse than this share of the recent frames' median fitness
RECENT_FITS = 30      # that median's frames
AGREE_DEG, AGREE_M = 3.0, 0.05   # an alignment this close to the matched features' motion settles it
# After a failed frame an alignment is taken only this close to the matched features' motion (at large motions the
# alignment moves several degrees from the features' guess, TUM's every 16th frame: up to 8; a wrong pose that a
# room's planes fit lay 1 m and 50 degrees off)
LOST_AGREE_DEG, LOST_AGREE_M = 10.0, 0.15
ORB_FEATURES = 500    # features per frame for the matched guess
MATCH_RATIO = 0.8     # a feature's best match is kept where it is this much nearer than its second (Lowe's test)
MIN_PNP_INLIERS = 12  # fewer RANSAC inliers give no matched guess
# The first tracked frame defines the world and starts the model: one with less of its pixels with depth (a camera
# that starts facing nothing within depth_max, or covered) is not taken, the next is tried (a 12 x 12 patch of depth
# as the first frame left every later frame's odometry singular)
MIN_START_DEPTH = 0.1
MAX_LISTED = 100      # failures listed by the report, the rest counted (a covered camera fails 30 times a second)
FIT_BINS = 1000       # the fitness's histogram over [0, 1]: its median to half a thousandth


class _View:
    """A tracked frame's colour and depth, its ORB features found when first asked for (most frames at 30 Hz never
    need them)."""

    def __init__(self, frame: Frame, prep):
        self.colour = frame.color   # (H, W, 3) uint8 RGB
        self.depth = prep.depth     # metres, 0 where invalid
        self._features: tuple[np.ndarray, np.ndarray | None] | None = None

    def features(self, orb) -> tuple[np.ndarray, np.ndarray | None]:
        """(pixels (N, 2) of the full-size frame, descriptors or None) of `orb` (cv2.ORB) on the frame's grey image at
        half size (a quarter of the pixels to search; the guess they give is refined by the alignment)."""
        if self._features is None:
            grey = cv2.cvtColor(self.colour, cv2.COLOR_RGB2GRAY)
            grey = cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA)
            kp, des = orb.detectAndCompute(grey, None)
            self._features = (np.array([k.pt for k in kp], np.float32).reshape(-1, 2) * 2 + 0.5, des)
        return self._features


@dataclass
class TrackingStats:
    """What the report needs of the frames tracked, its size bounded however long the stream (a live connection
    tracks for hours; every frame's pose and fitness kept grew it 350 bytes a frame): the failures counted and the
    first MAX_LISTED listed, the fitness's recent values (_doubtful) and a histogram for its median. The tracked poses
    are the frames' own (FrameResult.pose)."""
    frames: int = 0
    failed: int = 0
    failures: list = field(default_factory=list)   # [(frame index, reason)] of the first MAX_LISTED failures
    recent: deque = field(default_factory=lambda: deque(maxlen=RECENT_FITS))   # the latest fitness values
    fits: np.ndarray = field(default_factory=lambda: np.zeros(FIT_BINS, np.int64))   # fitness histogram
    unconfirmed: int = 0   # frames tracked on an alignment in doubt that no matched features confirmed
    unconfirmed_frames: list = field(default_factory=list)   # the first MAX_LISTED of them

    def fail(self, index: int, reason: str) -> None:
        self.failed += 1
        if len(self.failures) < MAX_LISTED:
            self.failures.append((index, reason))

    def fit(self, fitness: float) -> None:
        self.recent.append(fitness)
        self.fits[min(int(fitness * FIT_BINS), FIT_BINS - 1)] += 1

    def median_fitness(self) -> float | None:
        """The median of every tracked frame's fitness (its histogram bin's centre), None before one."""
        n = int(self.fits.sum())
        if n == 0:
            return None
        return (int(np.searchsorted(np.cumsum(self.fits), (n + 1) / 2)) + 0.5) / FIT_BINS


class Tracker:
    """Tracks each new frame against the volume's ray-cast model."""

    def __init__(self, volume, intrinsics: Intrinsics, recon: ReconstructionConfig, step: int | None = None,
                 min_fitness: float = 0.1, max_rmse: float = 0.04, max_jump_m: float = 0.3,
                 max_jump_deg: float = 30.0):
        import open3d as o3d

        self.o3d = o3d
        self.volume = volume
        self.intr = intrinsics
        self.recon = recon
        # pixel (step*r, step*c) of the frame is pixel (r, c) of the tracked images
        self.step = step or max(1, round(intrinsics.width / TRACK_WIDTH))
        K = intrinsics.K.copy()
        K[:2] /= self.step
        self.K = o3d.core.Tensor(K, o3d.core.float64)
        self.limits = (min_fitness, max_rmse, max_jump_m, max_jump_deg)
        self.pose: np.ndarray | None = None
        self.time = 0.0      # timestamp of the last tracked frame
        self.velocity: tuple[np.ndarray, float] | None = None   # its motion from the one before, and their time apart
        self.model = None   # RGBDImage ray-cast at self.pose after the last fusion
        self._key: _View | None = None   # the last tracked frame
        self.lost = False   # the frame before failed
        self._orb = cv2.ORB_create(ORB_FEATURES)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
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
        view = _View(frame, prep)
        if self.pose is None:
            if prep.valid_depth_fraction < MIN_START_DEPTH:
                reason = (f"tracking not started: {prep.valid_depth_fraction:.1%} of the pixels have depth, the "
                          f"first tracked frame needs {MIN_START_DEPTH:.0%}")
                self.stats.fail(frame.index, reason)
                return None, [f"frame {frame.index}: {reason}"]
            self.pose, self.time, self._key = np.eye(4), frame.timestamp, view
            return self.pose, []
        if self.model is None:
            self.update_model()
        src = self._rgbd(prep.depth[::self.step, ::self.step])
        fits, reasons = [], []

        def align(name: str, start: np.ndarray) -> np.ndarray | None:
            T, fitness, reason = self._align(src, start)
            if reason:
                reasons.append(f"{reason} from {name}")
                return None
            fits.append((fitness, T))
            return T

        predicted, matched = self.predicted(frame.timestamp), None
        start = predicted if predicted is not None else np.eye(4)
        first = align("the predicted motion" if predicted is not None else "rest", start)
        settled = not (first is None or self.lost or self._doubtful(first, start, fits[-1][0]))
        if not settled:
            matched = self.matched(view)
            settled = first is not None and matched is not None and _agree(first, matched)
            if matched is not None and not settled:
                T = align("matched features", matched)
                settled = T is not None and _agree(T, matched)
            if predicted is not None and not settled:
                align("rest", np.eye(4))
        lost = self.lost
        if lost:   # the camera may be anywhere: only an alignment the features confirm is taken
            fits = [f for f in fits if matched is not None and _agree(f[1], matched, LOST_AGREE_M, LOST_AGREE_DEG)]
            if not fits:
                reasons.append("lost since the last tracked frame: " + (
                    "no features matched with it" if matched is None else "no alignment agrees with its features"))
        self.lost = not fits
        if not fits:
            reason = "tracking failed: " + "; ".join(reasons)
            self.stats.fail(frame.index, reason)
            return None, [f"frame {frame.index}: {reason}"]
        fitness, T = max(fits, key=lambda f: f[0])
        self.stats.fit(fitness)
        self.velocity = (T, frame.timestamp - self.time)
        self.pose, self.time, self._key = self.pose @ T, frame.timestamp, view
        self.model = None  # ray-cast again after this frame is fused
        if settled or lost:   # (a lost camera's alignment is taken only where the features confirm it)
            return self.pose, []
        # taken on its fit alone: frames far apart (a generated orbit 26 degrees a frame) were tracked 0.2-0.5 m off
        # this way with no failure reported
        self.stats.unconfirmed += 1
        if len(self.stats.unconfirmed_frames) < MAX_LISTED:
            self.stats.unconfirmed_frames.append(frame.index)
        return self.pose, [f"frame {frame.index}: tracking unconfirmed: the alignment moved far from its guess or "
                           "fits worse than the recent frames, and no matched features confirmed it (fitness "
                           f"{fitness:.2f})"]

    def _doubtful(self, T: np.ndarray, start: np.ndarray, fitness: float) -> bool:
        """Whether an alignment needs the matched features' word: it corrected its guess by more than DOUBT_M or
        DOUBT_DEG, or fits worse than DOUBT_FIT of the recent frames' median fitness."""
        moved, angle = _size(np.linalg.solve(start, T))
        recent = self.stats.recent
        return moved > DOUBT_M or angle > DOUBT_DEG or (bool(recent) and fitness < DOUBT_FIT * np.median(recent))

    def matched(self, view: _View) -> np.ndarray | None:
        """The source-to-target motion that the ORB features of `view` matched with the last tracked frame's give
        (PnP with RANSAC on the tracked frame's depth under its features), None where too few of them agree."""
        (pts, des), (xy, cur) = self._key.features(self._orb), view.features(self._orb)
        if des is None or cur is None:
            return None
        matches = [m[0] for m in self._matcher.knnMatch(des, cur, k=2)
                   if len(m) == 2 and m[0].distance < MATCH_RATIO * m[1].distance]
        if len(matches) < MIN_PNP_INLIERS:
            return None
        uv = pts[[m.queryIdx for m in matches]]
        xy = xy[[m.trainIdx for m in matches]]
        depth = self._key.depth
        z = depth[np.clip(np.round(uv[:, 1]).astype(int), 0, depth.shape[0] - 1),
                  np.clip(np.round(uv[:, 0]).astype(int), 0, depth.shape[1] - 1)]
        ok = np.isfinite(z) & (z > 0)
        if ok.sum() < MIN_PNP_INLIERS:
            return None
        i = self.intr
        obj = np.stack([(uv[ok, 0] - i.cx) / i.fx * z[ok], (uv[ok, 1] - i.cy) / i.fy * z[ok], z[ok]], 1)
        cv2.setRNGSeed(0)   # RANSAC draws from OpenCV's one global generator: the same frames, the same guess
        found, rvec, tvec, inliers = cv2.solvePnPRansac(obj.astype(np.float64), xy[ok].astype(np.float64),
                                                        self.intr.K, None, iterationsCount=200,
                                                        reprojectionError=3.0)
        if not found or inliers is None or len(inliers) < MIN_PNP_INLIERS:
            return None
        M = np.eye(4)   # the tracked frame's camera to this one's
        M[:3, :3], M[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        return np.linalg.inv(M)

    def predicted(self, timestamp: float) -> np.ndarray | None:
        """The motion from the last tracked pose to the frame at `timestamp` (in the last pose's camera frame, as the
        odometry's source-to-target transform) at the last two tracked frames' velocity; None without them, or
        where they or the gap since are over MAX_PREDICT_S apart or out of order."""
        if self.velocity is None:
            return None
        delta, dt = self.velocity
        gap = timestamp - self.time
        if not (0 < gap <= MAX_PREDICT_S and 0 < dt <= MAX_PREDICT_S):
            return None
        M = np.eye(4)
        M[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(delta[:3, :3]).as_rotvec() * (gap / dt)).as_matrix()
        M[:3, 3] = delta[:3, 3] * (gap / dt)
        return M

    def _align(self, src, start: np.ndarray) -> tuple[np.ndarray, float, str]:
        """(source-to-target transform, fitness, why it failed or '') of the frame's depth `src` aligned with the
        model from the guess `start`; a correction of `start` past the jump limits counts as a failure."""
        od = self.o3d.t.pipelines.odometry
        try:
            res = od.rgbd_odometry_multi_scale(src, self.model, self.K, self.o3d.core.Tensor(start), 1.0,
                                               self.recon.depth_max, self.criteria, od.Method.PointToPlane)
        except RuntimeError as e:  # Open3D raises when too few correspondences
            return start, 0.0, f"odometry failed: {open3d_message(e)}"
        T = res.transformation.cpu().numpy()
        fitness, rmse = float(res.fitness), float(res.inlier_rmse)
        min_fit, max_rmse, max_t, max_r = self.limits
        moved, angle = _size(np.linalg.solve(start, T))
        if fitness < min_fit:
            return T, fitness, f"low fitness {fitness:.2f}"
        if rmse > max_rmse:
            return T, fitness, f"high residual {rmse * 1000:.1f} mm"
        if moved > max_t or angle > max_r:
            return T, fitness, f"implausible jump ({moved:.2f} m, {angle:.0f} deg)"   # past the guess
        return T, fitness, ""

    def update_model(self) -> None:
        from ..kernels.raycast import raycast_surface

        maps = raycast_surface(self.volume.dense_grid(), self.intr, self.pose, self.recon.depth_min,
                               self.recon.depth_max, stride=self.step)
        self.model = self._rgbd(maps.depth)

    def report(self) -> dict:
        """summary.json's "tracking": frames, failures (the first MAX_LISTED; "failures_not_listed" counts the rest),
        the frames tracked unconfirmed (count, the first MAX_LISTED), median fitness."""
        s = self.stats
        out = {"frames": s.frames, "failures": [{"frame": i, "reason": r} for i, r in s.failures],
               "unconfirmed": s.unconfirmed, "unconfirmed_frames": list(s.unconfirmed_frames),
               "median_fitness": s.median_fitness()}
        if s.failed > len(s.failures):
            out["failures_not_listed"] = s.failed - len(s.failures)
        return out


def _size(T: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) that a rigid motion moves and turns."""
    return float(np.linalg.norm(T[:3, 3])), float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))))


def _agree(a: np.ndarray, b: np.ndarray, metres: float = AGREE_M, degrees: float = AGREE_DEG) -> bool:
    """Whether two rigid motions are within `metres` and `degrees` of each other."""
    moved, angle = _size(np.linalg.solve(a, b))
    return moved <= metres and angle <= degrees


def ate_against(tracked: dict, recorded) -> dict:
    """summary.json's score of tracked poses (frame index -> 4x4) against a recording's (index -> 4x4 or None):
    {"ate_rmse_m", "rotation_rmse_deg", "ate_frames" (the frames with both)}, or {"ate_rmse_m": None, "ate_note":
    why} where too few frames have both."""
    gt = {i: recorded[i] for i in tracked if recorded[i] is not None}
    try:
        return {"ate_rmse_m": round(ate_rmse(tracked, gt)[0], 5),
                "rotation_rmse_deg": round(rotation_rmse_deg(tracked, gt), 3), "ate_frames": len(gt)}
    except ValueError as e:
        return {"ate_rmse_m": None, "ate_note": str(e)}


def rotation_rmse_deg(est: dict, gt: dict) -> float:
    """RMSE of the camera orientations' angles (degrees) after the best rotation of the estimate onto ground truth
    (the projection onto SO(3) of the sum of R_gt R_est^T), over frames present in both: what moves an inserted
    object far from the camera, which the positions' ATE does not see (a camera turning in place)."""
    keys = sorted(set(est) & set(gt))
    if not keys:
        raise ValueError("no frame has both poses")
    Re, Rg = np.stack([est[k][:3, :3] for k in keys]), np.stack([gt[k][:3, :3] for k in keys])
    U, _, Vt = np.linalg.svd(np.einsum("kij,klj->il", Rg, Re))
    align = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    cos = (np.einsum("kji,jl,kli->k", Rg, align, Re) - 1) / 2      # trace(Rg^T align Re)
    return float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(cos, -1, 1)) ** 2))))


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
