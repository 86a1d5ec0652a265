"""Motion blur of the insertion, matching the camera's (render.shutter).

A camera that moves while its shutter is open blurs the frame along each pixel's image motion, and an object
composited sharp into such a frame stands out from it. What the renderer's layers change (the objects and the shadows
they cast) is blurred along the same motion: at pixel x the layers are the mean of theirs at x + u b(x), u spread
evenly over [-1/2, 1/2], where b(x) is how far the surface seen at x moves in the image while the shutter is open:
its displacement between the previous frame's pose and this one's, times shutter / (t - t_prev) (a shutter centred on
the frame's time, the camera's velocity taken as constant across it). The surface is the virtual one where the
G-buffer covers a pixel, else the real one (sensor depth, its holes at the box's median depth). The motion and the
samples are computed on the pipeline's device (photoreg.kernels.blur).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from photoreg.kernels.blur import blur_layers, motion_lengths
from photoreg.render.composite import Layers, composite, stride_box
from photoreg.types import Intrinsics

MAX_SAMPLES = 32   # instants along a pixel's motion averaged at most (one per pixel of its blur, and one)
MIN_BLUR_PX = 0.5  # a longest blur below this gives the sharp composite
MAX_GAP_S = 0.25   # poses further apart than this do not give the camera's velocity over a shutter time
Box = tuple[int, int, int, int]   # pixels (x0, y0, x1, y1), x1 and y1 exclusive


@dataclass
class Motion:
    """The camera's motion over one frame's shutter: its pose at the frame's time, at the previous frame's, and
    the shutter time's share of the time between them."""

    pose: np.ndarray       # (4, 4) camera-to-world at the frame's time
    previous: np.ndarray   # (4, 4) camera-to-world at the previous frame's time
    share: float           # shutter / (t - t_previous)


def motion(pose: np.ndarray, timestamp: float, previous: tuple[float, np.ndarray] | None,
           shutter: float) -> Motion | None:
    """The Motion of a frame at `timestamp` seen from `pose`, given the previous rendered frame's (timestamp, pose);
    None without a shutter time, a previous frame, or with one out of order or more than MAX_GAP_S before."""
    if shutter <= 0 or previous is None:
        return None
    dt = timestamp - previous[0]
    if not 0 < dt <= MAX_GAP_S:
        return None
    return Motion(np.asarray(pose, np.float64), np.asarray(previous[1], np.float64), shutter / dt)


def blurred_composite(camera: np.ndarray, layers: Layers, depth: np.ndarray, intr: Intrinsics, m: Motion,
                      device: str = "cpu") -> tuple[np.ndarray, Box | None]:
    """(composite, its region) of a renderer's `layers` over the camera frame with what they change blurred along the
    camera's motion `m` (module docstring): the frame's factor (1 - alpha) ratio and the objects' term alpha colour
    are each averaged along the motion, so the frame shows through the objects only where their blurred coverage
    lets it (blurring the composite less the frame let the frame's own detail through them). `depth` (H, W) metres of
    the surface each pixel shows (0 or non-finite: unknown). The region grows by half the longest blur; the sharp
    composite (composite.composite) where that is under MIN_BLUR_PX or no depth is known. The samples are taken on
    `device` (kernels.blur)."""
    H, W = camera.shape[:2]
    box = layers.region if layers.region is not None else stride_box(
        (layers.alpha > 0) | (layers.ratio != 1.0).any(axis=-1), 1, (H, W))
    if box is None or not (box[2] > box[0] and box[3] > box[1]):
        return composite(camera, layers), layers.region
    d = depth[box[1]:box[3], box[0]:box[2]]
    known = np.isfinite(d) & (d > 0)
    if not known.any():
        return composite(camera, layers), layers.region
    fill = float(np.median(d[known]))   # the depth of the box's unknown pixels, and of the grown box's
    longest = float(motion_lengths(d, fill, box[:2], intr, m.pose, m.previous, m.share, device).max())
    if longest < MIN_BLUR_PX:
        return composite(camera, layers), layers.region
    reach = int(math.ceil(longest / 2)) + 1
    x0, y0, x1, y1 = grown = (max(box[0] - reach, 0), max(box[1] - reach, 0), min(box[2] + reach, W),
                              min(box[3] + reach, H))
    rows, cols = slice(y0, y1), slice(x0, x1)
    out = np.array(camera, dtype=np.float32)
    if not np.isfinite(out).all():
        np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    out[rows, cols] = blur_layers(out[rows, cols], layers.alpha[rows, cols], layers.ratio[rows, cols],
                                  layers.colour[rows, cols], depth[rows, cols], fill, (x0, y0), intr, m.pose,
                                  m.previous, m.share, MAX_SAMPLES, device)
    return out, grown
