"""Ablations of benchmarks/lighting_accuracy.py over several random seeds: one seed's median over 12 frames moves
by 0.01-0.02 in si-RMSE with the samples drawn, so a change is compared on the same recordings under seeds 1..n of
the solve's sample draws, the history's and the transfer's direction set (its random rotation).

usage: python benchmarks/lighting_seeds.py --synth-dir /tmp/bench [--seeds 1,2,3] [--changes "defaults;stride 2"]
       [--recordings tabletop,tabletop_static_90:90] (folders in --synth-dir instead of the list below, 12 frames of
       each unless ':FRAMES' follows its name)
(the recordings of lighting_accuracy.py's tables, made there; prints per recording the mean over seeds of direction
degrees, irradiance si-RMSE over the upper hemisphere (with its range) and flicker, then the means)
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import lighting_accuracy as la  # noqa: E402  (puts the repository first on the path)

from photoreg.bench.score import load_gt  # noqa: E402

RECORDINGS = [("tabletop", "tabletop", 12), ("tabletop, sun azimuth 150", "tabletop_sun_azimuth_150", 12),
              ("tabletop, sun azimuth 270", "tabletop_sun_azimuth_270", 12),
              ("tabletop, handheld camera", "tabletop_handheld_camera", 12), ("tabletop, 640x480", "tabletop_640x480", 12),
              ("coloured", "coloured", 12), ("coloured, sun azimuth 150", "coloured_sun_azimuth_150", 12),
              ("corner", "corner", 12), ("tabletop, 40 frames", "tabletop_40_frames", 40)]


def _recording(spec: str) -> tuple[str, str, int]:
    """(name, folder, frames) of a --recordings entry 'NAME' or 'NAME:FRAMES'."""
    folder, _, frames = spec.partition(":")
    if frames and not (frames.isdigit() and int(frames) > 1):
        raise SystemExit(f"--recordings {spec!r}: FRAMES must be a whole number above 1")
    return folder, folder, int(frames) if frames else 12


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--synth-dir", default="/tmp/photoreg_bench")
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--changes", default="defaults;stride 2;sample_box 3",
                    help="names of lighting_accuracy.py's ABLATIONS, separated by ';'")
    ap.add_argument("--recordings", help="comma-separated folders in --synth-dir, each 'NAME' (12 frames) or "
                                         "'NAME:FRAMES' (default: RECORDINGS)")
    a = ap.parse_args()
    recordings = [_recording(r) for r in a.recordings.split(",")] if a.recordings else RECORDINGS
    seeds = [int(x) for x in a.seeds.split(",")]
    changes = [c.strip() for c in a.changes.split(";")]
    unknown = [c for c in changes if c not in la.ABLATIONS]
    if unknown:
        ap.error(f"unknown changes {unknown}; known: {sorted(la.ABLATIONS)}")
    missing = [f for _, f, _ in recordings if not (Path(a.synth_dir) / f / "lighting_gt.json").is_file()]
    if missing:
        ap.error(f"{a.synth_dir}: no {missing} (make them with benchmarks/lighting_accuracy.py --ablations)")
    res = {}
    for name, folder, frames in recordings:
        path = Path(a.synth_dir) / folder
        gt = load_gt(path)
        for change in changes:
            rows = [la.summary(la.run(path, la.ABLATIONS[change], frames, False, seed), gt) for seed in seeds]
            res[name, change] = np.array([[r["direction_deg"], r["irradiance_si_rmse_upper"], r["flicker"]]
                                          for r in rows])
            v = res[name, change]
            print(f"{name} | {change}: {v[:, 0].mean():.1f} deg, si-RMSE {v[:, 1].mean():.3f} "
                  f"({v[:, 1].min():.3f}-{v[:, 1].max():.3f}), flicker {v[:, 2].mean():.4f}", flush=True)
    for change in changes:
        v = np.concatenate([res[name, change] for name, _, _ in recordings])
        print(f"mean | {change}: {v[:, 0].mean():.1f} deg, si-RMSE {v[:, 1].mean():.3f}, flicker {v[:, 2].mean():.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
