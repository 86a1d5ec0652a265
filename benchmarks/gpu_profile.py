"""Where the per-frame time goes inside the pipeline's 'raycast' stage on one device, and GPU memory of a
room-sized volume (issue 9). Run on the GPU machine:

    python3 benchmarks/gpu_profile.py RECORDING --device cuda --json OUT.json

1. Fuses the first 10 frames, then times (synchronised, median of 10) the pieces of the fuse and raycast
   stages: integrate alone and integrate + the TSDF -> dense Warp brick export (dense_grid), the ray cast
   at stride 1 and 4 with its maps' device -> host copies, and those copies alone.
2. Room memory: a VoxelBlockGrid at 1 cm voxels filled with synthetic depth frames of a 4 x 4 x 3 m
   box room seen from its centre (every wall, floor and ceiling observed), then its dense Warp brick;
   device memory in use (cudaMemGetInfo through Warp) before and after each.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np


def _timed(fn, wp, device, n=10) -> float:
    fn()
    wp.synchronize_device(device)
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        out.append((time.perf_counter() - t0) * 1000.0)
    return round(statistics.median(out), 3)


def _used_mib(wp, device) -> float:
    d = wp.get_device(device)
    return round((d.total_memory - d.free_memory) / 2**20, 1) if d.is_cuda else float("nan")


def room_depth(intr, pose, size=(4.0, 4.0, 3.0)) -> np.ndarray:
    """Depth (metres) of a camera inside an axis-aligned box room [0,sx]x[0,sy]x[0,sz] (world z up)."""
    h, w = intr.height, intr.width
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1) @ pose[:3, :3].T
    o = pose[:3, 3]
    t = np.full((h, w), np.inf)
    for k, s in enumerate(size):
        with np.errstate(divide="ignore", invalid="ignore"):
            for wall in (0.0, s):
                tk = (wall - o[k]) / rays[..., k]
                t = np.where((tk > 0) & (tk < t), tk, t)
    return (t * 1.0).astype(np.float32)  # rays have z = 1 in the camera: t is the camera depth


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("recording")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--json")
    a = ap.parse_args()
    from photoreg.device import init_warp, resolve_device
    from photoreg.io.recording import iter_frames, open_recording
    from photoreg.kernels.raycast import raycast_surface
    from photoreg.recon.fusion import FusionConfig, TSDFVolume
    from photoreg.synth.cameras import look_at
    from photoreg.types import Intrinsics

    wp = init_warp()
    a.device = resolve_device(a.device)
    res: dict = {"device": wp.get_device(a.device).name}
    rec = open_recording(a.recording)
    vol = TSDFVolume(FusionConfig(), device=a.device)
    frames = list(iter_frames(rec, range(10)))
    for f in frames:
        vol.integrate(f.depth, rec.intrinsics, f.pose)
    pose = frames[-1].pose
    last = frames[-1]
    res["integrate_ms"] = _timed(lambda: vol.integrate(last.depth, rec.intrinsics, pose), wp, a.device)
    res["integrate_and_dense_grid_ms"] = _timed(
        lambda: (vol.integrate(last.depth, rec.intrinsics, pose), vol.dense_grid()), wp, a.device)
    grid = vol.dense_grid()
    res["brick_voxels"] = int(np.prod(grid.sdf.shape))
    for s in (1, 4):
        res[f"raycast_s{s}_total_ms"] = _timed(lambda: raycast_surface(grid, rec.intrinsics, pose, 0.1, 4.0, stride=s),
                                               wp, a.device)
        maps = raycast_surface(grid, rec.intrinsics, pose, 0.1, 4.0, stride=s)
        res[f"raycast_s{s}_host_copy_ms"] = _timed(lambda: (maps.depth_wp.numpy(), maps.vertex_wp.numpy(),
                                                            maps.normal_wp.numpy()), wp, a.device)
    print(json.dumps(res, indent=1), flush=True)

    # 4 x 4 x 3 m room at 1 cm
    intr = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
    before = _used_mib(wp, a.device)
    room = TSDFVolume(FusionConfig(voxel_size=0.01, depth_max=6.0, max_dense_voxels=1 << 30), device=a.device)
    centre = np.array([2.0, 2.0, 1.5])
    for k, yaw in enumerate(np.linspace(0, 2 * np.pi, 24, endpoint=False)):
        for pitch in (-0.9, 0.0, 0.9):
            target = centre + np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
            p = look_at(centre, target, up=(0, 0, 1))
            room.integrate(room_depth(intr, p), intr, p)
    wp.synchronize_device(a.device)
    res["room_blocks"] = int(room.vbg.hashmap().size())
    res["room_vbg_mib"] = round(_used_mib(wp, a.device) - before, 1)
    g = room.dense_grid()
    wp.synchronize_device(a.device)
    res["room_dense_shape"] = list(g.sdf.shape)
    res["room_total_mib"] = round(_used_mib(wp, a.device) - before, 1)
    print(json.dumps(res, indent=1))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
