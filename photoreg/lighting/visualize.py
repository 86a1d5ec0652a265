"""Pictures of a lighting estimate: lat-long radiance map and a diffuse sphere lit by it.

Lat-long convention (docs/conventions.md): world +z is up (row 0), column u maps to azimuth
phi = 2*pi*(u + 0.5)/W - pi measured from +x toward +y, so the centre column looks along +x.
"""
from __future__ import annotations

import math

import numpy as np

from . import sh


def latlong_directions(height: int, width: int) -> np.ndarray:
    """World directions (H, W, 3) of the lat-long pixel centres."""
    theta = (np.arange(height) + 0.5) * math.pi / height
    phi = (np.arange(width) + 0.5) * 2 * math.pi / width - math.pi
    T, P = np.meshgrid(theta, phi, indexing="ij")
    return np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1)


def latlong(F: np.ndarray, height: int = 128) -> np.ndarray:
    """Radiance reconstructed from SH (3, B*B) as an (H, 2H, 3) linear image (negative lobes clipped)."""
    d = latlong_directions(height, 2 * height)
    return np.maximum(sh.radiance(F, d.reshape(-1, 3)).reshape(height, 2 * height, -1), 0).astype(np.float32)


def lit_sphere(F: np.ndarray, cam_to_world: np.ndarray, size: int = 128, albedo: float = 0.8) -> np.ndarray:
    """A white diffuse sphere seen orthographically from the camera: (size, size, 3) linear radiance,
    albedo*E(n)/pi, black outside the disc."""
    u = (np.arange(size) + 0.5) / size * 2 - 1
    X, Y = np.meshgrid(u, u)
    r2 = X**2 + Y**2
    inside = r2 < 1
    n_cam = np.stack([X, Y, -np.sqrt(np.clip(1 - r2, 0, 1))], axis=-1)  # OpenCV camera: faces the viewer (-z)
    n_world = n_cam.reshape(-1, 3) @ np.asarray(cam_to_world)[:3, :3].T
    E = sh.irradiance(F, n_world).reshape(size, size, -1)
    img = np.where(inside[..., None], albedo * np.maximum(E, 0) / math.pi, 0.0)
    return img.astype(np.float32)


def tonemap(img: np.ndarray, percentile: float = 99.0) -> np.ndarray:
    """Scale a linear image so its `percentile` maps to 1 (for viewing), finite and non-negative."""
    x = np.nan_to_num(np.maximum(img, 0), nan=0.0, posinf=0.0)
    ref = np.percentile(x.max(axis=-1), percentile) if x.size else 0.0
    return x / ref if ref > 0 else x
