"""Per-frame preprocessing: linear colour, saturation/black masks, depth validity, optional denoising."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from .config import LightingConfig, ReconstructionConfig
from .io.images import srgb_to_linear
from .types import Frame

UNIFORM_LEVELS = 1   # a colour frame whose brightest channel spans at most this many 8-bit levels is uniform


@dataclass
class Prepared:
    """A frame ready for fusion and sampling."""

    colour: np.ndarray      # HxWx3 uint8 sRGB as recorded
    depth: np.ndarray       # HxW float32 metres, 0 where invalid or out of range
    usable: np.ndarray      # HxW bool: colour neither saturated nor black, depth valid
    clipped: np.ndarray     # HxW bool: colour saturated (not black), depth valid: the radiance at least what it shows
    saturated_fraction: float
    black_fraction: float
    valid_depth_fraction: float
    denoise: str = "none"   # lighting.denoise: how `linear` is made from `colour`
    uniform: bool = False   # the colour one level everywhere (a camera's glitch): no pixel usable

    @cached_property
    def linear(self) -> np.ndarray:
        """HxWx3 float32 linear radiance (camera units), made when first read: a GPU's samples linearise the 8-bit
        colour on the device (kernels.samples), so without an object inserted no frame makes it on the host."""
        return _denoise_luminance(srgb_to_linear(self.colour), self.denoise)


def strided_box(prep: Prepared, stride: int, box: int = 0,
                censored: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(radiance, usable, clipped) at the pixels (r * stride, c * stride): the linear radiance averaged over an odd
    box of `box` pixels (0: stride | 1, the stride's cell) centred on the pixel (less noise at no extra cost), and
    whether the whole box is usable; a box of 1 is the pixel's own. `censored` (lighting.censored): a box may hold
    clipped pixels too (a few of them pull its mean down a little), and `clipped` says which boxes hold nothing
    else (their mean is a lower bound of the radiance); else it is all False."""
    box = box or (stride | 1)
    fit = (prep.usable | prep.clipped) if censored else prep.usable

    def whole(mask: np.ndarray) -> np.ndarray:
        """Whether the whole box round each strided pixel is in `mask`: an erosion (0.2 ms at 640x480 against 0.5
        for a box filter of the mask); with a box of 1 the pixel itself."""
        if box > 1:
            mask = cv2.erode(mask.view(np.uint8), np.ones((box, box), np.uint8), borderType=cv2.BORDER_REFLECT) > 0
        return mask if stride == 1 else mask[::stride, ::stride]

    radiance = prep.linear if box == 1 else cv2.boxFilter(prep.linear, -1, (box, box), borderType=cv2.BORDER_REFLECT)
    radiance = radiance if stride == 1 else radiance[::stride, ::stride]
    usable = whole(fit)
    return radiance, usable, whole(prep.clipped) if censored else np.zeros(usable.shape, bool)


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


def masked_depth(depth: np.ndarray, lo: float,
                 hi: float = float(np.finfo(np.float32).max)) -> tuple[np.ndarray, np.ndarray]:
    """(float32 copy of `depth` with 0 wherever it is not within [lo, hi], NaN and +-inf included; the bool mask of
    the pixels kept). The zeros by cv2.bitwise_and under the mask: 0.2 ms at 640x480 against 1.2 for a boolean
    assignment and 0.8 for np.where."""
    d = np.ascontiguousarray(depth, dtype=np.float32)
    valid = (d >= lo) & (d <= hi)   # False for NaN; +-inf fall outside any finite range
    return cv2.bitwise_and(d, d, mask=valid.view(np.uint8)), valid


def prepare(frame: Frame, light: LightingConfig, recon: ReconstructionConfig) -> Prepared:
    """Mask saturated/black pixels and invalid depth (NaN, inf, out of range); optionally filter the depth
    (reconstruction.depth_filter_px). The linear colour is made when first read (Prepared.linear)."""
    if frame.depth.ndim != 2 or not np.issubdtype(frame.depth.dtype, np.floating):
        raise ValueError(f"frame {frame.index} ({frame.source}): depth is {frame.depth.dtype} of shape "
                         f"{frame.depth.shape}, expected HxW float metres (a sensor's integer units divided by its "
                         "depth_scale, as photoreg's readers do)")
    if frame.color.size == 0:
        raise ValueError(f"frame {frame.index} ({frame.source}): an empty image ({frame.color.shape})")
    if frame.color.shape[:2] != frame.depth.shape[:2]:
        raise ValueError(f"frame {frame.index} ({frame.source}): colour {frame.color.shape[:2]} and depth "
                         f"{frame.depth.shape[:2]} sizes differ")
    if frame.color.shape[:2] != (frame.intrinsics.height, frame.intrinsics.width):
        raise ValueError(f"frame {frame.index} ({frame.source}): size {frame.color.shape[1]}x{frame.color.shape[0]} "
                         f"differs from the intrinsics {frame.intrinsics.width}x{frame.intrinsics.height}")
    if frame.color.dtype != np.uint8 or frame.color.ndim != 3 or frame.color.shape[2] != 3:
        raise ValueError(f"frame {frame.index} ({frame.source}): colour is {frame.color.dtype} of shape "
                         f"{frame.color.shape}, expected 8-bit RGB (HxWx3 uint8)")
    r, g, b = cv2.split(frame.color)
    cmax = cv2.max(cv2.max(r, g), b)   # the brightest channel: 0.13 ms at 640x480, 0.34 in numpy
    saturated = cmax >= light.saturation_level
    black = cmax <= light.black_level
    low, high = cv2.minMaxLoc(cmax)[:2]
    # no real view shows one level everywhere; a camera's grey or blank frame does, and lit as it is it restarted the
    # temporal filter and left the traced light's irradiance a third low for ten frames (the demo, frame 3 grey)
    uniform = high - low <= UNIFORM_LEVELS
    d, valid = masked_depth(frame.depth, recon.depth_min, recon.depth_max)
    if recon.depth_filter_px:
        d = filter_depth(d, valid, recon.depth_filter_px, recon.depth_filter_m)
    n = float(d.size)

    def share(mask: np.ndarray) -> float:
        return cv2.countNonZero(mask.view(np.uint8)) / n   # 15x faster than mask.sum()

    usable, clipped = ((np.zeros_like(valid),) * 2 if uniform else
                       (valid & ~saturated & ~black, valid & saturated & ~black))
    return Prepared(frame.color, d, usable, clipped, share(saturated), share(black), share(valid), light.denoise,
                    uniform)
