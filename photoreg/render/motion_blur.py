"""Motion blur of the insertion, matching the camera's (render.shutter).

A camera that moves while its shutter is open blurs the frame along each pixel's image motion, and an object
composited sharp into such a frame stands out from it. The insertion (the composite less the camera frame: the
objects and the shadows they cast) is blurred along the same motion: pixel x takes the mean of the insertion at
x + u b(x), u spread evenly over [-1/2, 1/2], where b(x) is how far the surface seen at x moves in the image while
the shutter is open: its displacement between the previous frame's pose and this one's, times shutter / (t - t_prev)
(a shutter centred on the frame's time, the camera's velocity taken as constant across it). The surface is the
virtual one where the G-buffer covers a pixel, else the real one (sensor depth, its holes at the box's median depth).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from photoreg.render.composite import stride_box
from photoreg.types import Intrinsics

MAX_SAMPLES = 32   # instants along a pixel's motion averaged at most (one per pixel of the longest blur)
MIN_BLUR_PX = 0.5  # a longest blur below this leaves the composite as it is
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


def blur_vectors(depth: np.ndarray, intr: Intrinsics, m: Motion, box: Box) -> np.ndarray:
    """(h, w, 2) image motion b (pixels, x then y) during the shutter of the surfaces at camera depth `depth`
    (the box's pixels, metres, finite and > 0) in the pixel box (x0, y0, x1, y1); 0 where the surface lies behind
    the previous camera."""
    x0, y0, x1, y1 = box
    ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    z = depth.astype(np.float64)
    cam = np.stack([(xs - intr.cx) / intr.fx * z, (ys - intr.cy) / intr.fy * z, z], axis=-1)
    world = cam @ m.pose[:3, :3].T + m.pose[:3, 3]
    before = (world - m.previous[:3, 3]) @ m.previous[:3, :3]    # world -> previous camera
    ahead = before[..., 2] > 1e-6
    zb = np.where(ahead, before[..., 2], 1.0)
    u = intr.fx * before[..., 0] / zb + intr.cx
    v = intr.fy * before[..., 1] / zb + intr.cy
    b = m.share * np.stack([xs - u, ys - v], axis=-1)
    b[~ahead] = 0.0
    return b.astype(np.float32)


def blur_insertion(out: np.ndarray, camera: np.ndarray, region: Box | None, depth: np.ndarray, intr: Intrinsics,
                   m: Motion) -> tuple[np.ndarray, Box | None]:
    """(composite, its region) with the insertion `out - camera` inside `region` (None: wherever they differ)
    blurred along the camera's motion `m` (module docstring); `depth` (H, W) metres of the surface each pixel shows
    (0 or non-finite: unknown). The region grows by half the longest blur; `out` is returned as it is where that is
    under MIN_BLUR_PX or no depth is known."""
    H, W = out.shape[:2]
    box = region if region is not None else stride_box(np.any(out != camera, axis=-1), 1, (H, W))
    if box is None or not (box[2] > box[0] and box[3] > box[1]):
        return out, box
    known = np.isfinite(depth) & (depth > 0)
    if not known[box[1]:box[3], box[0]:box[2]].any():
        return out, box
    fill = float(np.median(depth[box[1]:box[3], box[0]:box[2]][known[box[1]:box[3], box[0]:box[2]]]))
    z = np.where(known, depth, fill)

    def vectors(bx: Box) -> np.ndarray:
        return blur_vectors(z[bx[1]:bx[3], bx[0]:bx[2]], intr, m, bx)

    longest = float(np.linalg.norm(vectors(box), axis=-1).max())
    if longest < MIN_BLUR_PX:
        return out, box
    reach = int(math.ceil(longest / 2)) + 1
    grown = (max(box[0] - reach, 0), max(box[1] - reach, 0), min(box[2] + reach, W), min(box[3] + reach, H))
    x0, y0, x1, y1 = grown
    b = vectors(grown)
    longest = float(np.linalg.norm(b, axis=-1).max())
    n = min(MAX_SAMPLES, int(math.ceil(longest)) + 1)
    cam = np.nan_to_num(camera[y0:y1, x0:x1].astype(np.float32))
    delta = out[y0:y1, x0:x1] - cam
    ys, xs = np.mgrid[0:y1 - y0, 0:x1 - x0].astype(np.float32)
    acc = np.zeros_like(delta)
    for u in (np.arange(n) + 0.5) / n - 0.5:
        acc += cv2.remap(delta, xs + np.float32(u) * b[..., 0], ys + np.float32(u) * b[..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    blurred = out.copy()
    blurred[y0:y1, x0:x1] = np.maximum(cam + acc / n, 0.0)
    return blurred, grown
