"""A light moved mid-recording: how many frames the traced light (diagnostics.sun.direction, where shadows fall)
takes to follow it.

A static camera over the generated tabletop: NA frames under its sun at azimuth 0 (yaw 0), then NB frames of the
same view with the sun turned 120 degrees (yaw 120); both recordings are made with `photoreg synth` when missing.
Prints per frame whether the temporal filter detected a change and the traced light's angle to each sun, and the
first frame after the switch from which the traced light stays within 10 degrees of the new sun.

usage: python benchmarks/light_switch.py [--dir /tmp/light_switch] [--before 16] [--after 16]
"""
from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np

from photoreg.bench.score import true_light
from photoreg.config import Session
from photoreg.io.recording import open_recording
from photoreg.pipeline import Pipeline

FRAMES = 8   # frames of each recording, repeated (the camera is static)


def recording(folder: Path, yaw: int) -> Path:
    """The static tabletop at sun yaw `yaw` (made once)."""
    out = folder / f"yaw{yaw}"
    if not (out / "lighting_gt.json").is_file():
        subprocess.run([sys.executable, "-m", "photoreg", "synth", "tabletop", "--out", str(out), "--frames",
                        str(FRAMES), "--size", "320x240", "--spp", "8", "--camera", "static", "--insert-frames",
                        "none", "--yaw", str(yaw)], check=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", default="/tmp/light_switch", help="where the two recordings are made (kept)")
    ap.add_argument("--before", type=int, default=16, help="frames under the first sun")
    ap.add_argument("--after", type=int, default=16, help="frames under the turned sun")
    args = ap.parse_args()
    first, turned = (recording(Path(args.dir), yaw) for yaw in (0, 120))
    suns = [np.asarray(true_light(folder)[1]["direction"]) for folder in (first, turned)]
    recs = [open_recording(first), open_recording(turned)]
    s = Session(device="cpu")
    s.lighting.stride, s.lighting.rays = 8, 16
    pipe = Pipeline(s, recs[0].intrinsics)
    followed = None
    try:
        for i in range(args.before + args.after):
            which = int(i >= args.before)
            frame = dataclasses.replace(recs[which].frame(i % FRAMES), index=i, timestamp=i / 30.0)
            diag = pipe.process(frame).diagnostics
            angles = ["-" if not diag.sun else
                      f"{np.degrees(np.arccos(np.clip(np.asarray(diag.sun['direction']) @ d, -1, 1))):5.1f}"
                      for d in suns]
            print(f"frame {i:3d} {'change' if diag.change_detected else '      '} light to the first sun "
                  f"{angles[0]} deg, to the turned sun {angles[1]} deg")
            near = angles[1] != "-" and float(angles[1]) < 10
            if which and near and followed is None:
                followed = i
            elif which and not near:
                followed = None
    finally:
        pipe.close()
    print("followed the turned sun from frame", "never" if followed is None else
          f"{followed}, the turned sun's frame {followed - args.before + 1} (counted from 1)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
