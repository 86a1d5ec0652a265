"""`photoreg synth`: render a ground-truth RGB-D recording (native layout) with Mitsuba 3.

Outputs in the recording folder: rgb/ depth/ [depth_clean/] rgb.txt depth.txt groundtruth.txt
intrinsics.json lighting_gt.json scene.json, and for insert frames insert/ (sRGB PNG and linear EXR
with the virtual object added) insert_mask/ object.obj session.toml.
Images hold exposure * radiance; lighting_gt.json holds the SH of the unexposed environment, so
lighting estimated from the images should match exposure * sh.
"""
from __future__ import annotations

import importlib.metadata
import json
import os
import shlex
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
from trimesh.exchange.obj import export_obj

from ..config import ALBEDO_TEXTURE
from ..io.atomic import atomic_path, check_output_dir, hold_folder, write_json, write_text
from ..io.images import linear_to_srgb, write_exr, write_png_rgb
from ..io.native import NativeWriter, frame_name
from .cameras import CAMERA_PATHS, camera_path, default_intrinsics
from .depth import kinect_like
from .environment import ProceduralSky, emitter_rotation, environment_sh, load_environment
from .render import MitsubaScene, mitsuba
from .scenes import INSERT_MESH_SCALE, SCENE_KINDS, build_scene

GENERATOR_VERSION = "1"
FPS = 30.0  # frame i is at i / FPS seconds
BANDS = 8
SHUTTER_SAMPLES = 8  # instants a frame with a shutter time (--shutter) is rendered at and averaged over
# Beyond these the render runs out of memory with an opaque error (Dr.Jit's at 40000x30000, numpy's at 10^8 frames)
MAX_SIDE, MAX_FRAMES, MAX_SPP = 8192, 100_000, 65_536


@dataclass
class SynthConfig:
    """Everything that determines a generated recording (the CLI's options, plus the procedural sky)."""

    scene: str
    out: str
    frames: int = 30
    width: int = 320
    height: int = 240
    spp: int = 64
    env: str = "procedural"  # path to an equirect .hdr/.exr, or "procedural"
    yaw: float = 0.0  # degrees about world +z
    seed: int = 0
    camera: str = "orbit"
    direct_only: bool = False
    insert_frames: str = "auto"  # "auto", "none" or comma-separated frame indices
    noise: bool = True  # Kinect-like depth in depth/ and the clean depth in depth_clean/
    mesh: str | None = None  # mesh file for the tabletop's mesh object (default: a procedural cylinder)
    overexpose: float = 1.0  # times the chosen exposure (> 1: the brightest surfaces saturate, as a camera's do)
    insert_texture: bool = False  # the inserted cube textured (scenes.insert_texture), its session albedo = "texture"
    insert_mesh: str | None = None  # mesh file inserted instead of the cube (largest side scenes.INSERT_MESH_SCALE)
    shutter: float = 0.0  # seconds the shutter is open, centred on the frame's time (motion blur); 0: an instant
    sky: ProceduralSky = field(default_factory=ProceduralSky)

    def command_line(self) -> str:
        """The `photoreg synth` command reproducing this config (the procedural sky is always the default)."""
        args = ["photoreg", "synth", self.scene, "--out", self.out, "--frames", str(self.frames),
                "--size", f"{self.width}x{self.height}", "--spp", str(self.spp), "--env", self.env,
                "--yaw", f"{self.yaw:g}", "--seed", str(self.seed), "--camera", self.camera,
                "--insert-frames", self.insert_frames]
        args += ["--direct-only"] * self.direct_only + ["--no-noise"] * (not self.noise)
        args += ["--mesh", self.mesh] if self.mesh else []
        args += ["--overexpose", f"{self.overexpose:g}"] if self.overexpose != 1.0 else []
        args += ["--insert-texture"] * self.insert_texture
        args += ["--insert-mesh", self.insert_mesh] if self.insert_mesh else []
        args += ["--shutter", f"{self.shutter:g}"] if self.shutter else []
        return shlex.join(args)

    @property
    def max_depth(self) -> int:
        """Path length of the integrator: 2 (direct light only) or 6."""
        return 2 if self.direct_only else 6

    def validate(self) -> None:
        """Clear errors naming the option for values the generator cannot use."""
        if self.scene not in SCENE_KINDS:
            raise ValueError(f"unknown scene kind {self.scene!r}; choose one of {', '.join(SCENE_KINDS)}")
        if self.camera not in CAMERA_PATHS:
            raise ValueError(f"--camera {self.camera!r}: choose one of {', '.join(CAMERA_PATHS)}")
        if not 1 <= self.frames <= MAX_FRAMES:
            raise ValueError(f"--frames {self.frames}: need 1..{MAX_FRAMES}")
        if not 1 <= self.spp <= MAX_SPP:
            raise ValueError(f"--spp {self.spp}: need 1..{MAX_SPP}")
        if not (8 <= self.width <= MAX_SIDE and 8 <= self.height <= MAX_SIDE):
            raise ValueError(f"--size {self.width}x{self.height}: need 8..{MAX_SIDE} pixels a side")
        if not (self.overexpose > 0 and np.isfinite(self.overexpose)):
            raise ValueError(f"--overexpose {self.overexpose}: need a positive factor")
        if not np.isfinite(self.yaw):
            raise ValueError(f"--yaw {self.yaw}: need a finite angle in degrees")
        if not 0 <= self.seed < 2 ** 32:
            raise ValueError(f"--seed {self.seed}: need an integer in 0..2^32-1")
        if not 0 <= self.shutter <= 1.0 / FPS:
            raise ValueError(f"--shutter {self.shutter}: seconds in 0..{1.0 / FPS:.4f} (one frame interval at {FPS:g} "
                             "frames/s)")
        if self.mesh and self.scene != "tabletop":
            raise ValueError(f"--mesh is used by the tabletop scene only (scene is {self.scene!r})")
        if self.insert_mesh and self.insert_texture:
            raise ValueError("--insert-texture textures the inserted cube: it does not combine with --insert-mesh")
        if self.insert_mesh and not Path(self.insert_mesh).is_file():
            raise FileNotFoundError(f"--insert-mesh {self.insert_mesh}: no such mesh file")
        if self.env != "procedural" and not Path(self.env).is_file():
            raise FileNotFoundError(f"--env {self.env}: no such HDR file (give a .hdr/.exr path or 'procedural')")
        insert_indices(self.insert_frames, self.frames)


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' -> (W, H)."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise ValueError(f"--size {text!r}: expected WxH in pixels, e.g. 320x240")
    return int(parts[0]), int(parts[1])


