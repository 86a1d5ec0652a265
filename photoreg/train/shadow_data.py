"""Training and evaluation views for the neural shadow-map network: procedural scenes, buffers, targets.

Scenes are built like tests/test_render.py, so that every part of the run-time path is exercised:
the real geometry is an SDF brick (a floor at z = 0, sometimes a wall, sometimes a real box on the floor),
the virtual objects are 1-3 trimesh primitives (box, sphere, cylinder, cone, capsule, torus) of 6-30 cm,
resting on the floor or floating up to 15 cm above it, at random yaw and tilt; the camera looks at them
from 0.5-1.5 m and 20-70 degrees of elevation with a 128x96 pinhole of focal `--focal` px (default 100-350:
the pixel scale of a 640x480 frame at the lighting stride 4 up to stride 1.5; the network runs at the
lighting stride, so its pixel scale is the camera's focal length / stride). The lighting F (5 bands, the default) is a
disc sun (elevation 10-85 degrees, angular radius 0.5-20 degrees) plus a sky with a vertical gradient;
the light is parametric_light(F) in the direction of F's band 1, as render_voxel takes it.

Per view: the buffers (photoreg.render.shadow_buffers) of the view and of a perturbed twin (camera
turned by up to half a pixel, light by up to 0.5 degree: the perturbation loss), the target ratio from
the voxel renderer (render_voxel with the session defaults: 64 rays, 16 disc rays, 0.5 m, at lighting
stride `--target-stride`, its ratio interpolated back to every pixel as in the pipeline) on real
pixels and voxel colour / unshadowed colour (render_none) on fully covered virtual pixels, the
per-receiver opacity of the parametric light (receiver_opacity) and a weight mask (valid targets).
Views are written as .npz shards (atomic), `count` views per shard.
"""
from __future__ import annotations

import argparse
import copy
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from photoreg.io.atomic import atomic_path
from photoreg.kernels.grid import DenseGrid
from photoreg.kernels.raycast import raycast_surface
from photoreg.kernels.transfer import make_direction_set
from photoreg.lighting import sh
from photoreg.lighting.parametric import ParametricLight, lobe_sh, parametric_light, receiver_opacity
from photoreg.render.composite import RenderInput, shade
from photoreg.render.gbuffer import GBufferRenderer
from photoreg.render.scene import VirtualObject, VirtualScene, sdf_grid, voxel_grid
from photoreg.render.shadow_buffers import SM_RESOLUTION, shadow_buffers
from photoreg.render.shadowmap import fit_shadow_map
from photoreg.render.voxel import render_none, render_voxel
from photoreg.synth.cameras import look_at
from photoreg.types import Intrinsics

WIDTH, HEIGHT = 128, 96
BANDS, RAYS, LIGHT_RAYS, RAY_LENGTH = 5, 64, 16, 0.5   # the session defaults (photoreg.config)
VOXEL = 0.01
OFFSET = 1.5 * VOXEL
REAL_VOXEL = 0.01
FOCAL = (100.0, 350.0)  # focal length range of the views, pixels (log-uniform)
TARGET_STRIDE = 2   # the voxel renderer's lighting stride for targets (its ratio is interpolated back)
PRIMITIVES = ("box", "sphere", "cylinder", "cone", "capsule", "torus")


@dataclass
class View:
    buffers: np.ndarray    # (C, H, W) float32
    perturbed: np.ndarray  # (C, H, W) float32, the same view with camera and light jittered
    target: np.ndarray     # (H, W, 3) float32 ratio (real) or shadowed / unshadowed colour (virtual)
    opacity: np.ndarray    # (H, W, 3) float32 receiver opacity of the parametric light
    weight: np.ndarray     # (H, W) float32, 1 where the target holds


def _primitive(kind: str, rng: np.random.Generator) -> trimesh.Trimesh:
    if kind == "box":
        return trimesh.creation.box(extents=rng.uniform(0.3, 1.0, 3))
    if kind == "sphere":
        return trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=rng.uniform(0.15, 0.5), height=1.0, sections=24)
    if kind == "cone":
        return trimesh.creation.cone(radius=rng.uniform(0.2, 0.5), height=1.0, sections=24)
    if kind == "capsule":
        return trimesh.creation.capsule(height=0.6, radius=rng.uniform(0.1, 0.25), count=[12, 12])
    return trimesh.creation.torus(major_radius=0.35, minor_radius=rng.uniform(0.06, 0.15), major_sections=24,
                                  minor_sections=12)


