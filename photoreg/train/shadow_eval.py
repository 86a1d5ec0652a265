"""Error of neural shadow-map visibility against the voxel renderer's targets (numpy only, no PyTorch).

The region of interest is the voxel target's shadow (luminance ratio below ROI_LEVEL) dilated by
ROI_DILATE pixels, inside the valid-target mask; errors are RMSE of the ratio 1 - o (1 - v) over it.
Baselines on the same pixels: `none` (ratio 1) and a hard shadow-map test (v = 0 where the receiver is
more than HARD_BIAS behind the map's blocker), the unfiltered shadow map the network starts from.
"""
from __future__ import annotations

import math
from typing import Callable

import cv2
import numpy as np

from photoreg.lighting.sh import LUMINANCE

ROI_LEVEL = 0.98
ROI_DILATE = 7
HARD_BIAS = 0.005  # metres


def ratio_of(vis: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """1 - o (1 - v): vis (N, H, W), opacity (N, H, W, 3) -> (N, H, W, 3)."""
    return 1.0 - opacity * (1.0 - vis[..., None])


def roi(target: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(N, H, W) bool: dilated target shadow inside the weight mask."""
    k = np.ones((2 * ROI_DILATE + 1,) * 2, np.uint8)
    shadow = ((target @ LUMINANCE) < ROI_LEVEL) & (weight > 0)
    return np.stack([cv2.dilate(m.astype(np.uint8), k).astype(bool) for m in shadow]) & (weight > 0)


def hard_visibility(buffers: np.ndarray) -> np.ndarray:
    """Unfiltered shadow-map test from the buffers (N, C, H, W): 0 behind a blocker, else 1."""
    return (buffers[:, 5] - buffers[:, 4] <= HARD_BIAS).astype(np.float32)


def evaluate(views: dict[str, np.ndarray], predict: Callable[[np.ndarray], np.ndarray]) -> dict[str, float]:
    """RMSE in the region of interest of predict(buffers (N, C, H, W)) -> visibility (N, H, W), the baselines,
    and the correlation of predicted and target shadow (1 - luminance ratio) there."""
    t, o, w = views["target"], views["opacity"], views["weight"]
    m = roi(t, w)
    vis = predict(views["buffers"])
    pred = ratio_of(vis, o)

    def rmse(r: np.ndarray) -> float:
        return float(np.sqrt(np.mean((r[m] - t[m]) ** 2)))

    a, b = 1.0 - pred[m] @ LUMINANCE, 1.0 - t[m] @ LUMINANCE
    corr = float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else 0.0
    return {"rmse_roi": rmse(pred), "rmse_none": rmse(np.ones_like(t)),
            "rmse_hard_shadowmap": rmse(ratio_of(hard_visibility(views["buffers"]), o)),
            "shadow_correlation": corr, "roi_pixels": int(m.sum()), "views": int(len(t))}


def time_network(shapes=((480, 640), (120, 160)), repeats: int = 10) -> dict[str, float]:
    """Median ms of one cv2.dnn forward of the committed network per input (height, width)."""
    import time

    from photoreg.render.neural_shadowmap import load_net, predict_visibility

    net, out = load_net(), {}
    rng = np.random.default_rng(0)
    for h, w in shapes:
        x = rng.uniform(0, 1, (7, h, w)).astype(np.float32)
        predict_visibility(x, net)
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            predict_visibility(x, net)
            ts.append(time.perf_counter() - t)
        out[f"net_ms_{w}x{h}"] = round(1000 * float(np.median(ts)), 2)
    return out


def time_renderers(names=("none", "neural_shadowmap", "shadowmap", "voxel"), repeats: int = 3) -> dict[str, float]:
    """Median ms per 640x480 frame of registered renderers on one scene: the demo's 12 cm cube on a floor
    seen from 0.8 m (fx 525, lighting stride 4, 64 rays, 16 disc rays, a sun 40 degrees off zenith)."""
    import time

    from photoreg.kernels.raycast import raycast_surface
    from photoreg.kernels.transfer import make_direction_set
    from photoreg.lighting.parametric import lobe_sh
    from photoreg.render.composite import RenderInput
    from photoreg.render.gbuffer import GBufferRenderer
    from photoreg.render.registry import get_renderer
    from photoreg.render.scene import VirtualObject, VirtualScene, voxel_grid
    from photoreg.synth.cameras import look_at
    from photoreg.train.shadow_data import random_real
    from photoreg.types import Intrinsics
    import trimesh

    box = trimesh.creation.box(extents=(0.12, 0.12, 0.12))
    T = np.eye(4)
    T[2, 3] = 0.06
    scene = VirtualScene([VirtualObject("cube", np.asarray(box.vertices) + T[:3, 3], np.asarray(box.faces), 
                                        np.array([0.7, 0.5, 0.3], np.float32), T)])
    real = random_real(np.random.default_rng(3))
    intr = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
    pose = look_at([0.5, -0.45, 0.45], [0.0, 0.0, 0.05])
    maps = raycast_surface(real, intr, pose, 0.1, 5.0, stride=4)
    gb = GBufferRenderer(scene, intr, 2).render(pose, raycast_surface(real, intr, pose, 0.1, 5.0).depth, 0.005)
    d = np.array([math.sin(math.radians(40)), 0.3, math.cos(math.radians(40))])
    F = lobe_sh(np.array([3.0, 2.9, 2.7]), d / np.linalg.norm(d), math.radians(3.0), 5)
    F[:, 0] += 1.2
    dirs = make_direction_set(64, 5, seed=0)
    inp = RenderInput(np.full((480, 640, 3), 0.3, np.float32), F, 1.0, real, voxel_grid(scene, 0.01, real.device),
                      maps, gb, scene.bounds, lambda b: dirs, 0.015, 0.5, light_rays=16, scene=scene)
    out = {}
    for name in names:
        render = get_renderer(name)
        render(inp)
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            render(inp)
            ts.append(time.perf_counter() - t)
        out[f"render_ms_{name}"] = round(1000 * float(np.median(ts)), 1)
    return out


def main(argv: list[str] | None = None) -> int:
    import argparse
    import json

    from photoreg.render.neural_shadowmap import load_net, predict_visibility
    from photoreg.train.shadow_data import load_shards

    ap = argparse.ArgumentParser(description="Error of the committed neural shadow-map network on held-out views "
                                             "(cv2.dnn, the run-time path) and its speed on this machine.")
    ap.add_argument("views", help="folder of held-out shard_*.npz (photoreg.train.shadow_data)")
    ap.add_argument("--out", help="write the figures to this JSON file too")
    ap.add_argument("--no-timing", action="store_true", help="errors only (no speed figures)")
    a = ap.parse_args(argv)
    net = load_net()
    res = evaluate(load_shards(a.views), lambda b: np.stack([predict_visibility(x, net) for x in b]))
    if not a.no_timing:
        res.update(time_network())
        res.update(time_renderers())
    print(json.dumps(res, indent=1))
    if a.out:
        from photoreg.io.atomic import write_json
        write_json(a.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