def insert_indices(spec: str, n: int) -> list[int]:
    """Frames re-rendered with the virtual object: 'auto' (3 spread over the sequence), 'none', or 'i,j,k'."""
    spec = spec.strip().lower()
    if spec == "auto":
        return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(3, n) + 2)[1:-1]})
    if spec in ("none", ""):
        return []
    try:
        idx = sorted({int(x) for x in spec.split(",")})
    except ValueError:
        raise ValueError(f"--insert-frames {spec!r}: expected 'auto', 'none' or comma-separated frame indices") from None
    bad = [i for i in idx if not 0 <= i < n]
    if bad:
        raise ValueError(f"--insert-frames: frames {bad} outside 0..{n - 1}")
    return idx


def choose_exposure(linear: np.ndarray, percentile: float = 99.5, target: float = 0.9) -> float:
    """Scale putting the `percentile` of the per-pixel max channel at `target` (so under 1% clip)."""
    level = float(np.percentile(np.max(linear, axis=-1), percentile))
    if not np.isfinite(level) or level <= 0:
        raise RuntimeError("frame 0 rendered black: cannot choose an exposure")
    return target / level


def _session_toml(obj) -> str:
    """session.toml inserting the virtual object into this recording (DESIGN.md session file)."""
    def vec(v):
        return "[" + ", ".join(repr(float(x)) for x in v) + "]"
    albedo = f'"{ALBEDO_TEXTURE}"' if obj.textured else vec(obj.albedo)
    smooth = "smooth = true\n" if obj.mesh else ""   # Mitsuba interpolates a mesh's vertex normals
    return (f"# Virtual object of the insert/ ground truth, placed in this recording (written by photoreg synth).\n"
            f"[recording]\npath = \".\"\nformat = \"native\"\n\n"
            f"[[objects]]\nmesh = \"object.obj\"\nposition = {vec(obj.position)}\nrotation = {vec(obj.rotation_deg)}\n"
            f"scale = {float(obj.scale)!r}\nalbedo = {albedo}\n{smooth}\n"
            f"[render]\nshadows = \"voxel\"\n\n[output]\ndir = \"out\"\n")


