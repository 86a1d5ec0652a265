"""Generator cameras: pinhole intrinsics and camera-to-world paths (OpenCV frame: x right, y down, z forward)."""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from ..types import Intrinsics
from .scenes import OrbitRig

CAMERA_PATHS = ("orbit", "handheld", "static", "pan")
PAN_DEG = 10.0  # the pan path's yaw amplitude: it turns left and right twice over the sequence


def default_intrinsics(width: int, height: int, hfov_deg: float = 60.0, depth_scale: float = 5000.0) -> Intrinsics:
    """Square pixels, `hfov_deg` horizontal field of view, principal point at the image centre."""
    f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return Intrinsics(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0, depth_scale)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """4x4 camera-to-world of an OpenCV camera at `eye` looking at `target`, image 'up' towards `up`."""
    eye, target = np.asarray(eye, dtype=np.float64), np.asarray(target, dtype=np.float64)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction parallel to the up vector")
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def _smooth_noise(rng: np.random.Generator, s: np.ndarray, dims: int) -> np.ndarray:
    """Band-limited noise in [-1, 1]-ish along the path parameter s (sum of 3 random sinusoids per dim)."""
    out = np.zeros((len(s), dims))
    for _ in range(3):
        freq = rng.uniform(1.0, 4.0, dims)
        phase = rng.uniform(0, 2 * np.pi, dims)
        out += np.sin(2 * np.pi * freq * s[:, None] + phase) / 3.0
    return out


def camera_path(kind: str, n: int, rig: OrbitRig, seed: int = 0, at: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world poses (len(at), 4, 4) of an n-frame path: orbit about rig.target, orbit with hand jitter,
    static, or pan (the orbit, the camera turning about the vertical by up to PAN_DEG each way as it goes: the scene
    sweeps across the image, as under a hand-held camera's turns); at frames `at` (positions in frames, fractions
    between them included: a shutter's instants; default every frame 0..n-1)."""
    if kind not in CAMERA_PATHS:
        raise ValueError(f"unknown camera path {kind!r}; choose one of {', '.join(CAMERA_PATHS)}")
    if kind == "static":
        s = np.zeros(n if at is None else len(at))
    else:   # linspace at the frames themselves: the poses to the bit of the recordings made before `at`
        s = np.linspace(0.0, 1.0, n) if at is None else np.asarray(at, dtype=np.float64) / max(n - 1, 1)
    az = np.radians(rig.azimuth_deg + rig.arc_deg * s)
    h = rig.height + rig.wobble * np.sin(2 * np.pi * s)
    target = np.asarray(rig.target)
    eyes = target + np.stack([rig.radius * np.cos(az), rig.radius * np.sin(az), h], axis=1)
    poses = np.stack([look_at(e, target) for e in eyes])
    if kind == "pan":
        for T, yaw in zip(poses, np.radians(PAN_DEG) * np.sin(4 * np.pi * s)):
            T[:3, :3] = Rotation.from_euler("z", yaw).as_matrix() @ T[:3, :3]
    if kind == "handheld":
        rng = np.random.default_rng(seed)
        shake_t = 0.01 * _smooth_noise(rng, s, 3)  # about 1 cm
        shake_r = np.radians(1.0) * _smooth_noise(rng, s, 3)  # about 1 degree
        for T, dt, dr in zip(poses, shake_t, shake_r):
            T[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(dr).as_matrix()
            T[:3, 3] += dt
    return poses
