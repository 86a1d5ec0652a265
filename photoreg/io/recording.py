"""Recorded RGB-D sequences: one `Recording` over the native/TUM, ICL-NUIM/Redwood and 7-Scenes layouts.

Opening reads and checks the index files (frame lists, timestamps, poses, calibration); a frame's
images are read, checked and converted (depth to float32 metres) only when the frame is asked for,
so one bad image spoils one frame, not the recording. Format readers: tum.py, redwood.py, sevenscenes.py.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Callable, Iterable, Iterator

import cv2
import numpy as np

from ..types import Frame, Intrinsics
from .ahead import Ahead
from .images import read_depth_raw, read_rgb, registered_depth
from .poses import check_pose
from .text import read_text

FORMATS = ("native", "tum", "redwood", "7scenes")


@dataclass
class Recording:
    """An opened recording: index checked, images read lazily by `frame(i)`.

    Frame i is the i-th frame in the recording's order (rgb.txt order for TUM layouts).
    """

    path: Path
    format: str
    intrinsics: Intrinsics
    timestamps: np.ndarray               # (N,) seconds, strictly increasing
    color_files: list[Path]
    depth_files: list[Path]
    poses: list[np.ndarray | None] | None = None  # camera-to-world per frame; None: no trajectory at all
    distortion: np.ndarray | None = None  # k1 k2 p1 p2 k3 of the colour camera, when known
    undistort: bool = False               # remove `distortion` from every frame read
    invalid_depth: int | None = None      # raw depth value meaning "no measurement" besides 0 (7-Scenes: 65535)
    notes: list[str] = field(default_factory=list)  # where calibration/poses came from, how frames were paired
    # what a run says before its first frame: colour frames the recording's frame order leaves out (TUM: no depth
    # within 0.02 s), which the frame indices then skip
    warnings: list[str] = field(default_factory=list)
    shutter: float | None = None          # seconds the shutter is open for each frame, when the calibration says

    def __post_init__(self) -> None:
        n = len(self.color_files)
        if len(self.depth_files) != n or len(self.timestamps) != n or (self.poses is not None and len(self.poses) != n):
            raise ValueError(f"{self.path}: inconsistent frame lists")  # a reader bug, not bad input
        if self.undistort and self.distortion is None:
            raise ValueError(f"{self.path}: no distortion coefficients known for this {self.format} recording; "
                             "open it without undistort or give them ('dist k1 k2 p1 p2 k3' in intrinsics.txt, "
                             '"dist": [k1, k2, p1, p2, k3] in intrinsics.json)')
        k = self.intrinsics
        if not (0 <= k.cx <= k.width and 0 <= k.cy <= k.height):
            self.warnings.append(f"the principal point ({k.cx:g}, {k.cy:g}) lies outside the {k.width}x{k.height} "
                                 "image: a calibration of another image size?")

    def __len__(self) -> int:
        return len(self.color_files)

    def __iter__(self) -> Iterator[Frame]:
        return (self.frame(i) for i in range(len(self)))

    @property
    def has_poses(self) -> bool:
        return self.poses is not None and any(p is not None for p in self.poses)

    def frame_files(self, i: int) -> tuple[Path, Path]:
        """(colour file, depth file) of frame i."""
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame {i} out of range (recording has {len(self)} frames)")
        return self.color_files[i], self.depth_files[i]

    def frame(self, i: int) -> Frame:
        """Read frame i: colour HxWx3 uint8 RGB, depth float32 metres (0 = invalid); errors name the file."""
        cpath, dpath = self.frame_files(i)
        color = read_rgb(cpath)
        native = read_depth_raw(dpath)
        h, w = color.shape[:2]
        raw = registered_depth(native, w, h, f"{dpath} (colour {cpath.name})")   # a phone's LiDAR: scaled up
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise ValueError(f"{cpath}: image is {w}x{h} but the intrinsics say "
                             f"{self.intrinsics.width}x{self.intrinsics.height}")
        if self.undistort:
            mx, my = self._undistort_maps
            color = cv2.remap(color, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            raw = cv2.remap(raw, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        pose = None if self.poses is None or self.poses[i] is None else self.poses[i].copy()
        return Frame(index=i, timestamp=float(self.timestamps[i]), color=color, depth=self._metres(raw),
                     intrinsics=self.intrinsics, pose=pose, source=str(cpath),
                     depth_native=None if native is raw or self.undistort else self._metres(native),
                     shutter=self.shutter)

    def _metres(self, raw: np.ndarray) -> np.ndarray:
        """A depth file's values in float32 metres, 0 where they mean no measurement."""
        depth = raw.astype(np.float32) / np.float32(self.intrinsics.depth_scale)
        if self.invalid_depth is not None:
            depth[raw == self.invalid_depth] = 0.0
        return depth

    @cached_property
    def _undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixel maps of cv2.undistort (same K kept); depth, registered to the colour image, uses them too."""
        K = self.intrinsics.K
        size = (self.intrinsics.width, self.intrinsics.height)
        return cv2.initUndistortRectifyMap(K, self.distortion, None, K, size, cv2.CV_32FC1)


def data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, whitespace-separated fields) of each non-blank, non-'#' line of a text file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    text = read_text(path)
    rows = []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            rows.append((lineno, s.split()))
    return rows


def parse_floats(fields: list[str], path: Path, lineno: int, count: int) -> list[float]:
    """Exactly `count` numbers from one line, or a ValueError naming the file and line."""
    if len(fields) != count:
        raise ValueError(f"{path}:{lineno}: expected {count} values, found {len(fields)}")
    try:
        return [float(x) for x in fields]
    except ValueError:
        raise ValueError(f"{path}:{lineno}: not a number in {' '.join(fields)!r}") from None


def read_matrix4(rows: list[tuple[int, list[str]]], path: Path) -> np.ndarray:
    """A checked rigid 4x4 camera-to-world pose from four text rows of four numbers."""
    if len(rows) != 4:
        where = f"{path}:{rows[0][0]}" if rows else str(path)
        raise ValueError(f"{where}: expected 4 rows of a 4x4 matrix, found {len(rows)}")
    T = np.array([parse_floats(fields, path, n, 4) for n, fields in rows])
    return check_pose(T, f"{path}:{rows[0][0]}")


def detect_format(path: Path) -> str:
    """Layout of a recording folder: native (TUM + intrinsics.json), tum, redwood or 7scenes."""
    if (path / "rgb.txt").is_file() or (path / "associations.txt").is_file():
        return "native" if (path / "intrinsics.json").is_file() else "tum"
    if (path / "depth").is_dir() and any((path / d).is_dir() for d in ("color", "image")):
        return "redwood"
    if next(path.glob("frame-*.color.*"), None) is not None:
        return "7scenes"
    raise ValueError(f"{path}: not a recognised recording: expected rgb.txt (TUM/native), color/ and depth/ "
                     "folders (ICL-NUIM/Redwood) or frame-XXXXXX.color.png files (7-Scenes)")


def open_recording(path, fmt: str = "auto", undistort: bool = False, pose_time_offset: float = 0.0) -> Recording:
    """Open a recording folder and check its index files; fmt is 'auto' or one of FORMATS. pose_time_offset:
    seconds added to the frames' times where poses given by time (TUM groundtruth.txt) are looked up."""
    from . import redwood, sevenscenes, tum  # they build Recording objects, so import them here

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such recording folder")
    if not path.is_dir():
        raise ValueError(f"{path}: a recording is a folder, not a file")
    if fmt == "auto":
        fmt = detect_format(path)
    if fmt in ("native", "tum"):
        return tum.open_tum(path, native=fmt == "native", undistort=undistort, pose_time_offset=pose_time_offset)
    if fmt not in FORMATS:
        raise ValueError(f"unknown recording format {fmt!r}: expected auto or one of {', '.join(FORMATS)}")
    if pose_time_offset:
        raise ValueError(f"{path}: recording.pose_time_offset applies to poses given by time (TUM groundtruth.txt); a "
                         f"{fmt} recording gives each frame its own pose")
    return redwood.open_redwood(path, undistort=undistort) if fmt == "redwood" else \
        sevenscenes.open_7scenes(path, undistort=undistort)


