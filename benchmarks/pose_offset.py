"""The clock offset of a TUM recording's poses (groundtruth.txt, motion capture) against its camera, measured two
ways, over offsets added to the frames' times where the poses are looked up:

- the colour frames (what `recording.pose_time_offset` sets, and what an inserted object slides against): the
  pixels of a grid with depth in one frame are carried into the next by the two frames' poses, and compared with
  where the colour images' optical flow (OpenCV's pyramidal Lucas-Kanade, checked forward and back) takes them; a
  pose looked up at the wrong time moves them off the image content (the per-frame slide, pixels);
- the depth images: the camera is tracked from the depth images alone (`photoreg run --no-poses`), and its
  orientations compared with the recorded ones at the depth images' times (rotation RMSE after the best common
  rotation; the frame-to-frame rotations' RMSE, free of the tracking's drift).

usage: python benchmarks/pose_offset.py RECORDING [--frames 100] [--offsets-ms=-42:14:7] [--tracked TRAJECTORY]
(--tracked: a trajectory.txt of an earlier `photoreg run RECORDING --no-poses --frames 0:N`, instead of tracking)
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from photoreg.cli import main as photoreg  # noqa: E402
from photoreg.io.poses import interpolate_poses, read_tum_trajectory  # noqa: E402
from photoreg.io.recording import open_recording  # noqa: E402
from photoreg.io.tum import associate, read_timestamped  # noqa: E402
from photoreg.recon.tracking import rotation_rmse_deg  # noqa: E402


def step_rotation_rmse_deg(est: list[np.ndarray], gt: list[np.ndarray]) -> float:
    """RMSE (degrees) of the angle between each consecutive pair's rotation in `est` and in `gt`."""
    errs = []
    for k in range(len(est) - 1):
        d = (est[k][:3, :3].T @ est[k + 1][:3, :3]).T @ (gt[k][:3, :3].T @ gt[k + 1][:3, :3])
        errs.append(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
    return float(np.sqrt(np.mean(np.square(errs))))


GRID = 16   # pixels between the slide's points
LK = {"winSize": (31, 31), "maxLevel": 3}


def flow_pairs(recording: Path, frames: int) -> list[tuple[float, float, np.ndarray, np.ndarray, np.ndarray]]:
    """Per consecutive pair of the first `frames` frames, once for every offset: (the two frames' times, the grid
    points of the first frame that have depth, their depth, where the colour images' optical flow takes them), the
    points the flow tracks forward and back within half a pixel."""
    rec = open_recording(recording)
    v, u = np.mgrid[GRID // 2:rec.intrinsics.height:GRID, GRID // 2:rec.intrinsics.width:GRID]
    px = np.stack([u.ravel(), v.ravel()], 1).astype(np.float32)
    pairs, prev = [], None
    for i in range(min(frames, len(rec))):
        f = rec.frame(i)
        grey = cv2.cvtColor(f.color, cv2.COLOR_RGB2GRAY)
        if prev is not None:
            t0, g0, d0 = prev
            z = d0[px[:, 1].astype(int), px[:, 0].astype(int)]
            p0 = px[z > 0]
            p1, ok1, _ = cv2.calcOpticalFlowPyrLK(g0, grey, p0[:, None], None, **LK)
            back, ok2, _ = cv2.calcOpticalFlowPyrLK(grey, g0, p1, None, **LK)
            ok = (ok1[:, 0] == 1) & (ok2[:, 0] == 1) & (np.linalg.norm(back[:, 0] - p0, axis=1) < 0.5)
            pairs.append((t0, f.timestamp, p0[ok], z[z > 0][ok], p1[ok, 0]))
        prev = (f.timestamp, grey, f.depth)
    return pairs


def colour_slide_px(pairs, K: np.ndarray, gt_times: np.ndarray, gt_poses: np.ndarray, offset: float) -> np.ndarray:
    """Per frame pair of flow_pairs, the median distance (pixels) between where the recorded poses at the frames'
    times + `offset` carry the first frame's points (by their depth) and where the optical flow took them."""
    out = []
    for t0, t1, p0, z, p1 in pairs:
        T0, T1 = interpolate_poses(gt_times, gt_poses, np.array([t0, t1]) + offset)
        if T0 is None or T1 is None or not len(p0):
            continue
        world = (np.c_[(p0 - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones(len(p0))] * z[:, None]) @ T0[:3, :3].T + T0[:3, 3]
        cam = (world - T1[:3, 3]) @ T1[:3, :3]
        front = cam[:, 2] > 0
        if front.any():
            carried = cam[front, :2] / cam[front, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
            out.append(float(np.median(np.linalg.norm(p1[front] - carried, axis=1))))
    return np.array(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording")
    ap.add_argument("--frames", type=int, default=100, help="the first N frames")
    ap.add_argument("--offsets-ms", default="-42:14:7", help="first:last:step, milliseconds (--offsets-ms=-42:14:7)")
    ap.add_argument("--tracked", help="trajectory.txt of an earlier `photoreg run RECORDING --no-poses`")
    args = ap.parse_args()
    rec = Path(args.recording)
    tracked = args.tracked
    if tracked is None:
        out = Path(tempfile.mkdtemp(prefix="pose_offset_"))
        if photoreg(["run", str(rec), "--no-poses", "--frames", f"0:{args.frames}", "--rays", "8", "--bands", "3",
                     "--stride", "8", "--out", str(out), "--quiet"]) != 0:
            return 1
        tracked = out / "trajectory.txt"
    times, poses = read_tum_trajectory(tracked)
    colour, _ = read_timestamped(rec / "rgb.txt", 2)
    depth, _ = read_timestamped(rec / "depth.txt", 2)
    of_colour = dict(associate(colour, depth))
    depth_at = np.array([depth[of_colour[int(np.argmin(np.abs(colour - t)))]] for t in times])
    gt_times, gt_poses = read_tum_trajectory(rec / "groundtruth.txt")
    first, last, step = (float(x) for x in args.offsets_ms.split(":"))
    print(f"{len(times)} frames; depth image - colour frame time: median {np.median(depth_at - times) * 1000:.1f} ms\n")
    print("| offset ms | colour frames: slide px, median / mean / 90th percentile of the frame pairs | depth images "
          "(tracked): orientations deg / frame-to-frame deg |\n|---|---|---|")
    slide, rot = {}, {}
    pairs, K = flow_pairs(rec, args.frames), open_recording(rec).intrinsics.K
    for ms in np.arange(first, last + step / 2, step):
        s = colour_slide_px(pairs, K, gt_times, gt_poses, ms / 1000)
        slide[ms] = float(np.median(s))
        gt = interpolate_poses(gt_times, gt_poses, depth_at + ms / 1000)
        keep = [k for k, g in enumerate(gt) if g is not None]
        rot[ms] = rotation_rmse_deg({k: poses[k] for k in keep}, {k: gt[k] for k in keep})
        steps = step_rotation_rmse_deg([poses[k] for k in keep], [gt[k] for k in keep])
        print(f"| {ms:+.1f} | {slide[ms]:.2f} / {s.mean():.2f} / {np.percentile(s, 90):.2f} | {rot[ms]:.2f} / "
              f"{steps:.3f} |", flush=True)
    c, d = min(slide, key=slide.get), min(rot, key=rot.get)
    print(f"\ncolour frames: least slide at {c:+.1f} ms ({slide[c]:.2f} px): recording.pose_time_offset = "
          f"{c / 1000:g}; "
          f"depth images: best at {d:+.1f} ms after their own times ({rot[d]:.2f} deg)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
