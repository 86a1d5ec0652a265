"""TUM RGB-D layout, also the native one: rgb.txt/depth.txt lists associated by nearest timestamp
(or associations.txt), groundtruth.txt poses interpolated to the colour frame times."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..types import Intrinsics
from .intrinsics import Calibration, read_calibration
from .poses import MAX_GAP, interpolate_poses, read_tum_trajectory
from .recording import Recording, data_lines

MAX_DIFFERENCE = 0.02  # s, largest colour/depth time difference of a pair (TUM associate.py default)
DEPTH_SCALE = 5000.0   # TUM depth PNG units per metre
# Published freiburg calibrations: intrinsics and k1 k2 p1 p2 k3 (freiburg 3 images come undistorted).
FREIBURG = {
    1: (Intrinsics(640, 480, 517.3, 516.5, 318.6, 255.3, DEPTH_SCALE), [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
    2: (Intrinsics(640, 480, 520.9, 521.0, 325.1, 249.7, DEPTH_SCALE), [0.2312, -0.7849, -0.0033, -0.0001, 0.9172]),
    3: (Intrinsics(640, 480, 535.4, 539.2, 320.1, 247.6, DEPTH_SCALE), [0.0, 0.0, 0.0, 0.0, 0.0]),
}


def freiburg_calibration(path: Path) -> Calibration | None:
    """Calibration of the freiburg sensor named in the folder name (freiburg2, fr3, ...), if any."""
    m = re.search(r"(?<![a-z])(?:freiburg|fr)_?([123])(?![0-9])", path.resolve().name.lower())
    if m is None:
        return None
    intrinsics, distortion = FREIBURG[int(m.group(1))]
    return Calibration(intrinsics, np.array(distortion), f"freiburg{m.group(1)} defaults (from the folder name)")


def _timestamp(text: str, path: Path, lineno: int) -> float:
    try:
        t = float(text)
    except ValueError:
        t = math.nan
    if not math.isfinite(t):
        raise ValueError(f"{path}:{lineno}: {text!r} is not a timestamp")
    return t


def read_timestamped(path: Path, n_fields: int) -> tuple[np.ndarray, list[list[str]]]:
    """Lines of n_fields fields alternating timestamp and file (`t rgb/x.png` or associations.txt's
    `t rgb/x.png t depth/y.png`), first timestamps strictly increasing -> (first timestamps, fields)."""
    ts: list[float] = []
    rows = []
    for lineno, fields in data_lines(path):
        if len(fields) != n_fields:
            raise ValueError(f"{path}:{lineno}: expected {n_fields} fields, found {len(fields)}")
        t = _timestamp(fields[0], path, lineno)
        if ts and t <= ts[-1]:
            raise ValueError(f"{path}:{lineno}: timestamp {fields[0]} is not after the previous one ({ts[-1]:.6f})")
        for k in range(2, n_fields, 2):
            _timestamp(fields[k], path, lineno)
        ts.append(t)
        rows.append(fields)
    if not rows:
        raise ValueError(f"{path}: lists no frames")
    return np.array(ts), rows


def associate(first: np.ndarray, second: np.ndarray, max_difference: float = MAX_DIFFERENCE) -> list[tuple[int, int]]:
    """Index pairs (i, j) as TUM's associate.py forms them: pairs closer than max_difference, taken
    closest first, each index used once; sorted by i. Both time arrays ascending."""
    candidates = []
    for i, t in enumerate(first):
        lo = np.searchsorted(second, t - 2 * max_difference, side="left")    # sides: t +- d may round to t
        hi = np.searchsorted(second, t + 2 * max_difference, side="right")
        candidates += [(abs(t - second[j]), i, j) for j in range(lo, hi) if abs(t - second[j]) < max_difference]
    used_first, used_second, pairs = set(), set(), []
    for _, i, j in sorted(candidates):
        if i not in used_first and j not in used_second:
            used_first.add(i)
            used_second.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def open_tum(path: Path, native: bool, undistort: bool, pose_time_offset: float = 0.0) -> Recording:
    """A TUM/native folder; frame order is the colour frames' (rgb.txt) order; the poses of groundtruth.txt are
    taken at the frames' times + pose_time_offset seconds."""
    if native and not (path / "intrinsics.json").is_file():
        raise FileNotFoundError(f"{path / 'intrinsics.json'}: no such file (a native recording needs it)")
    calib = read_calibration(path, DEPTH_SCALE) or freiburg_calibration(path)
    if calib is None:
        raise ValueError(f"{path}: no intrinsics.json or intrinsics.txt, and the folder name names no freiburg "
                         "sensor (freiburg1/2/3): write intrinsics.json {width, height, fx, fy, cx, cy, depth_scale}")
    notes, warnings = [f"intrinsics from {calib.source}"], []

    if (path / "associations.txt").is_file():
        times, rows = read_timestamped(path / "associations.txt", 4)
        colors = [path / r[1] for r in rows]
        depths = [path / r[3] for r in rows]
        notes.append("frames from associations.txt")
    else:
        rgb_times, rgb_rows = read_timestamped(path / "rgb.txt", 2)
        depth_times, depth_rows = read_timestamped(path / "depth.txt", 2)
        pairs = associate(rgb_times, depth_times)
        if not pairs:
            raise ValueError(f"{path}: no colour frame of rgb.txt ({rgb_times[0]:.6f} .. {rgb_times[-1]:.6f}) has a "
                             f"depth frame of depth.txt ({depth_times[0]:.6f} .. {depth_times[-1]:.6f}) within "
                             f"{MAX_DIFFERENCE} s: timestamps are seconds (or give associations.txt)")
        if len(pairs) < len(rgb_rows):
            kept = {i for i, _ in pairs}
            first = next(i for i in range(len(rgb_rows)) if i not in kept)
            warnings.append(f"{len(rgb_rows) - len(pairs)} of {len(rgb_rows)} colour frames in rgb.txt have no depth "
                            f"within {MAX_DIFFERENCE} s and are left out (the first: {rgb_rows[first][1]}); frame "
                            "indices count the frames kept")
        times = rgb_times[[i for i, _ in pairs]]
        colors = [path / rgb_rows[i][1] for i, _ in pairs]
        depths = [path / depth_rows[j][1] for _, j in pairs]

    poses = None
    if not (path / "groundtruth.txt").is_file():
        if pose_time_offset:
            warnings.append("recording.pose_time_offset is set but there is no groundtruth.txt: no poses to offset")
    else:
        gt_times, gt_poses = read_tum_trajectory(path / "groundtruth.txt")
        looked = times + pose_time_offset
        poses = interpolate_poses(gt_times, gt_poses, looked)
        notes.append("poses from groundtruth.txt, interpolated to the colour frame times" + (
            f" {pose_time_offset * 1000:+g} ms (recording.pose_time_offset)" if pose_time_offset else ""))
        if len(gt_times) == 1:
            notes.append(f"groundtruth.txt holds one pose: the frames within {MAX_GAP} s of it take it, the others "
                         "have none")
        if all(T is None for T in poses):
            warnings.append(f"groundtruth.txt gives no frame a pose: no colour frame time ({looked[0]:.6f} .. "
                            f"{looked[-1]:.6f}{', pose_time_offset added' if pose_time_offset else ''}) lies "
                            f"between two of its poses ({gt_times[0]:.6f} .. "
                            f"{gt_times[-1]:.6f}) at most {MAX_GAP} s apart (timestamps are seconds)")
    return Recording(path=path, format="native" if native else "tum", intrinsics=calib.intrinsics,
                     timestamps=times, color_files=colors, depth_files=depths, poses=poses,
                     distortion=calib.distortion, undistort=undistort, notes=notes, warnings=warnings,
                     shutter=calib.shutter)