def random_objects(rng: np.random.Generator) -> VirtualScene:
    """1-3 primitives of 6-30 cm near the origin, on the floor or floating, random yaw and tilt."""
    objects = []
    for _ in range(rng.integers(1, 4)):
        mesh = _primitive(PRIMITIVES[rng.integers(len(PRIMITIVES))], rng)
        tilt = rng.uniform(-40, 40, 2) if rng.random() < 0.3 else np.zeros(2)
        R = Rotation.from_euler("xyz", [tilt[0], tilt[1], rng.uniform(0, 360)], degrees=True).as_matrix()
        v = np.asarray(mesh.vertices) @ R.T
        T = np.eye(4)
        T[:3, :3] = R * rng.uniform(0.06, 0.3) / (v.max(0) - v.min(0)).max()
        v = np.asarray(mesh.vertices) @ T[:3, :3].T
        lift = 0.0 if rng.random() < 0.7 else rng.uniform(0.02, 0.15)
        T[:3, 3] = np.r_[rng.uniform(-0.2, 0.2, 2), lift - v[:, 2].min()]
        objects.append(VirtualObject(f"procedural:{len(objects)}", v + T[:3, 3], np.asarray(mesh.faces, np.int64),
                                     rng.uniform(0.2, 0.9, 3).astype(np.float32), T))
    return VirtualScene(objects)


def random_real(rng: np.random.Generator, device: str = "cpu") -> DenseGrid:
    """Real SDF brick: the floor z = 0 over [-0.96, 0.96]^2, sometimes a wall and a real box (union = min)."""
    n, nz = 192, 64
    origin = np.array([-0.96, -0.96, -0.08])
    ax = [origin[i] + np.arange(m) * REAL_VOXEL for i, m in enumerate((n, n, nz))]
    x, y, z = np.meshgrid(*ax, indexing="ij")
    sdf = z.copy()
    if rng.random() < 0.35:                               # a wall facing the objects
        phi = rng.uniform(0, 2 * math.pi)
        u = np.array([math.cos(phi), math.sin(phi)])
        sdf = np.minimum(sdf, rng.uniform(0.3, 0.6) - (x * u[0] + y * u[1]))
    if rng.random() < 0.35:                               # a real box on the floor beside them
        c = rng.uniform(-0.5, 0.5, 2)
        c = c if np.linalg.norm(c) > 0.3 else c / max(np.linalg.norm(c), 1e-6) * 0.35
        half = np.r_[rng.uniform(0.04, 0.12, 2), rng.uniform(0.03, 0.15)]
        q = np.abs(np.stack([x - c[0], y - c[1], z - half[2]], -1)) - half
        box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)
        sdf = np.minimum(sdf, box)
    return sdf_grid(sdf, origin, REAL_VOXEL, 4 * REAL_VOXEL, device)


def random_lighting(rng: np.random.Generator) -> np.ndarray:
    """F (3, BANDS^2): a disc sun plus a sky brighter towards the zenith."""
    el, az = math.radians(rng.uniform(10, 85)), rng.uniform(0, 2 * math.pi)
    d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    sun = rng.uniform(2.0, 6.0) * np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.65, 0.95)])
    F = lobe_sh(sun, d, math.radians(rng.uniform(0.5, 20.0)), BANDS)
    dirs = sh.fibonacci_sphere(4096)
    sky = rng.uniform(0.05, 0.6) * np.array([rng.uniform(0.7, 0.9), rng.uniform(0.8, 0.95), 1.0])
    radiance = np.outer(np.clip(1.0 + rng.uniform(0.0, 0.8) * dirs[:, 2], 0.0, None), sky)
    return F + sh.project(dirs, radiance, np.full(len(dirs), 4 * math.pi / len(dirs)), BANDS)


