"""Per-stage timings of fusion, dense export, surface ray cast and transfer on the current device.

Scene: photoreg.synth.analytic.box_room() (2 x 2 x 2 m), 640x480 depth, 1 cm voxels (block 16),
ray cast at stride 4 (160x120 sample points), 64 rays per hemisphere, B = 3, 0.5 m rays.
On the CPU it also times the ray cast and the transfer with 1 thread against --threads threads
(photoreg.kernels.launch), interleaved in one run so that both see the same machine load.
Run: python benchmarks/kernels_cpu.py [--device cpu|cuda] [--frames N] [--repeats N] [--threads N]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("PHOTOREG_WARP_CACHE", str(REPO / ".cache" / "warp"))

import numpy as np  # noqa: E402

from photoreg.device import init_warp, resolve_device  # noqa: E402
from photoreg.kernels.raycast import raycast_surface  # noqa: E402
from photoreg.kernels.transfer import make_direction_set, radiance_transfer  # noqa: E402
from photoreg.recon.fusion import FusionConfig, TSDFVolume  # noqa: E402
from photoreg.synth.analytic import box_room  # noqa: E402
from photoreg.synth.cameras import default_intrinsics, look_at  # noqa: E402


def timed(fn, repeats: int) -> tuple[list[float], object]:
    """Wall times in ms of `repeats` calls (the device synchronised after each), and the last result."""
    wp = init_warp()
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        wp.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    return times, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=8, help="frames fused before timing the other stages")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=os.cpu_count(), help="CPU threads compared with 1")
    args = ap.parse_args(argv)
    device = resolve_device(args.device)

    intr = default_intrinsics(640, 480, hfov_deg=70.0)
    scene = box_room()
    rng = np.random.default_rng(0)
    poses = [look_at([-0.6, 0.0, 1.4], [0.8, 0.1, 0.1])]
    while len(poses) < args.frames + 1:
        eye, target = rng.uniform([-0.7, -0.7, 0.8], [0.7, 0.7, 1.6]), rng.uniform([-0.9, -0.9, 0.0], [0.9, 0.9, 1.0])
        if np.linalg.norm(target - eye) > 0.8:
            poses.append(look_at(eye, target))
    depths = [scene.render_depth(intr, p)[0] for p in poses]

    cfg = FusionConfig(voxel_size=0.01, block_resolution=16)
    vol = TSDFVolume(cfg, device)
    t_int = [timed(lambda: vol.integrate(d, intr, p), 1)[0][0] for d, p in zip(depths[1:], poses[1:])]
    t_first_export, grid = timed(vol.dense_grid, 1)  # allocates the brick (and compiles on a cold cache)
    t_export = []
    for _ in range(args.repeats):  # per-frame export: the blocks of one more integrated frame
        vol.integrate(depths[0], intr, poses[0])
        ms, grid = timed(vol.dense_grid, 1)
        t_export += ms
    view = poses[0]
    raycast_surface(grid, intr, view, 0.1, 4.0, stride=4)  # compile / load
    t_rc4, maps = timed(lambda: raycast_surface(grid, intr, view, 0.1, 4.0, stride=4), args.repeats)
    t_rc1, _ = timed(lambda: raycast_surface(grid, intr, view, 0.1, 4.0), args.repeats)
    t_o3d, _ = timed(lambda: vol.raycast_open3d(intr, view), args.repeats)

    dirs, Y = make_direction_set(64, 3, seed=0)
    radiance_transfer(grid, maps.vertex_wp, maps.normal_wp, dirs, Y, offset=cfg.voxel_size, ray_length=0.5)
    t_tr, res = timed(lambda: radiance_transfer(grid, maps.vertex_wp, maps.normal_wp, dirs, Y,
                                                offset=cfg.voxel_size, ray_length=0.5), args.repeats)

    valid = maps.valid.ravel()
    print(f"device {device}; brick {grid.shape} voxels ({np.prod(grid.shape) * 4 / 2**20:.0f} MB), "
          f"{vol.vbg.hashmap().size()} blocks; {valid.sum()}/{valid.size} valid samples; "
          f"mean visible fraction {res.visible_fraction[valid].mean():.2f}; load average {os.getloadavg()[0]:.1f}")
    rows = [
        ("integrate 640x480 (Open3D)", t_int),
        ("export, first (allocate brick + scatter)", t_first_export),
        ("export, per frame (blocks of one frame)", t_export),
        ("raycast Warp, stride 4 (160x120)", t_rc4),
        ("raycast Warp, 640x480", t_rc1),
        ("raycast Open3D, 640x480 (reference)", t_o3d),
        ("transfer, 160x120 x 64 rays, B=3, 0.5 m", t_tr),
    ]
    print(f"{'stage':45s} {'median':>9s} {'min':>9s}  (ms, {args.repeats} runs)")
    for name, ms in rows:
        print(f"{name:45s} {statistics.median(ms):9.1f} {min(ms):9.1f}")
    if device == "cpu":
        compare_threads(grid, intr, view, maps, dirs, Y, cfg.voxel_size, args.threads, args.repeats)
    return 0


def compare_threads(grid, intr, view, maps, dirs, Y, voxel, threads: int, repeats: int) -> None:
    """Ray cast and transfer with 1 thread and with `threads`, alternating; median times and their ratio."""
    cases = {
        "raycast Warp, 640x480": lambda n: raycast_surface(grid, intr, view, 0.1, 4.0, threads=n),
        "transfer, 160x120 x 64 rays": lambda n: radiance_transfer(grid, maps.vertex_wp, maps.normal_wp, dirs, Y,
                                                                    offset=voxel, ray_length=0.5, threads=n),
    }
    print(f"\nthreads: 1 against {threads} (alternating, {repeats} runs each; load average {os.getloadavg()[0]:.1f})")
    for name, fn in cases.items():
        t = {1: [], threads: []}
        for _ in range(repeats):
            for n in t:
                t[n] += timed(lambda: fn(n), 1)[0]
        one, many = statistics.median(t[1]), statistics.median(t[threads])
        print(f"{name:45s} 1 thread {one:8.1f} ms   {threads} threads {many:8.1f} ms   speed-up {one / many:.2f}x")


if __name__ == "__main__":
    raise SystemExit(main())
