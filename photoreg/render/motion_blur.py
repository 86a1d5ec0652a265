"""Motion blur of the insertion, matching the camera's (render.shutter).

A camera that moves while its shutter is open blurs the frame along each pixel's image motion, and an object
composited sharp into such a frame stands out from it. What the renderer's layers change (the objects and the shadows
they cast) is blurred along the same motion: at pixel x the layers are the mean of theirs at x + u b(x), u spread
evenly over [-1/2, 1/2], where b(x) is how far the surface seen at x moves in the image while the shutter is open:
its displacement between the previous frame's pose and this one's, times shutter / (t - t_prev) (a shutter centred on
the frame's time, the camera's velocity taken as constant across it). The surface is the virtual one where the
G-buffer covers a pixel, else the real one (sensor depth, its holes at the box's median depth).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from photoreg.render.composite import Layers, composite, stride_box
from photoreg.types import Intrinsics

MAX_SAMPLES = 32   # instants along a pixel's motion averaged at most (one per pixel of the longest blur)
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


def blurred_composite(camera: np.ndarray, layers: Layers, depth: np.ndarray, intr: Intrinsics,
                      m: Motion) -> tuple[np.ndarray, Box | None]:
    """(composite, its region) of a renderer's `layers` over the camera frame with what they change blurred along the
    camera's motion `m` (module docstring): the frame's factor (1 - alpha) ratio and the objects' term alpha colour
    are each averaged along the motion, so the frame shows through the objects only where their blurred coverage
    lets it (blurring the composite less the frame let the frame's own detail through them). `depth` (H, W) metres of
    the surface each pixel shows (0 or non-finite: unknown). The region grows by half the longest blur; the sharp
    composite (composite.composite) where that is under MIN_BLUR_PX or no depth is known."""
    H, W = camera.shape[:2]
    box = layers.region if layers.region is not None else stride_box(
        (layers.alpha > 0) | (layers.ratio != 1.0).any(axis=-1), 1, (H, W))
    known = np.isfinite(depth) & (depth > 0)
    if box is None or not (box[2] > box[0] and box[3] > box[1]) or not known[box[1]:box[3], box[0]:box[2]].any():
        return composite(camera, layers), layers.region
    fill = float(np.median(depth[box[1]:box[3], box[0]:box[2]][known[box[1]:box[3], box[0]:box[2]]]))
    z = np.where(known, depth, fill)

    def vectors(bx: Box) -> np.ndarray:
        return blur_vectors(z[bx[1]:bx[3], bx[0]:bx[2]], intr, m, bx)

    longest = float(np.linalg.norm(vectors(box), axis=-1).max())
    if longest < MIN_BLUR_PX:
        return composite(camera, layers), layers.region
    reach = int(math.ceil(longest / 2)) + 1
    grown = (max(box[0] - reach, 0), max(box[1] - reach, 0), min(box[2] + reach, W), min(box[3] + reach, H))
    x0, y0, x1, y1 = grown
    b = vectors(grown)
    n = min(MAX_SAMPLES, int(math.ceil(float(np.linalg.norm(b, axis=-1).max()))) + 1)
    rows, cols = slice(y0, y1), slice(x0, x1)
    alpha = layers.alpha[rows, cols, None]
    frame = ((1.0 - alpha) * layers.ratio[rows, cols]).astype(np.float32)   # 1 outside the layers' region
    objects = (alpha * layers.colour[rows, cols]).astype(np.float32)        # 0 there
    ys, xs = np.mgrid[0:y1 - y0, 0:x1 - x0].astype(np.float32)
    frame_sum, objects_sum = np.zeros_like(frame), np.zeros_like(objects)
    for u in (np.arange(n, dtype=np.float32) + 0.5) / n - 0.5:
        mx, my = xs + u * b[..., 0], ys + u * b[..., 1]
        frame_sum += cv2.remap(frame, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(1, 1, 1))
        objects_sum += cv2.remap(objects, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    out = np.nan_to_num(np.array(camera, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    out[rows, cols] = np.maximum(out[rows, cols] * frame_sum / n + objects_sum / n, 0.0)
    return out, grown
