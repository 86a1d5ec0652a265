"""Camera poses: TUM lines (`t tx ty tz qx qy qz qw`, camera-to-world), validation, interpolation."""
from __future__ import annotations

import threading

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .atomic import write_text
from .text import read_text


def pose_from_tum(values) -> np.ndarray:
    """(tx, ty, tz, qx, qy, qz, qw) -> 4x4 float64 camera-to-world."""
    v = np.asarray(values, dtype=np.float64)
    q = v[3:7]
    n = np.linalg.norm(q)
    if not np.all(np.isfinite(v[:3])):
        raise ValueError(f"invalid pose (non-finite translation {v[:3].tolist()})")
    if np.abs(v[:3]).max() > MAX_TRANSLATION:
        raise ValueError(f"invalid pose (translation {v[:3].tolist()} beyond {MAX_TRANSLATION:g} m)")
    if not np.all(np.isfinite(q)) or abs(n - 1.0) > 1e-2:
        raise ValueError(f"invalid pose (non-finite or non-unit quaternion, |q|={n:.4f})")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / n).as_matrix()
    T[:3, 3] = v[:3]
    return T


def pose_to_tum(T: np.ndarray) -> list[float]:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return [*map(float, T[:3, 3]), *map(float, q)]


def format_tum_line(t: float, T: np.ndarray) -> str:
    return f"{t:.6f} " + " ".join(f"{x:.9f}" for x in pose_to_tum(T))


def write_tum_trajectory(path, stamped) -> None:
    """(timestamp, 4x4 camera-to-world) pairs as a TUM trajectory file, atomically."""
    write_text(path, "".join(format_tum_line(t, T) + "\n" for t, T in stamped))


def read_tum_trajectory(path) -> tuple[np.ndarray, np.ndarray]:
    """groundtruth.txt -> (timestamps (N,), poses (N,4,4)); errors name the file and line."""
    ts, poses = [], []
    for lineno, line in enumerate(read_text(path).splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            if len(parts) != 8:
                raise ValueError(f"expected 8 values, found {len(parts)}")
            vals = [float(x) for x in parts]
            poses.append(pose_from_tum(vals[1:]))
        except ValueError as e:
            raise ValueError(f"{path}:{lineno}: {e}") from None
        if ts and vals[0] <= ts[-1]:
            raise ValueError(f"{path}:{lineno}: timestamps not increasing ({vals[0]} after {ts[-1]})")
        ts.append(vals[0])
    if not ts:
        raise ValueError(f"{path}: no poses")
    return np.asarray(ts), np.stack(poses)


MAX_GAP = 0.25   # seconds: the longest stretch without a pose that interpolation bridges


def interpolate_poses(ts: np.ndarray, poses: np.ndarray, query: np.ndarray, max_gap: float = MAX_GAP) -> list:
    """Poses at query times (slerp rotation, linear translation); None where a query is outside
    the trajectory or its neighbouring samples are more than `max_gap` seconds apart."""
    out: list = []
    slerp = Slerp(ts, Rotation.from_matrix(poses[:, :3, :3])) if len(ts) > 1 else None
    for t in np.atleast_1d(query):
        if len(ts) == 1 or t < ts[0] - 1e-9 or t > ts[-1] + 1e-9:
            out.append(poses[0].copy() if len(ts) == 1 and abs(t - ts[0]) <= max_gap else None)
            continue
        j = int(np.clip(np.searchsorted(ts, t), 1, len(ts) - 1))
        if ts[j] - ts[j - 1] > max_gap:
            out.append(None)
            continue
        a = (t - ts[j - 1]) / (ts[j] - ts[j - 1])
        T = np.eye(4)
        T[:3, :3] = slerp([min(max(t, ts[0]), ts[-1])]).as_matrix()[0]  # within the 1e-9 tolerance above
        T[:3, 3] = (1 - a) * poses[j - 1, :3, 3] + a * poses[j, :3, 3]
        out.append(T)
    return out


_checked = threading.local()   # per thread, the last pose found rigid (as bytes)


MAX_TRANSLATION = 1e9   # metres: farther is no camera's pose (and overflows where a pose is rounded for a file)


def check_pose(T: np.ndarray, where: str) -> np.ndarray:
    """A finite rigid 4x4 transform within MAX_TRANSLATION of the origin, or a ValueError naming `where`. The pose a
    thread checked last passes at once: a frame's stages check the same pose three or four times (0.1 ms each on the
    H100's host)."""
    T = np.asarray(T, dtype=np.float64)
    key = T.tobytes() if T.shape == (4, 4) else None
    if key is not None and getattr(_checked, "pose", None) == key:
        return T
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{where}: pose is not a finite 4x4 matrix")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0.99 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise ValueError(f"{where}: pose is not a rigid transform")
    if np.abs(T[:3, 3]).max() > MAX_TRANSLATION:
        raise ValueError(f"{where}: pose translation {T[:3, 3].tolist()} is beyond {MAX_TRANSLATION:g} m")
    _checked.pose = key
    return T