def open_configured(cfg) -> Recording:
    """open_recording of a session's [recording] (config.RecordingConfig): its path, format, undistort and
    pose_time_offset."""
    return open_recording(cfg.path, fmt=cfg.format, undistort=cfg.undistort, pose_time_offset=cfg.pose_time_offset)


def iter_frames(recording: Recording, indices: Iterable[int] | None = None,
                on_error: Callable[[int, str], None] | None = None) -> Iterator[Frame]:
    """Frames at `indices` (default all), in order. A frame that cannot be read is passed to
    on_error(index, message) and skipped; without on_error its error is raised."""
    for i in range(len(recording)) if indices is None else indices:
        try:
            frame = recording.frame(i)
        except (ValueError, OSError) as e:
            if on_error is None:
                raise
            on_error(i, str(e))
            continue
        yield frame


class ReadAhead(Ahead[int, Frame]):
    """The frames `indices` of a recording (default all) read on `threads` threads up to `depth` (default 2 * threads)
    frames ahead of the caller, in order (a TUM frame's two PNGs took 11-21 ms to decode, while the frame's own work
    waited for them). A frame that cannot be read is passed to on_error(index, message) in its place and skipped;
    without on_error its error is raised there (as iter_frames). `waited_s`: how long the caller waited for frames;
    close() (and the end of the loop) stops the reading."""

    def __init__(self, recording: Recording, indices: Iterable[int] | None = None,
                 on_error: Callable[[int, str], None] | None = None, threads: int = 1, depth: int | None = None):
        self.recording, self.on_error = recording, on_error
        super().__init__(self._read, range(len(recording)) if indices is None else indices, threads,
                         2 * threads if depth is None else depth, name="photoreg-read")

    def _read(self, i: int) -> Frame | tuple[int, Exception]:
        try:
            return self.recording.frame(i)
        except (ValueError, OSError) as e:
            if self.on_error is None:
                raise
            return i, e

    def __iter__(self) -> Iterator[Frame]:
        for frame in super().__iter__():
            if isinstance(frame, tuple):
                self.on_error(frame[0], str(frame[1]))
                continue
            yield frame


