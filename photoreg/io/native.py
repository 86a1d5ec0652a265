"""Writer of the native recording layout (DESIGN.md "Files"; TUM style): colour, 16-bit depth, lists,
ground-truth poses, intrinsics and ground-truth lighting, every file written atomically."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..types import Intrinsics
from .atomic import write_json, write_text
from .images import write_png16, write_png_rgb
from .poses import format_tum_line


def frame_name(index: int) -> str:
    """NNNNNN: the 0-based frame index zero-padded to 6 digits."""
    return f"{index:06d}"


def depth_to_png16(depth: np.ndarray, depth_scale: float) -> np.ndarray:
    """Float metres -> uint16 in `depth_scale` units per metre (rounded); invalid or out of range -> 0."""
    d = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0) * depth_scale
    q = np.round(d)
    return np.where((q > 0) & (q <= 65535), q, 0).astype(np.uint16)


class NativeWriter:
    """Writes frames as they come (rgb/, depth/, optional depth_clean/); `finish()` writes rgb.txt,
    depth.txt, groundtruth.txt and intrinsics.json."""

    def __init__(self, root: str | os.PathLike, intrinsics: Intrinsics, source: str = "photoreg",
                 shutter: float | None = None):
        self.root = Path(root)
        self.K = intrinsics
        self.source = source
        self.shutter = shutter   # seconds the shutter was open for each frame (intrinsics.json "shutter")
        self._frames: list[tuple[float, str, np.ndarray | None]] = []

    def write_frame(self, index: int, timestamp: float, rgb8: np.ndarray, depth: np.ndarray,
                    pose: np.ndarray | None = None, depth_clean: np.ndarray | None = None) -> None:
        """One frame: 8-bit sRGB RGB image (H, W, 3), depth in metres (0 = invalid), camera-to-world pose."""
        if index != len(self._frames):
            raise ValueError(f"frame {index} written out of order (expected {len(self._frames)})")
        shape = (self.K.height, self.K.width)
        if rgb8.shape != shape + (3,) or rgb8.dtype != np.uint8 or depth.shape != shape:
            raise ValueError(f"frame {index}: rgb {rgb8.shape} {rgb8.dtype} / depth {depth.shape} "
                             f"do not match intrinsics {self.K.width}x{self.K.height} uint8")
        name = frame_name(index) + ".png"
        write_png_rgb(self.root / "rgb" / name, rgb8)
        write_png16(self.root / "depth" / name, depth_to_png16(depth, self.K.depth_scale))
        if depth_clean is not None:
            write_png16(self.root / "depth_clean" / name, depth_to_png16(depth_clean, self.K.depth_scale))
        self._frames.append((float(timestamp), name, None if pose is None else np.asarray(pose, dtype=np.float64)))

    def write_lighting_gt(self, sh: np.ndarray, **extra) -> None:
        """lighting_gt.json: {"bands", "sh" (3 x B*B), "frame": "world", **extra}."""
        sh = np.asarray(sh, dtype=np.float64)
        bands = int(round(np.sqrt(sh.shape[1])))
        write_json(self.root / "lighting_gt.json", {"bands": bands, "sh": sh.tolist(), "frame": "world", **extra})

    def finish(self) -> None:
        """The lists, trajectory (when every frame has a pose) and intrinsics."""
        for kind in ("rgb", "depth"):
            lines = [f"# {kind} images written by {self.source}", "# timestamp filename"]
            lines += [f"{t:.6f} {kind}/{name}" for t, name, _ in self._frames]
            write_text(self.root / f"{kind}.txt", "\n".join(lines) + "\n")
        if self._frames and all(p is not None for _, _, p in self._frames):
            lines = [f"# ground-truth trajectory written by {self.source}", "# timestamp tx ty tz qx qy qz qw"]
            lines += [format_tum_line(t, p) for t, _, p in self._frames]
            write_text(self.root / "groundtruth.txt", "\n".join(lines) + "\n")
        write_json(self.root / "intrinsics.json",
                   {**self.K.to_json(), **({} if self.shutter is None else {"shutter": self.shutter})})
