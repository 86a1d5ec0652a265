"""Per-frame preprocessing: linear colour, saturation/black masks, depth validity, optional denoising."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .config import LightingConfig, ReconstructionConfig
from .io.images import srgb_to_linear
from .types import Frame


@dataclass
class Prepared:
    """A frame ready for fusion and sampling."""

    linear: np.ndarray      # HxWx3 float32 linear radiance (camera units)
    depth: np.ndarray       # HxW float32 metres, 0 where invalid or out of range
    usable: np.ndarray      # HxW bool: colour neither saturated nor black, depth valid
    saturated_fraction: float
    black_fraction: float
    valid_depth_fraction: float


def _denoise_luminance(linear: np.ndarray, method: str) -> np.ndarray:
    """Edge-preserving denoising of luminance only; chromaticity is kept."""
    if method == "none":   # before the luminance: 1-2 ms a frame at 640x480 for nothing
        return linear
    lum = linear @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    if method == "tvl1":
        u8 = np.clip(lum * 255.0, 0, 255).astype(np.uint8)
        out = np.zeros_like(u8)
        cv2.denoise_TVL1([u8], out, 1.0, 15)
        den = out.astype(np.float32) / 255.0
    else:
        den = cv2.ximgproc.guidedFilter(lum, lum, 2, 1e-3)
    ratio = np.where(lum > 1e-6, den / np.maximum(lum, 1e-6), 1.0)
    return (linear * ratio[..., None]).astype(np.float32)


def filter_depth(depth: np.ndarray, valid: np.ndarray, window: int, sigma_m: float) -> np.ndarray:
    """Bilateral filter of a depth map (metres, 0 where not `valid`): each valid pixel becomes the average of its
    `window`-pixel neighbourhood weighted by distance (sigma window // 2 pixels) and by depth difference (sigma_m),
    so sensor noise is averaged and depth edges kept; invalid pixels stay 0 and, being far in depth from any
    valid one, weigh next to nothing."""
    return np.where(valid, cv2.bilateralFilter(depth, window, sigma_m, window // 2), np.float32(0.0))


def prepare(frame: Frame, light: LightingConfig, recon: ReconstructionConfig) -> Prepared:
    """Linearise colour, mask saturated/black pixels and invalid depth (NaN, inf, out of range); optionally
    filter the depth (reconstruction.depth_filter_px)."""
    if frame.color.shape[:2] != frame.depth.shape[:2]:
        raise ValueError(f"frame {frame.index} ({frame.source}): colour {frame.color.shape[:2]} and depth "
                         f"{frame.depth.shape[:2]} sizes differ")
    if frame.color.shape[:2] != (frame.intrinsics.height, frame.intrinsics.width):
        raise ValueError(f"frame {frame.index} ({frame.source}): size {frame.color.shape[1]}x{frame.color.shape[0]} "
                         f"differs from the intrinsics {frame.intrinsics.width}x{frame.intrinsics.height}")
    c = frame.color
    cmax = np.maximum(np.maximum(c[..., 0], c[..., 1]), c[..., 2])  # 8x faster than c.max(axis=2)
    saturated = cmax >= light.saturation_level
    black = cmax <= light.black_level
    d = frame.depth.astype(np.float32)   # a copy: NaN and +-inf fail the range test below
    valid = (d >= recon.depth_min) & (d <= recon.depth_max)
    d[~valid] = 0.0
    if recon.depth_filter_px:
        d = filter_depth(d, valid, recon.depth_filter_px, recon.depth_filter_m)
    linear = _denoise_luminance(srgb_to_linear(frame.color), light.denoise)
    n = float(d.size)
    return Prepared(linear, d, valid & ~saturated & ~black, float(saturated.sum() / n), float(black.sum() / n),
                    float(valid.sum() / n))