PLAUSIBLE_DEPTH_M = (0.1, 20.0)   # median depths taken for a depth camera's (else: wrong units?)


def depth_units_warning(depth: np.ndarray, depth_scale: float) -> str | None:
    """A warning where the median of the valid depth (metres) is no depth camera's (PLAUSIBLE_DEPTH_M): the depth
    scale wrong, as a rule; None where it is, or where there is no valid depth."""
    valid = depth[np.isfinite(depth) & (depth > 0)]
    if not valid.size:
        return None
    median = float(np.median(valid))
    if PLAUSIBLE_DEPTH_M[0] <= median <= PLAUSIBLE_DEPTH_M[1]:
        return None
    return (f"a median depth of {median:.4g} m is no depth camera's: is the depth scale ({depth_scale:g} units per "
            "metre; float images in metres need 1) right?")


def depth_summary(recording: Recording, samples: int = 5) -> tuple[np.ndarray | None, float, list[tuple[int, str]]]:
    """Valid depth values (metres) and the valid fraction over a few evenly spaced frames, plus their errors."""
    indices = np.unique(np.linspace(0, len(recording) - 1, min(samples, len(recording))).round().astype(int))
    errors: list[tuple[int, str]] = []
    values, total = [], 0
    for frame in iter_frames(recording, indices.tolist(), lambda i, msg: errors.append((i, msg))):
        d = frame.depth
        values.append(d[np.isfinite(d) & (d > 0)])
        total += d.size
    valid = np.concatenate(values) if values else None
    return valid, (valid.size / total if total else 0.0), errors


def info_command(args: argparse.Namespace) -> int:
    """`photoreg info PATH`: what a recording holds and whether it looks sane."""
    rec = open_recording(args.path)
    k = rec.intrinsics
    n = len(rec)
    print(f"recording:   {rec.path}")
    print(f"format:      {rec.format}")
    print(f"frames:      {n}")
    print(f"image size:  {k.width}x{k.height}")
    try:   # depth registered at another resolution is read at the colour's (images.registered_depth)
        dh, dw = read_depth_raw(rec.depth_files[0]).shape[:2] if n else (k.height, k.width)
    except (ValueError, OSError):   # an unreadable first frame: listed below
        dh, dw = k.height, k.width
    if (dw, dh) != (k.width, k.height):
        print(f"depth size:  {dw}x{dh} (first frame), scaled to the colour's")
    print(f"intrinsics:  fx={k.fx:g} fy={k.fy:g} cx={k.cx:g} cy={k.cy:g}")
    if rec.distortion is not None:
        print(f"distortion:  k1 k2 p1 p2 k3 = {' '.join(f'{x:g}' for x in rec.distortion)} (not removed)")
    print(f"depth scale: {k.depth_scale:g} units per metre")
    if rec.shutter is not None:
        print(f"shutter:     {rec.shutter * 1000:g} ms (the objects blurred by the camera's motion over it)")
    with_pose = 0 if rec.poses is None else sum(p is not None for p in rec.poses)
    print(f"poses:       {'yes' if rec.has_poses else 'no'} ({with_pose}/{n} frames)")
    if n:
        span = float(rec.timestamps[-1] - rec.timestamps[0])
        rate = f", {(n - 1) / span:.2f} frames/s" if span > 0 else ""
        print(f"time span:   {span:.3f} s ({rec.timestamps[0]:.6f} .. {rec.timestamps[-1]:.6f}){rate}")
        valid, fraction, errors = depth_summary(rec)
        if valid is not None and valid.size:
            print(f"depth:       min {valid.min():.3f} / median {float(np.median(valid)):.3f} / max "
                  f"{valid.max():.3f} m, {100 * fraction:.1f}% valid (sampled frames)")
            if units := depth_units_warning(valid, k.depth_scale):
                print(f"warning:     {units}")
        elif valid is not None:
            print("depth:       no valid depth in the sampled frames")
        for i, msg in errors:
            print(f"unreadable:  frame {i}: {msg}")
        missing = [(i, p) for i, pair in enumerate(zip(rec.color_files, rec.depth_files)) for p in pair
                   if not Path(p).is_file()]   # of every frame: the depth above reads a few
        if missing:
            print(f"missing:     {len(missing)} listed file(s) of {len({i for i, _ in missing})} frame(s): "
                  + ", ".join(f"frame {i} {p}" for i, p in missing[:3]) + (", ..." if len(missing) > 3 else ""))
    for note in rec.notes:
        print(f"note:        {note}")
    for warning in rec.warnings:
        print(f"warning:     {warning}")
    return 0
