"""Training of the neural soft-shadow MLP (Sommer et al., WSCG 2023) in numpy, and `photoreg train neural_soft`.

Data: ray-traced visibility textures of the object on its ground plane (photoreg.render.shadow_texture)
for a grid of light directions (301 by default). Each step draws `batch` random (texture, u, v) samples,
bilinearly interpolated, and takes an Adam step on their mean squared error; the learning rate decays
exponentially from lr to lr_final. Hand-written backpropagation: PyTorch is not needed anywhere.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from photoreg.io.atomic import check_output_dir
from photoreg.render.neural_soft_weights import NeuralSoftSettings, cache_dir, mesh_sha256, save_weights, weights_key
from photoreg.render.shadow_mlp import ShadowMLP, encode, forward, init_mlp, predict
from photoreg.render.shadow_texture import ShadowTracer, light_grid

HELD_OUT = [(6.75, 6.0), (20.25, 114.0), (33.75, 222.0), (42.75, 330.0)]  # (theta, phi) deg off the grid

Progress = Callable[[str], None]


def stderr_progress(msg: str) -> None:
    print(f"neural_soft: {msg}", file=sys.stderr, flush=True)


@dataclass
class ShadowDataset:
    """Visibility textures (K, R, R) float32 (row = local +y, column = local +x) and their local light
    directions (K, 3)."""

    textures: np.ndarray
    directions: np.ndarray


def directions_deg(pairs: list[tuple[float, float]]) -> np.ndarray:
    """(K, 3) local unit directions from (theta, phi) pairs in degrees."""
    t, p = np.radians(np.asarray(pairs, np.float64)).T
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)


def make_dataset(tracer: ShadowTracer, directions: np.ndarray, settings: NeuralSoftSettings,
                 progress: Progress | None = None) -> ShadowDataset:
    """Trace one texture per direction at the settings' resolution, rays and cone angle (seeded per index)."""
    cone = math.radians(settings.cone_deg)
    tex = np.empty((len(directions), settings.resolution, settings.resolution), np.float32)
    every = max(len(directions) // 10, 1)
    for k, d in enumerate(directions):
        tex[k] = tracer.texture(d, settings.resolution, settings.rays, cone, seed=settings.seed * 100003 + k)
        if progress and ((k + 1) % every == 0 or k + 1 == len(directions)):
            progress(f"traced {k + 1}/{len(directions)} textures")
    return ShadowDataset(tex, np.asarray(directions, np.float64))


def sample(ds: ShadowDataset, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n random bilinear samples: uv (n, 2) in [0, 1), directions (n, 3), visibility targets (n,)."""
    K, R, _ = ds.textures.shape
    k = rng.integers(0, K, n)
    uv = rng.random((n, 2))
    x = np.clip(uv * R - 0.5, 0.0, R - 1.0)            # texel-centre coordinates (column, row)
    i0 = np.minimum(np.floor(x).astype(np.int64), max(R - 2, 0))
    f = x - i0
    i1 = np.minimum(i0 + 1, R - 1)
    t = ds.textures
    top = t[k, i0[:, 1], i0[:, 0]] * (1 - f[:, 0]) + t[k, i0[:, 1], i1[:, 0]] * f[:, 0]
    bot = t[k, i1[:, 1], i0[:, 0]] * (1 - f[:, 0]) + t[k, i1[:, 1], i1[:, 0]] * f[:, 0]
    return uv.astype(np.float32), ds.directions[k].astype(np.float32), (top * (1 - f[:, 1]) + bot * f[:, 1]).astype(np.float32)


def loss_and_grads(net: ShadowMLP, x: np.ndarray, y: np.ndarray) -> tuple[float, list[np.ndarray], list[np.ndarray]]:
    """Mean squared error of the net on encoded inputs x against y, and its gradients per layer."""
    out, acts = forward(net, x)
    err = out - y
    g = (2.0 / len(y)) * (err * out * (1.0 - out))[:, None].astype(np.float32)
    gw, gb = [None] * len(net.weights), [None] * len(net.weights)
    for k in range(len(net.weights) - 1, -1, -1):
        gw[k] = acts[k].T @ g
        gb[k] = g.sum(0)
        if k:
            g = (g @ net.weights[k].T) * (acts[k] > 0)
    return float(np.mean(err * err)), gw, gb


class Adam:
    """Adam (beta 0.9 / 0.999) over the net's weights and biases, in place."""

    def __init__(self, net: ShadowMLP, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8):
        self.params = net.weights + net.biases
        self.m = [np.zeros_like(p) for p in self.params]
        self.v = [np.zeros_like(p) for p in self.params]
        self.b1, self.b2, self.eps, self.t = b1, b2, eps, 0

    def step(self, grads: list[np.ndarray], lr: float) -> None:
        self.t += 1
        c1, c2 = 1.0 - self.b1 ** self.t, 1.0 - self.b2 ** self.t
        for p, g, m, v in zip(self.params, grads, self.m, self.v):
            m *= self.b1
            m += (1.0 - self.b1) * g
            v *= self.b2
            v += (1.0 - self.b2) * g * g
            p -= (lr / c1) * m / (np.sqrt(v / c2) + self.eps)


@dataclass
class TrainResult:
    net: ShadowMLP
    losses: np.ndarray    # (steps,) training MSE per step
    seconds: float


def train_mlp(ds: ShadowDataset, settings: NeuralSoftSettings, progress: Progress | None = None) -> TrainResult:
    """Fit a fresh MLP to the dataset with the settings' optimiser and schedule."""
    s = settings.check()
    rng = np.random.default_rng(s.seed)
    net = init_mlp(s.pos_freqs, s.dir_freqs, s.hidden, s.width, rng)
    opt = Adam(net)
    losses = np.empty(s.steps)
    decay = (s.lr_final / s.lr) ** (1.0 / max(s.steps - 1, 1))
    every = max(s.steps // 20, 1)
    t0 = time.perf_counter()
    for step in range(s.steps):
        uv, d, y = sample(ds, s.batch, rng)
        losses[step], gw, gb = loss_and_grads(net, encode(uv, d, s.pos_freqs, s.dir_freqs), y)
        opt.step(gw + gb, s.lr * decay ** step)
        if progress and ((step + 1) % every == 0 or step + 1 == s.steps):
            progress(f"step {step + 1}/{s.steps} loss {losses[max(step - every + 1, 0):step + 1].mean():.2e} "
                     f"({time.perf_counter() - t0:.0f} s)")
    return TrainResult(net, losses, time.perf_counter() - t0)


def texture_rmse(net: ShadowMLP, ds: ShadowDataset) -> float:
    """RMSE of the net against every texel centre of every texture of the dataset."""
    R = ds.textures.shape[1]
    c = (np.arange(R) + 0.5) / R
    v, u = np.meshgrid(c, c, indexing="ij")
    uv = np.stack([u.ravel(), v.ravel()], -1)
    se = [np.mean((predict(net, uv, d) - t.ravel()) ** 2) for d, t in zip(ds.directions, ds.textures)]
    return float(np.sqrt(np.mean(se)))


def train_mesh(mesh_path: str | Path, vertices: np.ndarray, faces: np.ndarray,
               settings: NeuralSoftSettings = NeuralSoftSettings(), out_dir: Path | None = None,
               progress: Progress | None = stderr_progress, up: np.ndarray | None = None) -> Path:
    """Trace, train and write the weights of one mesh (vertices (V, 3) in its standing frame, faces; `up`: the
    mesh's up in its own frame, None for +z: neural_soft_weights.standing_rotation) to out_dir/<key>.npz (default:
    the cache), with its figures in the file's meta. Returns the path."""
    s = settings.check()
    key = weights_key(mesh_path, s, up)
    tracer = ShadowTracer(vertices, faces)
    t0 = time.perf_counter()
    ds = make_dataset(tracer, light_grid(s.theta_max_deg, s.theta_step_deg, s.phi_step_deg), s, progress)
    trace_s = time.perf_counter() - t0
    res = train_mlp(ds, s, progress)
    held = make_dataset(tracer, directions_deg(HELD_OUT), s)
    meta = {"key": key, "mesh": Path(mesh_path).name, "mesh_sha256": mesh_sha256(mesh_path), "settings": asdict(s),
            "up": None if up is None else np.asarray(up, np.float64).tolist(),
            "n_params": res.net.n_params, "trace_seconds": round(trace_s, 1), "train_seconds": round(res.seconds, 1),
            "final_loss": float(res.losses[-max(len(res.losses) // 20, 1):].mean()),
            "rmse_train": texture_rmse(res.net, ds), "rmse_held_out": texture_rmse(res.net, held)}
    path = save_weights((out_dir or cache_dir()) / f"{key}.npz", res.net, meta)
    if progress:
        progress(f"wrote {path} ({res.net.n_params} parameters, held-out RMSE {meta['rmse_held_out']:.4f})")
    return path


SUPPORT_FRAMES = 8   # frames whose depth `train neural_soft` reads to find the side each object stands on
SUPPORT_STEP = 4     # ... at every 4th pixel


def recorded_support(session, objects: list) -> list[np.ndarray | None]:
    """The side each placed object stands on as a run finds it (neural_soft.support_axis), from the sensor depth of
    up to SUPPORT_FRAMES frames of the session's selection with a recorded pose (world points and depth-map normals
    of every SUPPORT_STEP-th pixel within the texture's reach of the object): the side most of them pick; None for
    an object none of them shows standing on anything (or a session without recorded poses)."""
    from photoreg.config import select_frames
    from photoreg.io.recording import open_configured
    from photoreg.lighting.samples import depth_normals
    from photoreg.render.neural_soft import plane_tolerance, support_axis
    from photoreg.render.neural_soft_weights import axis_name, axis_vector
    from photoreg.render.shadow_texture import PLANE_SIDE

    rec = open_configured(session.recording)
    picks: list[list[str]] = [[] for _ in objects]
    if not (session.recording.use_poses and rec.has_poses):
        return [None] * len(objects)
    posed = [i for i in select_frames(session.frames, len(rec), session.recording.path) if rec.poses[i] is not None]
    offset = session.lighting.ray_offset_voxels * session.reconstruction.voxel_size
    for i in posed[::max(1, len(posed) // SUPPORT_FRAMES)][:SUPPORT_FRAMES]:
        f = rec.frame(i)
        k = f.intrinsics
        r, c = np.mgrid[0:k.height:SUPPORT_STEP, 0:k.width:SUPPORT_STEP]
        z, n = f.depth[r, c], depth_normals(f.depth, k, r, c, SUPPORT_STEP)
        ok = (z > 0) & np.any(n != 0, axis=-1)
        cam = np.stack([(c - k.cx) / k.fx * z, (r - k.cy) / k.fy * z, z], -1)[ok]
        world, normals = cam @ f.pose[:3, :3].T + f.pose[:3, 3], n[ok] @ f.pose[:3, :3].T
        for j, obj in enumerate(objects):
            lo, hi = obj.vertices.min(0), obj.vertices.max(0)
            near = np.linalg.norm(np.clip(world, lo, hi) - world, axis=1) <= PLANE_SIDE * float((hi - lo).max())
            up = support_axis(obj, world[near], normals[near], plane_tolerance(obj, offset))
            if up is not None:
                picks[j].append(axis_name(up))
    return [axis_vector(max(set(p), key=p.count)) if p else None for p in picks]


def train_command(args) -> int:
    """`photoreg train neural_soft SESSION.toml`: train (or find cached) weights for every object's mesh, once per
    mesh and side it stands on (--up: a signed axis of the mesh, or auto: the side a run finds from the real surface
    near the object, recorded_support); with --out, each mesh's weights end up in that folder (found ones copied
    there)."""
    import shutil

    from photoreg.config import load_session
    from photoreg.render.neural_soft_weights import axis_name, axis_vector, find_weights, standing_rotation
    from photoreg.render.scene import load_scene

    out = Path(args.out) if args.out else None
    if out is not None:
        check_output_dir(out, "--out")
    session = load_session(args.session)
    settings = NeuralSoftSettings()
    done: set[str] = set()
    objects = load_scene(session.objects).objects
    found_sides = recorded_support(session, objects) if args.up == "auto" else [None] * len(objects)
    for obj, side in zip(objects, found_sides):
        if args.up != "auto":
            up = axis_vector(args.up)
        elif side is not None:
            up = side
        else:
            up = axis_vector(axis_name(np.linalg.solve(obj.transform[:3, :3], [0.0, 0.0, 1.0])))
            print(f"{obj.source}: no real surface to stand on found near it in the recording's depth: taking the side "
                  f"its rotation turns nearest to the world's +z, {axis_name(up)} (give --up=SIDE if wrong)")
        key = weights_key(obj.source, settings, up)
        if key in done:   # another object of the same mesh, standing on the same side
            continue
        done.add(key)
        found = find_weights(key)
        if found and not args.force:
            if out is not None and found.parent.resolve() != out.resolve():
                out.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(found, out / found.name)
                found = out / found.name
            print(f"{obj.source}: weights at {found}")
            continue
        standing = obj.local_vertices() @ standing_rotation(up).T
        print(f"{obj.source} standing on its {axis_name(up)} side: "
              f"{train_mesh(obj.source, standing, obj.faces, settings, out, up=up)}")
    return 0
