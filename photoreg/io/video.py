"""composite.mp4: a run's composites as one video (OpenCV's MPEG-4 'mp4v' writer). It is written to a
.partial.mp4 file and renamed when finished, so an interrupted run leaves no truncated video under the
final name."""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from .images import linear_to_srgb

FALLBACK_FPS = 30.0


def frame_rate(timestamps: np.ndarray) -> float:
    """Frames per second of the frames at these timestamps (seconds): 1 / the median step; FALLBACK_FPS when
    there are fewer than two or the steps are not positive."""
    steps = np.diff(np.asarray(timestamps, dtype=np.float64))
    step = float(np.median(steps)) if steps.size else 0.0
    return 1.0 / step if step > 0 and np.isfinite(step) else FALLBACK_FPS


class VideoOut:
    """Linear RGB frames (H, W, 3) appended in order to `path` as sRGB at `fps`; close() finishes and renames, or
    drops a video of no frames (an earlier one under that name stays)."""

    def __init__(self, path: str | Path, width: int, height: int, fps: float):
        self.path = Path(path)
        self.tmp = self.path.with_name(self.path.stem + ".partial" + self.path.suffix)
        self.size, self.frames = (int(width), int(height)), 0
        self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), self.size)
        if not self.writer.isOpened():
            raise RuntimeError(f"{self.tmp}: OpenCV cannot write an mp4v video here (its video backend is missing)")

    def write(self, linear: np.ndarray) -> None:
        if (linear.shape[1], linear.shape[0]) != self.size:
            raise ValueError(f"{self.path}: frame is {linear.shape[1]}x{linear.shape[0]}, the video "
                             f"{self.size[0]}x{self.size[1]}")
        self.writer.write(cv2.cvtColor(linear_to_srgb(linear), cv2.COLOR_RGB2BGR))
        self.frames += 1

    def close(self) -> bool:
        """Finish the video; True when it was written under its name, False when it had no frames."""
        self.writer.release()
        if not self.frames:
            self.tmp.unlink(missing_ok=True)
            return False
        os.replace(self.tmp, self.path)
        return True
