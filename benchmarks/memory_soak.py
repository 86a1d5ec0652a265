"""Memory over a long session: the demo's 40 frames played forward and back (0..39, 38..1, ...) for N frames with
increasing index and timestamp, through one Pipeline; the process's resident memory every 50 frames, as JSON lines.

    python benchmarks/memory_soak.py default|track|async|object N
    python benchmarks/memory_soak.py recording N DIR   # the same N frames as a recording for `photoreg run`

default/track/async: stride 8, 16 rays, 3 bands (track: the camera tracked, no recorded poses; async:
lighting.asynchronous); object: the demo session as it is, with its object. `recording` writes DIR: links to the
demo's images, their lists and poses, its intrinsics, object and session (`photoreg run DIR/session.toml` then reads
it). benchmarks/memory.md holds the figures.
"""
from __future__ import annotations

import dataclasses
import gc
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from photoreg.config import Session, load_session
from photoreg.io.poses import format_tum_line
from photoreg.io.recording import open_configured, open_recording
from photoreg.pipeline import Pipeline

DEMO = Path(__file__).resolve().parents[1] / "data" / "demo"
CONFIGS = ("default", "track", "async", "object")


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1024.0 for line in f if line.startswith("VmRSS"))


def session(config: str) -> Session:
    if config == "object":
        s = load_session(DEMO / "session.toml")
    else:
        s = Session()
        s.recording.path = str(DEMO)
        s.lighting.stride, s.lighting.rays, s.lighting.bands = 8, 16, 3
    s.device = "cpu"
    s.recording.use_poses = config != "track"
    s.lighting.asynchronous = config == "async"
    return s


def played(n: int, frames: int) -> list[int]:
    """The frame of `frames` shown at each of n steps: forward and back, so the camera's motion stays continuous."""
    order = list(range(frames)) + list(range(frames - 2, 0, -1))
    return [order[k % len(order)] for k in range(n)]


def write_recording(n: int, out: Path) -> None:
    rec = open_recording(DEMO)
    dt = float(np.median(np.diff(rec.timestamps)))
    lists = {"rgb": ["# timestamp filename"], "depth": ["# timestamp filename"]}
    poses = ["# timestamp tx ty tz qx qy qz qw"]
    for kind in lists:
        (out / kind).mkdir(parents=True)
    for k, i in enumerate(played(n, len(rec))):
        for kind, files in (("rgb", rec.color_files), ("depth", rec.depth_files)):
            (out / kind / f"{k:06d}.png").symlink_to(Path(files[i]).resolve())
            lists[kind].append(f"{k * dt:.6f} {kind}/{k:06d}.png")
        poses.append(format_tum_line(k * dt, rec.poses[i]))
    for kind, lines in lists.items():
        (out / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    (out / "groundtruth.txt").write_text("\n".join(poses) + "\n")
    for name in ("intrinsics.json", "object.obj", "session.toml"):
        shutil.copy(DEMO / name, out / name)


def main() -> None:
    config, n = sys.argv[1], int(sys.argv[2])
    if config == "recording":
        write_recording(n, Path(sys.argv[3]))
        return
    if config not in CONFIGS:
        raise SystemExit(f"config: one of {', '.join(CONFIGS)}, got {config!r}")
    s = session(config)
    rec = open_configured(s.recording)
    frames = [rec.frame(i) if s.recording.use_poses else dataclasses.replace(rec.frame(i), pose=None)
              for i in range(len(rec))]
    dt = float(np.median(np.diff(rec.timestamps)))
    pipe = Pipeline(s, rec.intrinsics)
    t0 = time.perf_counter()
    try:
        for k, i in enumerate(played(n, len(frames))):
            frame = dataclasses.replace(frames[i], index=k, timestamp=k * dt)
            pipe.process(frame)
            if k == 0 or (k + 1) % 50 == 0:
                gc.collect()
                row = {"config": config, "frame": k + 1, "rss_mb": round(rss_mb(), 1),
                       "s": round(time.perf_counter() - t0, 1),
                       "history_rows": None if pipe.history is None else len(pipe.history),
                       "tracking_failures_listed": None if pipe.tracker is None else len(pipe.tracker.stats.failures)}
                print(json.dumps(row), flush=True)
    finally:
        pipe.close()


if __name__ == "__main__":
    main()