def _world(cfg: SynthConfig):
    """(scene layout, environment image, its scene.json description, emitter rotation, intrinsics, camera
    poses) of a config."""
    layout = build_scene(cfg.scene, cfg.mesh)
    layout.insert = replace(layout.insert, textured=cfg.insert_texture)
    if cfg.insert_mesh:
        layout.insert = replace(layout.insert, mesh=str(Path(cfg.insert_mesh).resolve()), scale=INSERT_MESH_SCALE)
    env_image, env_desc = load_environment(cfg.env, cfg.sky)
    return (layout, env_image, env_desc, emitter_rotation(cfg.yaw), default_intrinsics(cfg.width, cfg.height),
            camera_path(cfg.camera, cfg.frames, layout.rig, cfg.seed))


def _exposed(scene: MitsubaScene, cfg: SynthConfig, layout, i: int, pose: np.ndarray, seed: int) -> np.ndarray:
    """Radiance of frame i (camera at `pose` at the frame's time): rendered at that instant, or with a shutter time
    the mean of SHUTTER_SAMPLES renders at instants spread over it (the spp shared among them), the camera moving
    along its path: the motion blur of a real camera."""
    if not cfg.shutter:
        return scene.render(pose, cfg.spp, seed)
    m = SHUTTER_SAMPLES
    at = i + cfg.shutter * FPS * ((np.arange(m) + 0.5) / m - 0.5)
    poses = camera_path(cfg.camera, cfg.frames, layout.rig, cfg.seed, at=at)
    spp = shutter_spp(cfg.spp)
    return np.mean([scene.render(p, spp, (seed + k * 7919) % 2**32) for k, p in enumerate(poses)], axis=0)


