"""Camera calibration files of a recording folder: intrinsics.json (native) or intrinsics.txt (key-value lines)."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..types import Intrinsics
from .recording import data_lines, parse_floats

VGA = (640, 480)  # image size of every supported sensor (Kinect v1 class) when a file does not give one
TXT_KEYS = {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "depth_scale": 1, "width": 1, "height": 1, "dist": 5}


class Calibration(NamedTuple):
    intrinsics: Intrinsics
    distortion: np.ndarray | None  # k1 k2 p1 p2 k3, None when unknown
    source: str                    # where it came from, for notes and error messages


def checked_intrinsics(values: dict, where: str) -> Intrinsics:
    """Intrinsics from a dict of numbers, refusing sizes, focal lengths or scales that cannot be right."""
    w, h = values["width"], values["height"]
    if not (float(w).is_integer() and float(h).is_integer() and w > 0 and h > 0):
        raise ValueError(f"{where}: image size must be positive integers, found {w}x{h}")
    for key in ("fx", "fy", "depth_scale"):
        if not (math.isfinite(values[key]) and values[key] > 0):
            raise ValueError(f"{where}: {key} must be a positive number, found {values[key]}")
    for key in ("cx", "cy"):
        if not math.isfinite(values[key]):
            raise ValueError(f"{where}: {key} must be a finite number, found {values[key]}")
    return Intrinsics(int(w), int(h), float(values["fx"]), float(values["fy"]),
                      float(values["cx"]), float(values["cy"]), float(values["depth_scale"]))


def read_intrinsics_json(path: Path, depth_scale: float) -> Intrinsics:
    """intrinsics.json {width, height, fx, fy, cx, cy, depth_scale}; depth_scale defaults to `depth_scale`."""
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}:{e.lineno}: not valid JSON ({e.msg})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object")
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in data]
    if missing:
        raise ValueError(f"{path}: missing {', '.join(missing)}")
    values = {"depth_scale": depth_scale, **data}
    for key in ("width", "height", "fx", "fy", "cx", "cy", "depth_scale"):
        if isinstance(values[key], bool) or not isinstance(values[key], (int, float)):
            raise ValueError(f"{path}: {key} must be a number, found {values[key]!r}")
    return checked_intrinsics(values, str(path))


def read_intrinsics_txt(path: Path, depth_scale: float) -> tuple[Intrinsics, np.ndarray | None]:
    """intrinsics.txt: lines `fx 517.3`, `cx ...`, optional `depth_scale`, `width`, `height` and
    `dist k1 k2 p1 p2 k3`; '#' comments. Size defaults to 640x480, depth_scale to `depth_scale`."""
    values: dict = {"width": VGA[0], "height": VGA[1], "depth_scale": depth_scale}
    distortion = None
    for lineno, fields in data_lines(path):
        key = fields[0]
        if key not in TXT_KEYS:
            raise ValueError(f"{path}:{lineno}: unknown key {key!r} (expected one of {', '.join(TXT_KEYS)})")
        numbers = parse_floats(fields[1:], path, lineno, TXT_KEYS[key])
        if key == "dist":
            distortion = np.array(numbers)
        else:
            values[key] = numbers[0]
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in values]
    if missing:
        raise ValueError(f"{path}: missing {', '.join(missing)}")
    if distortion is not None and not np.all(np.isfinite(distortion)):
        raise ValueError(f"{path}: distortion coefficients must be finite")
    return checked_intrinsics(values, str(path)), distortion


def read_calibration(folder: Path, depth_scale: float) -> Calibration | None:
    """The folder's intrinsics.json, else its intrinsics.txt, else None (the format's defaults apply)."""
    if (folder / "intrinsics.json").is_file():
        path = folder / "intrinsics.json"
        return Calibration(read_intrinsics_json(path, depth_scale), None, path.name)
    if (folder / "intrinsics.txt").is_file():
        path = folder / "intrinsics.txt"
        return Calibration(*read_intrinsics_txt(path, depth_scale), path.name)
    return None