def _jitter_rotation(rng: np.random.Generator, angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()


def view_buffers(real: DenseGrid, scene: VirtualScene, gbr: GBufferRenderer, intr: Intrinsics, pose: np.ndarray,
                 light: ParametricLight):
    """(ShadowBuffers, maps, gbuffer) of one view at stride 1."""
    maps = raycast_surface(real, intr, pose, 0.1, 5.0, stride=1)
    gb = gbr.render(pose, maps.depth, tolerance=0.5 * VOXEL)
    verts, faces, _ = scene.triangles()
    buf = shadow_buffers(maps, gb, light, fit_shadow_map(verts, faces, light.direction, real.device, SM_RESOLUTION))
    return buf, maps, gb


def make_views(rng: np.random.Generator, per_scene: int, target_stride: int = TARGET_STRIDE,
               focal: tuple[float, float] = FOCAL, device: str = "cpu") -> list[View]:
    """`per_scene` views of one random scene (module docstring)."""
    scene = random_objects(rng)
    real, virt = random_real(rng, device), voxel_grid(scene, VOXEL, device)
    f = math.exp(rng.uniform(math.log(focal[0]), math.log(focal[1])))
    intr = Intrinsics(WIDTH, HEIGHT, f, f, (WIDTH - 1) / 2, (HEIGHT - 1) / 2)
    gbr = GBufferRenderer(scene, intr, 2)
    dirs = make_direction_set(RAYS, BANDS, seed=0)
    views = []
    for _ in range(per_scene):
        lo, hi = scene.bounds
        target = (lo + hi) / 2 + np.r_[rng.uniform(-0.15, 0.15, 2), 0.0]
        el, az, dist = math.radians(rng.uniform(20, 70)), rng.uniform(0, 2 * math.pi), rng.uniform(0.5, 1.5)
        eye = target + dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        pose = look_at(eye, target)
        F = random_lighting(rng)
        light = parametric_light(F, sh.dominant_direction(F))   # the voxel renderer's light
        buf, maps, gb = view_buffers(real, scene, gbr, intr, pose, light)
        jpose = pose.copy()
        jpose[:3, :3] = _jitter_rotation(rng, rng.uniform(0, 0.5) / f) @ pose[:3, :3]
        jlight = copy.copy(light)
        jlight.direction = _jitter_rotation(rng, math.radians(rng.uniform(0, 0.5))) @ light.direction
        jbuf = view_buffers(real, scene, gbr, intr, jpose, jlight)[0]
        nrm = np.where(buf.valid[..., None], buf.normal, 0.0).reshape(-1, 3)
        opacity = receiver_opacity(light, nrm).reshape(HEIGHT, WIDTH, 3).astype(np.float32)
        lit = shade(F, sh.unoccluded_transfer(maps.normal.reshape(-1, 3), BANDS)).reshape(HEIGHT, WIDTH, 3)
        camera = (rng.uniform(0.3, 0.7) * np.maximum(lit, 0.0)).astype(np.float32)   # a grey real surface
        maps_t = raycast_surface(real, intr, pose, 0.1, 5.0, stride=target_stride)
        inp = RenderInput(camera, F, 1.0, real, virt, maps_t, gb, scene.bounds, lambda b: dirs, OFFSET, RAY_LENGTH,
                          light_rays=LIGHT_RAYS, scene=scene)
        vox, non = render_voxel(inp), render_none(inp)
        full = gb.coverage >= 1.0
        tgt = vox.ratio.copy()
        tgt[full] = np.clip(vox.colour[full] / np.maximum(non.colour[full], 1e-6), 0.0, 1.0)
        weight = ((maps.valid & (gb.coverage == 0)) | (full & buf.virtual)).astype(np.float32)
        views.append(View(buf.data, jbuf.data, tgt.astype(np.float32), opacity, weight))
    return views


def write_shard(path: Path, views: list[View]) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **{k: np.stack([getattr(v, k) for v in views])
                                       for k in ("buffers", "perturbed", "target", "opacity", "weight")})


def load_shards(folder: str | Path) -> dict[str, np.ndarray]:
    """Every shard of a folder, concatenated; FileNotFoundError naming the folder when it has none."""
    files = sorted(Path(folder).glob("shard_*.npz"))
    if not files:
        raise FileNotFoundError(f"{folder}: no shard_*.npz (write them with python3 -m photoreg.train.shadow_data)")
    parts = [dict(np.load(f)) for f in files]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Write neural shadow-map training views (.npz shards).")
    ap.add_argument("out", help="output folder")
    ap.add_argument("--scenes", type=int, default=200)
    ap.add_argument("--per-scene", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenes-per-shard", type=int, default=10)
    ap.add_argument("--target-stride", type=int, default=TARGET_STRIDE)
    ap.add_argument("--focal", type=float, nargs=2, default=FOCAL, metavar=("MIN", "MAX"),
                    help="focal length range of the views, pixels")
    a = ap.parse_args(argv)
    out = Path(a.out)
    t0 = time.perf_counter()
    for first in range(0, a.scenes, a.scenes_per_shard):
        path = out / f"shard_{a.seed:03d}_{first:05d}.npz"
        if path.exists():
            continue
        views = []
        for k in range(first, min(first + a.scenes_per_shard, a.scenes)):
            views += make_views(np.random.default_rng([a.seed, k]), a.per_scene, a.target_stride, tuple(a.focal))
        write_shard(path, views)
        print(f"{path.name}: {len(views)} views, {time.perf_counter() - t0:.0f} s", flush=True)
    (out / "README.json").write_text(json.dumps(vars(a)) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
