"""Camera calibration files of a recording folder: intrinsics.json (native) or intrinsics.txt (key-value lines)."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..types import Intrinsics
from .recording import data_lines, parse_floats
from .text import read_text

VGA = (640, 480)  # image size of every supported sensor (Kinect v1 class) when a file does not give one
TXT_KEYS = {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "depth_scale": 1, "width": 1, "height": 1, "dist": 5, "shutter": 1}


class Calibration(NamedTuple):
    intrinsics: Intrinsics
    distortion: np.ndarray | None  # k1 k2 p1 p2 k3, None when unknown
    source: str                    # where it came from, for notes and error messages
    shutter: float | None = None   # seconds the shutter is open for each frame, when the file says (motion blur)


def checked_shutter(value, where: str) -> float:
    """A calibration file's shutter time: seconds in 0..1."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 1:
        raise ValueError(f"{where}: shutter must be seconds in 0..1, found {value!r}")
    return float(value)


DEPTH_SCALE_RANGE = (0.01, 1e7)   # depth-image units per metre a depth image may have (0.001: metres per unit)


def checked_intrinsics(values: dict, where: str) -> Intrinsics:
    """Intrinsics from a dict of numbers, refusing sizes, focal lengths or scales that cannot be right."""
    w, h = values["width"], values["height"]
    if not (float(w).is_integer() and float(h).is_integer() and w > 0 and h > 0):
        raise ValueError(f"{where}: image size must be positive integers, found {w}x{h}")
    for key in ("fx", "fy", "depth_scale"):
        if not (math.isfinite(values[key]) and values[key] > 0):
            raise ValueError(f"{where}: {key} must be a positive number, found {values[key]}")
    if not DEPTH_SCALE_RANGE[0] <= values["depth_scale"] <= DEPTH_SCALE_RANGE[1]:
        raise ValueError(f"{where}: depth_scale = {values['depth_scale']:g} is no depth image's: it counts the "
                         "depth image's units per metre (1: metres, 1000: millimetres, 5000: TUM), between "
                         f"{DEPTH_SCALE_RANGE[0]:g} and {DEPTH_SCALE_RANGE[1]:g}")
    for key in ("cx", "cy"):
        if not math.isfinite(values[key]):
            raise ValueError(f"{where}: {key} must be a finite number, found {values[key]}")
    for f, c, size in (("fx", "cx", w), ("fy", "cy", h)):
        if values[f] < 1:
            raise ValueError(f"{where}: {f} = {values[f]} is under a pixel: focal lengths are in pixels (normalised "
                             f"ones times the image size)")
        if abs(values[c] - size / 2) > 10 * size:   # a crop far from the centre keeps it within a few sizes
            raise ValueError(f"{where}: {c} = {values[c]} lies far outside the {w:g}x{h:g} image: the principal "
                             "point is in pixels")
    return Intrinsics(int(w), int(h), float(values["fx"]), float(values["fy"]),
                      float(values["cx"]), float(values["cy"]), float(values["depth_scale"]))


JSON_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "depth_scale", "shutter", "dist")


def _scale_source(path: Path, given: bool, depth_scale: float) -> str:
    """Calibration.source of a file, saying when its depth scale is the format's default (depth in other units
    reads wrong by a factor, silently but for this note)."""
    return path.name if given else f"{path.name} (no depth_scale: {depth_scale:g} units per metre, the format's)"


def read_intrinsics_json(path: Path, depth_scale: float) -> Calibration:
    """Calibration of intrinsics.json {width, height, fx, fy, cx, cy, depth_scale, shutter, dist}; depth_scale
    defaults to `depth_scale` (the source says so), shutter (seconds) and dist ([k1, k2, p1, p2, k3], OpenCV's) to
    None."""
    try:
        data = json.loads(read_text(path))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}:{e.lineno}: not valid JSON ({e.msg})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object")
    unknown = [k for k in data if k not in JSON_KEYS]
    if unknown:   # a misspelt depth_scale would silently take the default
        raise ValueError(f"{path}: unknown key(s) {', '.join(map(repr, unknown))} (expected {', '.join(JSON_KEYS)})")
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in data]
    if missing:
        raise ValueError(f"{path}: missing {', '.join(missing)}")
    values = {"depth_scale": depth_scale, **data}
    for key in ("width", "height", "fx", "fy", "cx", "cy", "depth_scale"):
        if isinstance(values[key], bool) or not isinstance(values[key], (int, float)):
            raise ValueError(f"{path}: {key} must be a number, found {values[key]!r}")
    shutter = None if data.get("shutter") is None else checked_shutter(data["shutter"], str(path))
    distortion = None
    if data.get("dist") is not None:
        dist = data["dist"]
        if (not isinstance(dist, list) or len(dist) != TXT_KEYS["dist"]
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in dist)):
            raise ValueError(f"{path}: dist must be {TXT_KEYS['dist']} finite numbers (k1 k2 p1 p2 k3), found {dist!r}")
        distortion = np.array(dist, dtype=np.float64)
    return Calibration(checked_intrinsics(values, str(path)), distortion,
                       _scale_source(path, "depth_scale" in data, depth_scale), shutter)


def read_intrinsics_txt(path: Path, depth_scale: float) -> Calibration:
    """Calibration of intrinsics.txt: lines `fx 517.3`, `cx ...`, optional `depth_scale`, `width`, `height`,
    `dist k1 k2 p1 p2 k3` and `shutter SECONDS`, each once; '#' comments. Size defaults to 640x480, depth_scale to
    `depth_scale` (the source says so)."""
    values: dict = {"width": VGA[0], "height": VGA[1], "depth_scale": depth_scale}
    distortion = shutter = None
    seen: dict[str, int] = {}
    for lineno, fields in data_lines(path):
        key = fields[0]
        if key not in TXT_KEYS:
            raise ValueError(f"{path}:{lineno}: unknown key {key!r} (expected one of {', '.join(TXT_KEYS)})")
        if key in seen:
            raise ValueError(f"{path}:{lineno}: {key} given again (first on line {seen[key]})")
        seen[key] = lineno
        numbers = parse_floats(fields[1:], path, lineno, TXT_KEYS[key])
        if key == "dist":
            distortion = np.array(numbers)
        elif key == "shutter":
            shutter = checked_shutter(numbers[0], f"{path}:{lineno}")
        else:
            values[key] = numbers[0]
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in values]
    if missing:
        raise ValueError(f"{path}: missing {', '.join(missing)}")
    if distortion is not None and not np.all(np.isfinite(distortion)):
        raise ValueError(f"{path}: distortion coefficients must be finite")
    sized = "width" in seen and "height" in seen
    where = str(path) if sized else f"{path} (size {VGA[0]}x{VGA[1]} assumed: give width and height)"
    return Calibration(checked_intrinsics(values, where), distortion,
                       _scale_source(path, "depth_scale" in seen, depth_scale), shutter)


def read_calibration(folder: Path, depth_scale: float) -> Calibration | None:
    """The folder's intrinsics.json, else its intrinsics.txt, else None (the format's defaults apply)."""
    if (folder / "intrinsics.json").is_file():
        calib = read_intrinsics_json(folder / "intrinsics.json", depth_scale)
        ignored = " (intrinsics.txt beside it ignored)" if (folder / "intrinsics.txt").is_file() else ""
        return calib._replace(source=calib.source + ignored)
    if (folder / "intrinsics.txt").is_file():
        return read_intrinsics_txt(folder / "intrinsics.txt", depth_scale)
    return None