def shutter_spp(spp: int) -> int:
    """Samples per pixel of each of a shuttered frame's SHUTTER_SAMPLES renders: the frame's spp shared, at least 1."""
    return max(1, spp // SHUTTER_SAMPLES)


def _insert_scene(cfg: SynthConfig, layout, env_image: np.ndarray, rotation: np.ndarray, K) -> MitsubaScene:
    """The scene with the virtual object added (the insert renders)."""
    return MitsubaScene(layout.objects + [layout.insert.scene_object()], env_image, rotation, K, cfg.max_depth)


def _frame_seed(cfg: SynthConfig, i: int, other: bool = False) -> int:
    """Monte Carlo seed of frame i (the camera frame and its insert share it: correlated noise); `other`: a
    seed no frame of any recording uses (rerender_inserts)."""
    return (cfg.seed * 100003 + i + (2**31 if other else 0)) % 2**32


def rerender_inserts(recording: str | Path) -> dict[int, np.ndarray]:
    """Every insert frame of a recording made by generate(), rendered again with another Monte Carlo seed
    (linear, exposure applied, as insert/NNNNNN.exr): the same image up to render noise. An exact renderer
    does not share the ground truth's noise, so this is what it would score (photoreg bench renderers);
    the 'no shadow' baseline pastes the ground truth's own object, noise included."""
    recording = Path(recording)
    meta = json.loads((recording / "scene.json").read_text())
    cfg = SynthConfig(**meta["config"])
    mitsuba()
    layout, env_image, _, rotation, K, poses = _world(cfg)
    scene = _insert_scene(cfg, layout, env_image, rotation, K)
    return {i: meta["exposure"] * _exposed(scene, cfg, layout, i, poses[i], _frame_seed(cfg, i, other=True))
            for i in meta["insert"]["frames"]}


PARTIAL = ".partial"                 # an existing --out folder's unfinished recording is made in OUT/.partial
PARTIAL_MARK = ".photoreg-synth-partial"   # what marks OUT.partial (or OUT/.partial) as an unfinished recording


def generate(cfg: SynthConfig, log: Callable[[str], None] | None = print) -> Path:
    """Render the recording described by `cfg` into cfg.out (which must be absent or empty); returns its path. It is
    written into OUT.partial (into OUT/.partial where an empty OUT exists: its own file system, a mount point
    perhaps) and renamed (its files moved into OUT) when whole, so an interrupted run leaves no folder that passes
    for a recording; a later run removes an unfinished one (marked PARTIAL_MARK) and refuses any other."""
    cfg.validate()
    # the input files' absolute paths in scene.json: rerender_inserts and the command line read them from elsewhere
    cfg = replace(cfg, **{key: str(Path(value).resolve()) for key, value in
                          (("mesh", cfg.mesh), ("insert_mesh", cfg.insert_mesh), ("env", cfg.env))
                          if value and not (key == "env" and value == "procedural")})
    final = Path(cfg.out)
    check_output_dir(final, "--out")
    say = log or (lambda _msg: None)
    resolved = final.resolve()   # "." and a link to a folder have a name
    # the partial folder on OUT's own file system (an empty OUT may be a mount point): inside an existing OUT
    out = resolved / PARTIAL if final.exists() else resolved.with_name(resolved.name + ".partial")
    if final.exists() and any(p.name != PARTIAL for p in final.iterdir()):
        raise ValueError(f"--out {final}: exists and is not an empty folder; remove it or choose another")
    if out.exists() or out.is_symlink():
        if not (out / PARTIAL_MARK).is_file():
            raise ValueError(f"--out {final}: {out} exists and is not an interrupted photoreg synth run's (it holds no "
                             f"{PARTIAL_MARK}): remove it or choose another --out")
        held = hold_folder(out, "--out")   # a run still writing it holds it: refused, its work left alone
        say(f"removing {out}, an interrupted run's")
        shutil.rmtree(out)
        if held is not None:
            os.close(held)
    out.mkdir(parents=True)
    held = hold_folder(out, "--out")   # held while this run writes it (the rename keeps the folder's lock)
    try:
        (out / PARTIAL_MARK).write_text("an unfinished photoreg synth recording: a later run removes this folder\n")
        _render(cfg, out, final, say)
    finally:
        if held is not None:
            os.close(held)
    return final


def _render(cfg: SynthConfig, out: Path, final: Path, say: Callable[[str], None]) -> None:
    """generate's rendering into the partial folder `out` it holds, renamed to `final` when whole."""
    t_start = time.perf_counter()
    mi = mitsuba()
    layout, env_image, env_desc, rotation, K, poses = _world(cfg)
    sh = environment_sh(env_image, rotation, BANDS)
    inserts = insert_indices(cfg.insert_frames, cfg.frames)
    base = MitsubaScene(layout.objects, env_image, rotation, K, cfg.max_depth)
    with_object = _insert_scene(cfg, layout, env_image, rotation, K) if inserts else None
    writer = NativeWriter(out, K, source=f"photoreg synth {GENERATOR_VERSION}", shutter=cfg.shutter or None)
    exposure = None
    per_frame = []
    for i, pose in enumerate(poses):
        t0 = time.perf_counter()
        seed = _frame_seed(cfg, i)
        radiance = _exposed(base, cfg, layout, i, pose, seed)
        if exposure is None:
            exposure = cfg.overexpose * choose_exposure(radiance)
        z = base.geometry(pose)
        noisy = kinect_like(z, np.random.default_rng([cfg.seed, i])) if cfg.noise else None
        writer.write_frame(i, i / FPS, linear_to_srgb(exposure * radiance), z if noisy is None else noisy, pose,
                           depth_clean=z if cfg.noise else None)
        if i in inserts:
            lit = exposure * _exposed(with_object, cfg, layout, i, pose, seed)  # same seed: noise correlated with rgb/
            z_obj = with_object.geometry(pose)
            mask = (z_obj > 0) & ((z == 0) | (z_obj < z - 1e-5 * (1.0 + z)))
            name = frame_name(i)
            write_png_rgb(out / "insert" / f"{name}.png", linear_to_srgb(lit))
            write_exr(out / "insert" / f"{name}.exr", lit)
            write_png_rgb(out / "insert_mask" / f"{name}.png", np.repeat(mask[..., None] * np.uint8(255), 3, axis=-1))
        per_frame.append(time.perf_counter() - t0)
        say(f"frame {i + 1}/{cfg.frames}: {per_frame[-1]:.2f} s" + (" (+ insert)" if i in inserts else ""))
    writer.finish()
    writer.write_lighting_gt(sh, exposure=exposure)

    if inserts:
        # a mesh's vertex normals written out: the session's smooth shading takes the ones Mitsuba interpolates
        text, files = export_obj(layout.insert.local_mesh(), include_normals=bool(cfg.insert_mesh),
                                 return_texture=True, mtl_name="object.mtl")
        for name, data in files.items():   # a textured cube's material and image, beside it
            with atomic_path(out / name) as tmp:
                tmp.write_bytes(data)
        write_text(out / "object.obj", text)
        write_text(out / "session.toml", _session_toml(layout.insert))
    each = shutter_spp(cfg.spp)
    shutter_text = (f"colour and inserts the mean of {SHUTTER_SAMPLES} renders over the shutter time at {each} samples "
                    f"per pixel each ({SHUTTER_SAMPLES * each} in all), centred on the frame's time and pose; depth at "
                    "that instant")
    write_json(out / "scene.json", {
        "generator": {"name": "photoreg synth", "version": GENERATOR_VERSION,
                      "photoreg": importlib.metadata.version("photoreg"),
                      "mitsuba": mi.__version__, "variant": mi.variant()},
        "command": cfg.command_line(),
        "config": {k: v for k, v in asdict(cfg).items() if k != "sky"},
        "world": {"up": "+z", "floor_z": 0.0, "units": "metres",
                  "object_local_frame": "base on z=0, centred in x and y; transform is object-to-world"},
        "scene": cfg.scene,
        "objects": [o.to_json() for o in layout.objects],
        "lighting": {**env_desc, "yaw_deg": cfg.yaw, "emitter_to_world": rotation.tolist(), "bands": BANDS,
                     "emitter_mapping": "v = R^T w; u = atan2(v.x, -v.z)/(2 pi); t = acos(v.y)/pi; "
                                        "texel nodes at u=(j+0.5)/W, t=i/(H-1), bilinear"},
        "camera": {"path": cfg.camera, "rig": layout.rig.to_json(), "hfov_deg": 60.0, "fps": FPS,
                   "pose": "camera-to-world, OpenCV camera frame (x right, y down, z forward)",
                   "shutter_s": cfg.shutter,
                   "shutter": shutter_text if cfg.shutter else "an instant"},
        "render": {"integrator": "path", "max_depth": cfg.max_depth, "spp": cfg.spp, "seed": cfg.seed,
                   "reconstruction_filter": "box"},
        "exposure": exposure,
        "exposure_rule": f"99.5th percentile of frame 0's per-pixel max channel -> 0.9, times {cfg.overexpose:g}; "
                         "images = exposure * radiance",
        "depth": {"depth_scale": K.depth_scale, "clean": "depth_clean/" if cfg.noise else "depth/",
                  "noise": ("sigma = 1.2 mm + 1.9 mm * (z - 0.4)^2, holes where a 3x3 neighbourhood spans "
                            "> 4% of z or touches a missing pixel, quantised to 1/depth_scale m") if cfg.noise else None},
        "insert": {"frames": inserts, "mesh": "object.obj" if inserts else None,
                   "object": {**asdict(layout.insert), "type": (
                       "mesh (the file's, largest side 1, base on z=0; smooth normals)" if cfg.insert_mesh else
                       "box (unit cube, base on z=0)" + (", every face textured (object.mtl)" if cfg.insert_texture
                                                         else ""))},
                   "images": "insert/NNNNNN.png (sRGB) and .exr (linear, exposure applied); insert_mask/ 255 = virtual object"},
    })
    (out / PARTIAL_MARK).unlink()
    if final.exists():   # an empty folder (checked above), perhaps "." or a link: the files move into it
        for entry in sorted(out.iterdir(), key=lambda e: e.name == "scene.json"):   # scene.json last: whole
            os.replace(entry, final / entry.name)
        out.rmdir()
    else:
        os.replace(out, final)
    total = time.perf_counter() - t_start
    say(f"wrote {cfg.frames} frames to {final} in {total:.1f} s ({np.mean(per_frame):.2f} s/frame, "
        f"{mi.variant()}, exposure {exposure:.4g})")


def synth_command(args) -> int:
    """CLI wrapper: argparse namespace of `photoreg synth` -> generate()."""
    width, height = parse_size(args.size)
    cfg = SynthConfig(scene=args.scene, out=args.out, frames=args.frames, width=width, height=height, spp=args.spp,
                      env=args.env, yaw=args.yaw, seed=args.seed, camera=args.camera, direct_only=args.direct_only,
                      insert_frames=args.insert_frames, noise=not args.no_noise, mesh=args.mesh,
                      overexpose=args.overexpose, insert_texture=args.insert_texture, insert_mesh=args.insert_mesh,
                      shutter=args.shutter)
    generate(cfg, log=lambda msg: print(msg, flush=True))
    return 0
