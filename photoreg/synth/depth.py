"""Kinect-like depth degradation for generated depth maps (clean camera z in metres, 0 = no hit)."""
from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter


def depth_sigma(z: np.ndarray) -> np.ndarray:
    """Axial noise standard deviation in metres: 1.2 mm + 1.9 mm * (z - 0.4)^2 (Kinect-style)."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def kinect_like(z: np.ndarray, rng: np.random.Generator, edge_jump: float = 0.04) -> np.ndarray:
    """Noisy copy of clean depth: Gaussian axial noise and holes at depth discontinuities (pixels whose
    3x3 neighbourhood spans more than `edge_jump` * z, or touches a pixel without depth).
    Quantisation to the depth scale happens when the PNG is written."""
    z = np.asarray(z, dtype=np.float32)
    valid = z > 0
    padded = np.where(valid, z, np.inf)  # a missing neighbour makes `hi` infinite: an edge
    lo = minimum_filter(padded, size=3, mode="nearest")
    hi = maximum_filter(padded, size=3, mode="nearest")
    with np.errstate(invalid="ignore"):  # inf - inf at pixels without depth, masked below
        edge = hi - lo > edge_jump * z
    noisy = z + rng.standard_normal(z.shape).astype(np.float32) * depth_sigma(z)
    return np.where(valid & ~edge & (noisy > 0), noisy, 0.0).astype(np.float32)
