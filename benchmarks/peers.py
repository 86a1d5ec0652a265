"""Side-by-side peers on one fused volume and one view (issue 9), timed in the same run:

1. surface ray cast: Warp (photoreg.kernels.raycast) against Open3D's VoxelBlockGrid.ray_cast
   (TSDFVolume.raycast_open3d) at full resolution: time, coverage, depth and normal agreement;
2. visibility: Warp's SDF-marched occlusion pass (photoreg.kernels.transfer, the R_TR rays) against
   Embree (Open3D RaycastingScene.test_occlusions) on the marching-cubes mesh extracted from the same
   TSDF, for the same ray set (sample points of a strided ray cast, hemisphere directions, origin offset
   along the normal, same length): time, per-ray agreement and agreement of the per-point visible fraction.

Run: python benchmarks/peers.py [RECORDING] [--frames N] [--device cpu|cuda] [--threads N] [--stride N]
     [--rays N] [--voxel-size M] [--repeats N] [--json FILE]
RECORDING defaults to $PHOTOREG_DATA/recordings/tum_fr1_rpy (else ../shared/data/...).
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

from photoreg.bench.speed import device_name  # noqa: E402
from photoreg.device import init_warp, resolve_device  # noqa: E402
from photoreg.io.atomic import write_json  # noqa: E402
from photoreg.io.recording import iter_frames, open_recording  # noqa: E402
from photoreg.kernels.launch import cpu_threads, set_cpu_threads  # noqa: E402
from photoreg.kernels.raycast import raycast_surface  # noqa: E402
from photoreg.kernels.transfer import REAL, make_direction_set, radiance_transfer  # noqa: E402
from photoreg.recon.fusion import FusionConfig, TSDFVolume  # noqa: E402

wp = init_warp()


def timed(fn, repeats: int) -> tuple[float, object]:
    """Median wall ms of `repeats` calls after one untimed call (device synchronised), and the last result."""
    out = fn()
    wp.synchronize()
    ms = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        wp.synchronize()
        ms.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ms), out


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def default_recording() -> Path:
    data = Path(os.environ.get("PHOTOREG_DATA", REPO.parent / "shared" / "data"))
    return data / "recordings" / "tum_fr1_rpy"


def raycast_peers(vol: TSDFVolume, grid, intr, view, sensor: np.ndarray, voxel: float, repeats: int) -> dict:
    """Both ray casts of the view; `sensor` (the view's own depth map) is a third reference for depth."""
    rc = vol.cfg
    t_warp, maps = timed(lambda: raycast_surface(grid, intr, view, rc.depth_min, rc.depth_max), repeats)
    t_o3d, (d_o3d, n_o3d) = timed(lambda: vol.raycast_open3d(intr, view), repeats)
    vw, vo = maps.valid, d_o3d > 0
    both = vw & vo
    dd = np.abs(maps.depth - d_o3d)[both]
    ang = angle_deg(maps.normal, n_o3d)[both]
    all3 = both & np.isfinite(sensor) & (sensor > 0)
    return {"warp_ms": t_warp, "open3d_ms": t_o3d, "warp_valid": float(vw.mean()), "open3d_valid": float(vo.mean()),
            "valid_in_both_of_either": float(both.sum() / max((vw | vo).sum(), 1)),
            "depth_diff_median_mm": float(np.median(dd) * 1e3), "depth_diff_p95_mm": float(np.percentile(dd, 95) * 1e3),
            "depth_within_1_voxel": float((dd < voxel).mean()), "normal_angle_median_deg": float(np.median(ang)),
            "normal_within_5deg": float((ang < 5.0).mean()),
            "warp_vs_sensor_median_mm": float(np.median(np.abs(maps.depth - sensor)[all3]) * 1e3),
            "open3d_vs_sensor_median_mm": float(np.median(np.abs(d_o3d - sensor)[all3]) * 1e3)}


def visibility_peers(vol: TSDFVolume, grid, intr, view, stride: int, rays: int, offset: float, length: float,
                     repeats: int) -> dict:
    import open3d as o3d

    rc = vol.cfg
    maps = raycast_surface(grid, intr, view, rc.depth_min, rc.depth_max, stride=stride)
    points, normals = maps.vertex[maps.valid], maps.normal[maps.valid]
    dirs, Y = make_direction_set(rays, 3, seed=0)
    t_warp, tr = timed(lambda: radiance_transfer(grid, points, normals, dirs, Y, offset=offset, ray_length=length),
                       repeats)
    warp_blocked = (tr.occlusion_wp.numpy() & int(REAL)) != 0              # (N, D)

    t0 = time.perf_counter()
    mesh = vol.extract_mesh().cpu()
    t_extract = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh.vertex.positions.to(o3d.core.float32), mesh.triangle.indices.to(o3d.core.uint32))
    hemi = normals @ dirs.T > 0                                             # the pairs Warp marches
    pi, di = np.nonzero(hemi)
    origins = points[pi] + normals[pi] * offset
    ray_t = o3d.core.Tensor(np.hstack([origins, dirs[di]]).astype(np.float32))
    scene.test_occlusions(ray_t, tnear=0.0, tfar=length)                    # builds the BVH (first query)
    t_build = (time.perf_counter() - t0) * 1e3
    t_embree, occ = timed(lambda: scene.test_occlusions(ray_t, tnear=0.0, tfar=length).numpy(), repeats)
    embree_blocked = np.zeros_like(warp_blocked)
    embree_blocked[pi, di] = occ.astype(bool)

    frac_w = tr.visible_fraction
    frac_e = 1.0 - embree_blocked.sum(1) / np.maximum(hemi.sum(1), 1)
    diff = np.abs(frac_w - frac_e)
    agree = warp_blocked[pi, di] == embree_blocked[pi, di]
    return {"points": int(len(points)), "rays": int(len(pi)), "warp_ms": t_warp, "embree_ms": t_embree,
            "embree_bvh_ms": t_build, "mesh_extract_ms": t_extract,
            "mesh_triangles": int(mesh.triangle.indices.shape[0]),
            "ray_agreement": float(agree.mean()), "warp_blocked_share": float(warp_blocked[pi, di].mean()),
            "embree_blocked_share": float(embree_blocked[pi, di].mean()),
            "visible_fraction_mean_warp": float(frac_w.mean()), "visible_fraction_mean_embree": float(frac_e.mean()),
            "visible_fraction_abs_diff_median": float(np.median(diff)),
            "visible_fraction_abs_diff_p95": float(np.percentile(diff, 95)),
            "visible_fraction_correlation": float(np.corrcoef(frac_w, frac_e)[0, 1])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", nargs="?", default=str(default_recording()))
    ap.add_argument("--frames", type=int, default=10, help="frames fused; the last one is the view")
    ap.add_argument("--device", default="cpu", choices=["auto", "cpu", "cuda"])
    ap.add_argument("--threads", type=int, help="CPU threads of the Warp launches (default: all cores)")
    ap.add_argument("--voxel-size", type=float, default=0.01)
    ap.add_argument("--stride", type=int, default=4, help="sample stride of the visibility points")
    ap.add_argument("--rays", type=int, default=64, help="rays per hemisphere (make_direction_set)")
    ap.add_argument("--ray-length", type=float, default=0.5)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", dest="json_out", help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    if args.threads is not None:
        set_cpu_threads(args.threads)
    import open3d as o3d

    device = resolve_device(args.device)
    rec = open_recording(args.recording)
    if not rec.has_poses:
        raise SystemExit(f"{args.recording}: needs poses")
    vol = TSDFVolume(FusionConfig(voxel_size=args.voxel_size), device)
    view = None
    for frame in iter_frames(rec, list(range(min(args.frames, len(rec))))):
        vol.integrate(frame.depth, rec.intrinsics, frame.pose)
        view, sensor = frame.pose, frame.depth
    grid = vol.dense_grid()
    res = {"device": device, "device_name": device_name(device), "threads": cpu_threads() if device == "cpu" else 0,
           "warp": wp.__version__, "open3d": o3d.__version__, "fusion_on": str(vol.o3d_device),
           "recording": args.recording, "frames_fused": vol.frames_integrated,
           "size": f"{rec.intrinsics.width}x{rec.intrinsics.height}", "voxel_size": args.voxel_size,
           "load_average": os.getloadavg()[0],
           "raycast": raycast_peers(vol, grid, rec.intrinsics, view, sensor, args.voxel_size, args.repeats),
           "visibility": visibility_peers(vol, grid, rec.intrinsics, view, args.stride, args.rays,
                                          1.5 * args.voxel_size, args.ray_length, args.repeats)}
    r, v = res["raycast"], res["visibility"]
    print(f"{res['device_name']} ({device}, {res['threads']} threads), Warp {res['warp']}, Open3D {res['open3d']} "
          f"(fusion on {res['fusion_on']}); {res['recording']}: {res['frames_fused']} frames fused, "
          f"{args.voxel_size} m voxels, view = last frame; load average {res['load_average']:.1f}")
    print(f"ray cast {res['size']}: Warp {r['warp_ms']:.1f} ms, Open3D VoxelBlockGrid.ray_cast "
          f"{r['open3d_ms']:.1f} ms; "
          f"valid Warp {r['warp_valid']:.3f} / Open3D {r['open3d_valid']:.3f}, both {r['valid_in_both_of_either']:.3f} "
          f"of either; |depth diff| median {r['depth_diff_median_mm']:.2f} mm, p95 {r['depth_diff_p95_mm']:.2f} mm, "
          f"{100 * r['depth_within_1_voxel']:.1f}% within a voxel; normal angle median "
          f"{r['normal_angle_median_deg']:.2f} deg, {100 * r['normal_within_5deg']:.1f}% within 5 deg; against the "
          f"view's sensor depth: median |diff| Warp {r['warp_vs_sensor_median_mm']:.2f} mm, Open3D "
          f"{r['open3d_vs_sensor_median_mm']:.2f} mm")
    print(f"visibility ({v['points']} points, stride {args.stride}, {v['rays']} rays of {args.ray_length} m): "
          f"Warp {v['warp_ms']:.1f} ms (occlusion + projection), Embree {v['embree_ms']:.1f} ms "
          f"(+ BVH {v['embree_bvh_ms']:.0f} ms, mesh extraction {v['mesh_extract_ms']:.0f} ms, "
          f"{v['mesh_triangles']} triangles); rays agreeing {100 * v['ray_agreement']:.2f}% (blocked: Warp "
          f"{100 * v['warp_blocked_share']:.1f}%, Embree {100 * v['embree_blocked_share']:.1f}%); "
          f"visible fraction mean "
          f"{v['visible_fraction_mean_warp']:.3f} / {v['visible_fraction_mean_embree']:.3f}, |diff| median "
          f"{v['visible_fraction_abs_diff_median']:.3f}, p95 {v['visible_fraction_abs_diff_p95']:.3f}, "
          f"correlation {v['visible_fraction_correlation']:.3f}")
    if args.json_out:
        write_json(args.json_out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
