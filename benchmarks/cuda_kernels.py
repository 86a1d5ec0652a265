"""CUDA correctness and speed of the ray kernels on an analytic grid: needs Warp and numpy only (no Open3D).

usage: python benchmarks/cuda_kernels.py [--points N] [--rays R] [--json FILE]
A room-sized brick (1 cm voxels) holding a floor, two walls and a box is built from closed-form signed
distances; random surface-like points with normals over its floor and box march the same direction set on
the CPU and on CUDA through radiance_transfer (with hit distances and, as the virtual layer, the box alone) and
observed_bounce (a luminance map over the walls). Reports the largest CPU/CUDA differences of each output and,
on CUDA, the milliseconds of each call (mean of 5 after a warm-up). benchmarks/cuda_check.py checks the whole
pipeline (it needs Open3D's CUDA build).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from photoreg.device import init_warp  # noqa: E402
from photoreg.kernels.transfer import make_direction_set, observed_bounce, radiance_transfer  # noqa: E402
from photoreg.lighting.exposure import ExposureTracker  # noqa: E402
from photoreg.render.scene import sdf_grid  # noqa: E402

VOXEL, TRUNC = 0.01, 0.04


def room(shape=(256, 256, 128)):
    """(real grid, box-only grid): floor z = 0, walls x = 2.2 and y = 2.2, a 0.4 x 0.3 x 0.25 m box at (1, 1)."""
    origin = np.array([-0.3, -0.3, -0.2])
    x, y, z = (origin[a] + np.arange(shape[a]) * VOXEL for a in range(3))
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    q = np.abs(np.stack([X - 1.0, Y - 1.0, Z - 0.125])) - np.array([0.2, 0.15, 0.125])[:, None, None, None]
    box = np.linalg.norm(np.maximum(q, 0.0), axis=0) + np.minimum(q.max(axis=0), 0.0)
    real = np.minimum.reduce([Z, 2.2 - X, 2.2 - Y, box])
    return sdf_grid(real, origin, VOXEL, TRUNC, "cpu"), sdf_grid(box, origin, VOXEL, TRUNC, "cpu")


def samples(n: int, seed: int = 0):
    """Points on the floor (normal +z) and on the box's top (normal +z) and side (normal -x)."""
    rng = np.random.default_rng(seed)
    k = rng.integers(0, 3, n)
    p = np.column_stack([rng.uniform(0.0, 2.1, n), rng.uniform(0.0, 2.1, n), np.zeros(n)])
    top = k == 1
    p[top] = np.column_stack([rng.uniform(0.8, 1.2, top.sum()), rng.uniform(0.85, 1.15, top.sum()),
                              np.full(top.sum(), 0.25)])
    side = k == 2
    p[side] = np.column_stack([np.full(side.sum(), 0.8), rng.uniform(0.85, 1.15, side.sum()),
                               rng.uniform(0.02, 0.23, side.sum())])
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    nrm[side] = [-1.0, 0.0, 0.0]
    return p.astype(np.float32), nrm.astype(np.float32)


def on(grid, device: str):
    """The grid's arrays copied to `device` (a DenseGrid is device-bound)."""
    wp = init_warp()
    return dataclasses.replace(grid, sdf=wp.clone(grid.sdf, device=device), empty=wp.clone(grid.empty, device=device))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=8000)
    ap.add_argument("--rays", type=int, default=64)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    wp = init_warp()
    real, box = room()
    points, normals = samples(args.points)
    dirs, Y = make_direction_set(args.rays, 4, seed=0)
    walls = ExposureTracker(cell=2 * VOXEL)
    g = np.arange(0.0, 2.2, 0.01)
    yz = np.stack(np.meshgrid(g, g[:120]), -1).reshape(-1, 2)
    for side in (2.19, 2.21):   # both cells that the wall planes separate, as noisy samples of a wall fill them
        walls.update(np.column_stack([np.full(len(yz), side), yz]), np.full((len(yz), 3), 0.7))
        walls.update(np.column_stack([yz[:, 0], np.full(len(yz), side), yz[:, 1]]), np.full((len(yz), 3), 0.3))
    offset, length = 1.5 * VOXEL, 1.0
    out, ms = {}, {}
    for device in ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else []):
        r, b = (real, box) if device == "cpu" else (on(real, device), on(box, device))

        def transfer():
            return radiance_transfer(r, points, normals, dirs, Y, offset, length, device=device, virtual=b,
                                     hit_distances=True)

        def bounce(tr):
            return observed_bounce(tr, points, normals, dirs, offset, walls.cell, *walls.map[:2])

        tr = transfer()
        cols = bounce(tr)
        out[device] = {"transfer": tr.transfer, "transfer_rv": tr.transfer_rv, "occlusion": tr.occlusion_wp.numpy(),
                       "hits": tr.hit_distance_wp.numpy(), "bounce": cols}
        if device != "cpu":
            for name, fn in (("transfer", transfer), ("observed_bounce", lambda: bounce(tr))):
                t0 = time.perf_counter()
                for _ in range(5):
                    fn()
                wp.synchronize_device(device)
                ms[name] = round((time.perf_counter() - t0) * 200.0, 3)
    res = {"points": args.points, "directions": int(len(dirs)), "voxel": VOXEL, "ray_length": length,
           "blocked_share": float((out["cpu"]["hits"] >= 0).mean()),
           "points_seeing_a_wall": float((out["cpu"]["bounce"][:, 0] > 0).mean())}
    if "cuda:0" in out:
        c, g_ = out["cpu"], out["cuda:0"]
        hit_both = (c["hits"] >= 0) & (g_["hits"] >= 0)
        res.update({
            "device": wp.get_device("cuda:0").name, "warp": wp.__version__,
            "transfer_max_abs_diff": float(np.abs(c["transfer"] - g_["transfer"]).max()),
            "transfer_rv_max_abs_diff": float(np.abs(c["transfer_rv"] - g_["transfer_rv"]).max()),
            "occlusion_flags_differ": float((c["occlusion"] != g_["occlusion"]).mean()),
            "hit_blocked_differ": float(((c["hits"] >= 0) != (g_["hits"] >= 0)).mean()),
            "hit_distance_max_abs_diff_m": float(np.abs(c["hits"] - g_["hits"])[hit_both].max()),
            "bounce_max_abs_diff": float(np.abs(c["bounce"] - g_["bounce"]).max()),
            "bounce_scale": float(np.abs(c["bounce"]).max()), "cuda_ms": ms})
    print(json.dumps(res, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
