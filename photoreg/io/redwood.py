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


def numbered(folder: Path) -> dict[tuple[int, ...], Path]:
    """Image files of a folder by the numbers in their names (00012.png -> (12,), 000001-000000033.jpg -> (1, 33)),
    in number order."""
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
    return dict(sorted(found.items()))


def pair_frames(color_dir: Path, depth_dir: Path) -> tuple[list[int] | None, list[Path], list[Path], list[str]]:
    """Colour and depth images paired by frame number: (frame numbers or None, colours, depths, notes).

    Where both folders hold the same numbers they pair as named; else by each name's first number (Redwood's
    INDEX-TIMESTAMP names, whose timestamps differ between the two) where that is unique in both folders: a colour
    image without a depth image of its number gets the one its name would have (depth/NAME.png, missing: its frame
    is skipped, the file named, when read). Names whose first numbers repeat (timestamps) pair in order, and only in
    equal numbers. The frame numbers (None where names pair in order) index the .log trajectory."""
    colors, depths = numbered(color_dir), numbered(depth_dir)
    if colors.keys() == depths.keys():
        first = [n[0] for n in colors]
        return (first if len(set(first)) == len(first) else None), list(colors.values()), list(depths.values()), []
    c_first = {n[0]: p for n, p in colors.items()}
    d_first = {n[0]: p for n, p in depths.items()}
    if len(c_first) == len(colors) and len(d_first) == len(depths):
        numbers = sorted(c_first)
        no_depth = [n for n in numbers if n not in d_first]
        no_color = sorted(set(d_first) - set(c_first))
        notes = [f"{len(no_depth)} colour image(s) without a depth image of their number (first: "
                 f"{c_first[no_depth[0]].name})"] if no_depth else []
        notes += [f"{len(no_color)} depth image(s) without a colour image of their number, left out (first: "
                  f"{d_first[no_color[0]].name})"] if no_color else []
        depth = [d_first.get(n, depth_dir / f"{c_first[n].stem}.png") for n in numbers]
        return numbers, [c_first[n] for n in numbers], depth, notes
    if len(colors) != len(depths):
        raise ValueError(f"{color_dir} holds {len(colors)} images but {depth_dir} holds {len(depths)}, and their "
                         "names' numbers do not pair them")
    return None, list(colors.values()), list(depths.values()), ["colour and depth images paired in name order"]


def read_log(path: Path, numbers: list[int] | None, n_frames: int) -> tuple[list[np.ndarray | None], int]:
    """Redwood .log: per pose a line `id id frame` then 4 rows of a 4x4 camera-to-world matrix. The id is the
    frame's number (`numbers`, pair_frames') where that matches at least as many records as its 0-based position
    does (a folder with frames missing, or a part of a sequence; a record of a missing frame is unused), else the
    position. Returns the poses (None for frames it does not list) and the count of records past the recording's
    last frame (the first frames of a sequence kept with its whole log), which are unused."""
    rows = data_lines(path)
    records = []
    for k in range(0, len(rows), 5):
        lineno, head = rows[k]
        if len(head) != 3 or not all(x.isdigit() for x in head):
            raise ValueError(f"{path}:{lineno}: expected a record header of 3 integers 'id id frame', "
                             f"found {' '.join(head)!r}")
        records.append((lineno, int(head[0]), k))
    position = {i: i for i in range(n_frames)}
    if numbers is not None:
        by_number = {n: i for i, n in enumerate(numbers)}
        if sum(i in by_number for _, i, _ in records) >= sum(i in position for _, i, _ in records):
            position = by_number
    last = max(position)
    poses: list[np.ndarray | None] = [None] * n_frames
    for lineno, i, k in records:
        if i not in position:
            continue
        if poses[position[i]] is not None:
            raise ValueError(f"{path}:{lineno}: second pose for frame {i}")
        poses[position[i]] = read_matrix4(rows[k + 1:k + 5], path)
    return poses, sum(i > last for _, i, _ in records)


def open_redwood(path: Path, undistort: bool) -> Recording:
    """An ICL-NUIM/Redwood folder; colour and depth images paired by frame number (pair_frames)."""
    color_dir = next((path / d for d in COLOR_DIRS if (path / d).is_dir()), None)
    if color_dir is None:
        raise FileNotFoundError(f"{path}: no color/ or image/ folder")
    numbers, colors, depths, pairing = pair_frames(color_dir, path / "depth")
    calib = read_calibration(path, DEFAULT_INTRINSICS.depth_scale) or Calibration(
        DEFAULT_INTRINSICS, None, "ICL-NUIM/Redwood defaults (fx=fy=525, cx=319.5, cy=239.5)")
    clock = "number" if numbers is not None else "position"
    notes = [f"intrinsics from {calib.source}", f"timestamps are frame {clock} / {FPS:g}", *pairing]
    logs = sorted(path.glob("*.log"))
    if len(logs) > 1:
        raise ValueError(f"{path}: several .log trajectories ({', '.join(p.name for p in logs)}); keep one")
    poses, warnings = None, []
    if logs:
        poses, past = read_log(logs[0], numbers, len(colors))
        notes.append(f"poses from {logs[0].name}")
        if past:
            notes.append(f"{logs[0].name}: {past} record(s) of frames past the recording's last unused")
        if not any(p is not None for p in poses):
            warnings.append(f"{logs[0].name} gives none of the {len(colors)} frames a pose: the camera is tracked")
        elif past and poses[0] is None:   # a log counted from 1 poses each frame as the one after it
            warnings.append(f"{logs[0].name} has records past the recording's last frame and none for its first: "
                            "are its ids counted from 1? They are frame numbers, from 0 (each pose would be the "
                            "next frame's)")
    return Recording(path=path, format="redwood", intrinsics=calib.intrinsics,
                     timestamps=np.asarray(numbers if numbers is not None else range(len(colors)), float) / FPS,
                     color_files=colors, depth_files=depths, poses=poses, distortion=calib.distortion,
                     undistort=undistort, notes=notes, warnings=warnings,
                     shutter=calib.shutter)
