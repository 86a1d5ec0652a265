"""CUDA correctness: the same frames through the pipeline on CPU and on CUDA must agree.

usage: python benchmarks/cuda_check.py RECORDING [FRAMES] [HISTORY] [--censored]   (prints one JSON object; HISTORY:
lighting.history, default the session's; --censored: lighting.censored, saturated pixels kept)
Compares, per frame, the SH estimate (relative difference), the dominant direction (degrees),
and the Warp ray-cast depth of the last frame (fraction of pixels within one voxel).
"""
import json
import sys

import numpy as np

from photoreg.config import Session
from photoreg.io.recording import iter_frames, open_recording
from photoreg.kernels.raycast import raycast_surface
from photoreg.pipeline import Pipeline


def run(device: str, rec, frames, history: int | None, censored: bool):
    s = Session()
    s.recording.path = str(rec.path)
    s.device, s.lighting.censored = device, censored
    if history is not None:
        s.lighting.history = history
    pipe = Pipeline(s, rec.intrinsics)
    out = [pipe.process(f) for f in iter_frames(rec, frames)]
    last = rec.frame(frames[-1])
    maps = raycast_surface(pipe.volume.dense_grid(), rec.intrinsics, last.pose, 0.1, 4.0)
    return out, maps, str(pipe.volume.o3d_device)


def main() -> None:
    censored = "--censored" in sys.argv
    args = [a for a in sys.argv[1:] if a != "--censored"]
    rec = open_recording(args[0])
    frames = list(range(int(args[1]) if len(args) > 1 else 4))
    history = int(args[2]) if len(args) > 2 else None
    cpu, maps_cpu, _ = run("cpu", rec, frames, history, censored)
    gpu, maps_gpu, fusion = run("cuda", rec, frames, history, censored)
    rel = [float(np.linalg.norm(a.lighting.sh - b.lighting.sh) / np.linalg.norm(a.lighting.sh)) for a, b in zip(cpu, gpu)]
    ang = [float(np.degrees(np.arccos(np.clip(a.dominant_direction @ b.dominant_direction, -1, 1))))
           for a, b in zip(cpu, gpu)]
    both = maps_cpu.valid & maps_gpu.valid
    agree = float(np.mean(np.abs(maps_cpu.depth[both] - maps_gpu.depth[both]) < 0.01))
    print(json.dumps({"frames": len(frames), "history": history, "censored": censored, "fusion_on_cuda": fusion,
                      "sh_rel_diff_max": max(rel), "direction_diff_deg_max": max(ang), "raycast_depth_within_1cm": agree,
                      "valid_cpu": int(maps_cpu.valid.sum()), "valid_gpu": int(maps_gpu.valid.sum())}))


if __name__ == "__main__":
    main()
