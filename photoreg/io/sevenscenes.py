"""Microsoft 7-Scenes sequence layout: frame-XXXXXX.color.png, .depth.png (millimetres, 65535 = invalid)
and .pose.txt (4x4 camera-to-world) side by side in one folder, 30 frames per second."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..types import Intrinsics
from .intrinsics import Calibration, read_calibration
from .recording import Recording, data_lines, read_matrix4

FILE_NAME = re.compile(r"frame-(\d+)\.(color|depth|pose)\.\w+")
DEFAULT_INTRINSICS = Intrinsics(640, 480, 585.0, 585.0, 320.0, 240.0, 1000.0)
INVALID_DEPTH = 65535
FPS = 30.0


def open_7scenes(path: Path, undistort: bool) -> Recording:
    """A 7-Scenes sequence folder; frames in number order, all pose files read and checked."""
    files: dict[str, dict[int, Path]] = {"color": {}, "depth": {}, "pose": {}}
    for p in path.iterdir():
        m = FILE_NAME.fullmatch(p.name)
        if m:
            n, kind = int(m.group(1)), m.group(2)
            if n in files[kind]:
                raise ValueError(f"{p}: frame {n} already has a {kind} file ({files[kind][n].name})")
            files[kind][n] = p
    numbers = sorted(files["color"])
    if not numbers:
        raise ValueError(f"{path}: no frame-XXXXXX.color.* files")
    colors = [files["color"][n] for n in numbers]
    # a missing depth file is reported when its frame is read, like any other unreadable image
    depths = [files["depth"].get(n, c.with_name(c.name.split(".color.")[0] + ".depth.png"))
              for n, c in zip(numbers, colors)]
    poses = None
    if files["pose"]:
        poses = [read_matrix4(data_lines(files["pose"][n]), files["pose"][n]) if n in files["pose"] else None
                 for n in numbers]
    calib = read_calibration(path, DEFAULT_INTRINSICS.depth_scale) or Calibration(
        DEFAULT_INTRINSICS, None, "7-Scenes defaults (fx=fy=585, cx=320, cy=240)")
    notes = [f"intrinsics from {calib.source}", f"timestamps are frame position / {FPS:g}"]
    return Recording(path=path, format="7scenes", intrinsics=calib.intrinsics,
                     timestamps=np.arange(len(colors)) / FPS, color_files=colors, depth_files=depths,
                     poses=poses, distortion=calib.distortion, undistort=undistort,
                     invalid_depth=INVALID_DEPTH, notes=notes, shutter=calib.shutter)
