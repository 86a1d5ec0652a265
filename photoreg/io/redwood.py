"""ICL-NUIM / Redwood / Open3D layout: color/ (or image/, rgb/) and depth/ folders of numbered images,
a Redwood .log trajectory (camera-to-world), depth in millimetres, 30 frames per second."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..types import Intrinsics
from .intrinsics import Calibration, read_calibration
from .recording import Recording, data_lines, read_matrix4

COLOR_DIRS = ("color", "image")  # not rgb/: that is a TUM folder missing its rgb.txt
DEFAULT_INTRINSICS = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5, 1000.0)  # PrimeSense defaults, as Open3D
FPS = 30.0
IMAGE_EXTENSIONS = {".png", ".jpg", ".jpeg", ".jpe", ".bmp", ".dib", ".tif", ".tiff", ".exr", ".hdr", ".pic",
                    ".webp", ".jp2", ".pbm", ".pgm", ".ppm", ".pxm", ".pnm", ".pfm", ".sr", ".ras", ".avif"}


def numbered_images(folder: Path) -> list[Path]:
    """Image files of a folder ordered by the numbers in their names (00012.png -> 12,
    000001-000000033.jpg -> (1, 33))."""
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    found: dict[tuple[int, ...], Path] = {}
    for p in folder.iterdir():
        if p.name.startswith(".") or p.suffix.lower() not in IMAGE_EXTENSIONS:
            continue
        n = tuple(int(x) for x in re.findall(r"\d+", p.stem))
        if not n:
            raise ValueError(f"{p}: no frame number in the file name")
        if n in found:
            raise ValueError(f"{p}: same frame number as {found[n].name}")
        found[n] = p
    if not found:
        raise ValueError(f"{folder}: no images")
    return [found[n] for n in sorted(found)]


def read_log(path: Path, n_frames: int) -> list[np.ndarray | None]:
    """Redwood .log: per pose a line `id id frame` (id = 0-based frame index) then 4 rows of a
    4x4 camera-to-world matrix. Frames it does not list get None."""
    rows = data_lines(path)
    poses: list[np.ndarray | None] = [None] * n_frames
    for k in range(0, len(rows), 5):
        lineno, head = rows[k]
        if len(head) != 3 or not all(x.isdigit() for x in head):
            raise ValueError(f"{path}:{lineno}: expected a record header of 3 integers 'id id frame', "
                             f"found {' '.join(head)!r}")
        i = int(head[0])
        if i >= n_frames:
            raise ValueError(f"{path}:{lineno}: frame {i} out of range (the recording has {n_frames} frames)")
        if poses[i] is not None:
            raise ValueError(f"{path}:{lineno}: second pose for frame {i}")
        poses[i] = read_matrix4(rows[k + 1:k + 5], path)
    return poses


def open_redwood(path: Path, undistort: bool) -> Recording:
    """An ICL-NUIM/Redwood folder; colour and depth images paired in number order."""
    color_dir = next((path / d for d in COLOR_DIRS if (path / d).is_dir()), None)
    if color_dir is None:
        raise FileNotFoundError(f"{path}: no color/ or image/ folder")
    colors = numbered_images(color_dir)
    depths = numbered_images(path / "depth")
    if len(colors) != len(depths):
        raise ValueError(f"{color_dir} holds {len(colors)} images but {path / 'depth'} holds {len(depths)}")
    calib = read_calibration(path, DEFAULT_INTRINSICS.depth_scale) or Calibration(
        DEFAULT_INTRINSICS, None, "ICL-NUIM/Redwood defaults (fx=fy=525, cx=319.5, cy=239.5)")
    notes = [f"intrinsics from {calib.source}", f"timestamps are frame position / {FPS:g}"]
    logs = sorted(path.glob("*.log"))
    if len(logs) > 1:
        raise ValueError(f"{path}: several .log trajectories ({', '.join(p.name for p in logs)}); keep one")
    poses = read_log(logs[0], len(colors)) if logs else None
    if logs:
        notes.append(f"poses from {logs[0].name}")
    return Recording(path=path, format="redwood", intrinsics=calib.intrinsics,
                     timestamps=np.arange(len(colors)) / FPS, color_files=colors, depth_files=depths,
                     poses=poses, distortion=calib.distortion, undistort=undistort, notes=notes,
                     shutter=calib.shutter)
