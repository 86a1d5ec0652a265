"""Run configuration as dataclasses; TOML session files (sessions/*.toml) load into them.

Unknown keys, wrong types and missing files are errors naming the file and the key, raised before
any frame is processed. Relative paths are relative to the session file's folder.
"""
from __future__ import annotations

import dataclasses
import math
import os
import sys
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from .io.text import read_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


@dataclass
class RecordingConfig:
    path: str = ""
    format: str = "auto"          # auto | native | tum | redwood | 7scenes
    undistort: bool = False
    use_poses: bool = True        # False: track the camera (frame-to-model odometry)
    # Seconds added to the frames' times where poses given by time (TUM groundtruth.txt) are looked up: a motion-capture
    # clock's offset against the colour camera's, which slides an inserted object over the frames as the camera turns
    # (benchmarks/pose_offset.py measures it; TUM fr1_rpy's is 0: benchmarks/tracking.md, "The poses' clock").
    pose_time_offset: float = 0.0


@dataclass
class ReconstructionConfig:
    voxel_size: float = 0.01      # metres
    trunc_voxels: float = 4.0     # truncation distance in voxels
    depth_min: float = 0.1        # metres
    depth_max: float = 4.0        # metres
    block_count: int = 6000       # initial Open3D hash-map capacity in 16^3-voxel blocks (32 KB each: 200 MB); grows on demand
    # Edge-preserving (bilateral) filter of the depth before fusion and sampling, as KinectFusion does: a window
    # of this many pixels (odd; 0 = off), spatial sigma half of it (rounded down), range sigma depth_filter_m
    # (steps larger than a few of it are kept). Generated scenes (12 frames): 9 px / 2 cm took tabletop to 6.1 deg
    # / si-RMSE 0.082 (9.2 / 0.087), corner 0.199 -> 0.159, but the 40-frame tabletop 0.083 -> 0.092 and TUM's
    # held-out residual 0.216 -> 0.224; 5 px / 1 cm: corner 0.165, tabletop 0.086, the 40-frame one 0.085, TUM
    # 0.219, but flicker up (ICL-NUIM 0.038 -> 0.053) (benchmarks/lighting_accuracy.md): off until understood.
    depth_filter_px: int = 0
    depth_filter_m: float = 0.02
    # Ray-cast normals averaged over this radius (voxels) in the tangent plane, edges kept (photoreg.kernels.
    # raycast; 0 = off). The depth noise reaches the lighting mostly through the normals; 3 voxels: generated
    # 12-frame scenes tabletop 9.2 -> 6.2 deg / si-RMSE 0.087 -> 0.080, corner 0.199 -> 0.165, coloured 0.139 ->
    # 0.117, but the 40-frame tabletop 0.083 -> 0.091, TUM held-out 0.216 -> 0.219 and flicker up on both real
    # recordings (benchmarks/lighting_accuracy.md, rows "normal_smoothing_voxels 3"): for sparse captures.
    normal_smoothing_voxels: float = 0.0


@dataclass
class LightingConfig:
    bands: int = 5                # SH bands B (B*B coefficients); 5 beat 3 (benchmarks/lighting_accuracy.md)
    rays: int = 64                # visibility rays per sample over the hemisphere
    stride: int = 4               # sample every n-th pixel in x and y
    # Odd box (pixels) whose mean radiance a sample takes, the whole box usable; 0: stride | 1 (the stride's cell).
    # 3 at stride 4, 3 seeds x 9 generated recordings: si-RMSE 0.098 against 0.106, the same flicker; on the real
    # recordings no better (ICL-NUIM flicker 0.059 against 0.037; benchmarks/lighting_accuracy.md, "sample_box 3")
    sample_box: int = 0
    ray_length: float = 0.5       # metres
    ray_offset_voxels: float = 1.5
    min_visible: float = 0.05     # drop samples with >95% of rays blocked (paper)
    weighting: str = "bins"       # bins | density | none (normal-distribution weighting)
    regularization: float = 1e-2  # Tikhonov strength, relative to the data scale (measured best: tests/test_solver.py)
    mode: str = "rgb"             # rgb | white
    saturation_level: int = 250   # 8-bit value at or above which a pixel counts as saturated
    # Saturated pixels (with valid depth) kept: a sample box holding some is measured as it is, one holding nothing
    # else is a lower bound of the radiance (censored: photoreg.lighting.robust); false leaves every box with one out.
    # For sunlit surfaces that saturate (a tabletop whose sunlit floor does, 5-10% of the pixels: 7 degrees / si-RMSE
    # 0.13 against 20 / 0.24); off by default: where windows or lamps saturate (ICL-NUIM) it doubled the flicker
    # and the held-out residual (benchmarks/lighting_accuracy.md, "Saturated pixels as lower bounds")
    censored: bool = False
    black_level: int = 3          # 8-bit value at or below which a pixel counts as black
    denoise: str = "none"         # none | tvl1 | guided: edge-preserving luminance denoising
    # Robust lighting (issue 4; photoreg.lighting.robust, benchmarks/lighting_accuracy.md). All "off" values
    # (loss none, albedo single, select fixed, checks 180/inf, temporal and exposure false) give the paper's solver.
    loss: str = "huber"           # none | huber | tukey: IRLS loss on luminance residuals
    albedo: str = "regions"       # single | regions: one albedo, or per-region albedo solved jointly
    albedo_reference: str = "max"  # max | largest | mean: the region whose albedo fixes the scale ambiguity
    # alternate | joint: F then albedos in turn, or a joint Gauss-Newton step in both (robust.py). joint
    # converges in a few steps (alternate still moves 1% per step after 12 on the tabletop) and fits tabletop
    # better, but the demo's later frames and its inserted object worse (benchmarks/lighting_accuracy.md)
    albedo_step: str = "alternate"
    reference_albedo: float = 0.8  # ... taken to have this albedo: F in absolute units (objects' albedos)
    select: str = "fixed"         # fixed | gcv | holdout | aic | bic: per-frame band count and regularisation
    max_bands: int = 5            # largest band count tried when select is not fixed
    max_samples: int = 8000       # random subsample of the usable samples per solve (solve time is linear in it)
    bin_min_fraction: float = 0.01  # normal bins with fewer samples than this share get less weight
    # Normal bins counted per albedo region (photoreg.lighting.solver): generated tabletops' mean si-RMSE
    # 0.169 -> 0.115 (benchmarks/lighting_accuracy.py --ablations: rows "no region weights").
    region_weights: bool = True
    max_normal_angle: float = 30.0  # degrees: drop samples whose fused normal disagrees with the frame's depth
    max_depth_gap_voxels: float = 3.0  # ... or whose fused surface is this far from the frame's depth
    temporal: bool = True         # Kalman filter of the SH across frames (photoreg.lighting.temporal)
    process_noise: float = 0.02   # filter random-walk step, share of a frame's measurement variance
    change_threshold: float = 1.0  # restart the filter when the prediction fits (1 + this) x worse than usual
    # Share of the filter's precision kept when a frame reaches a new view of the history (photoreg.lighting.
    # temporal): the solve already holds the earlier views' samples. Generated 12-frame tabletop: direction
    # 12.6 -> 9.5 degrees, si-RMSE 0.096 -> 0.086 at 0.3; 0.1: 8.8 / 0.087 but ICL-NUIM flicker 0.037 -> 0.044
    # instead of 0.040 (benchmarks/lighting_accuracy.md).
    new_view_share: float = 0.3
    # Samples of earlier frames solved with the current ones (photoreg.lighting.history): a random subset of at
    # most this many in which older views fade, 0 = the current view only.
    history: int = 8000
    # A frame whose camera is within this many degrees of the newest kept view replaces that view's samples
    # instead of joining as a new view (photoreg.lighting.history), so dense recordings keep distinct views;
    # 0 = every frame is a new view.
    history_view_deg: float = 10.0
    # Estimate the lighting on every n-th frame with a pose (1: every frame). The frames between still fuse, ray
    # cast and composite, with the latest estimate and their own exposure gain: the host-side solve sets the
    # frame rate on a GPU (benchmarks/gpu.md), and a lighting change is followed at most n - 1 frames later.
    every: int = 1
    # Estimate the lighting in a worker thread beside the frames (live use): each frame composites with the latest
    # finished estimate, and a new one starts from the first frame that finds the worker free (and `every` due).
    # The first frame is estimated in line. The lighting lags by about one estimate (TUM on the H100: 3.6-5.6 frames,
    # 55-85 ms, at 64-83 frames/s; benchmarks/gpu.md); which frame's samples gave it: diagnostics.estimated_frame.
    asynchronous: bool = False
    # ... and its robust solves in a child process of their own: the frames and the solve then share no interpreter
    # lock (beside the worker thread a frame's host work took 13-16 ms instead of 7.5-8 on the H100; gpu.md)
    solve_process: bool = True
    exposure: bool = True         # per-frame gain against the fused radiance (auto-exposure)
    bounce: bool = True           # one bounce in the model: directions blocked by real geometry see radiance e
    # ... and those whose hit point the camera has seen, its fused luminance (photoreg.lighting.bounce)
    bounce_observed: bool = True
    sun: bool = True              # trace the dominant light apart from the SH (photoreg.lighting.sun; fixed bands)
    sun_candidates: int = 256     # coarse directions searched over the sphere
    sun_samples: int = 1500       # samples traced per candidate direction
    sun_min_gain: float = 0.05    # hold a light whose mean share of the residual explained is at least this
    sun_rays: int = 8             # rays over the light's disc in the joint solve
    # Frames between refinements of a held light's direction; the frames between hold it as last refined and
    # need no solve of the current view alone (photoreg.lighting.sun), one solve a frame instead of two plus
    # the refinement, unless the joint fit with it turns stale (a light switched: refined then after all).
    # 5 (the coarse passes' spacing; a newly held light is refined every frame for 5 frames) against 1: the
    # demo's median frame 1.5-1.6x faster on the H100 (benchmarks/gpu.md), the same mean accuracy over the
    # generated recordings that hold a light (benchmarks/lighting_accuracy.md, rows "sun_refine_every 1").
    sun_refine_every: int = 5
    # Tikhonov strength (relative, as `regularization`) of the SH part in the joint solve with a traced light.
    # With the light apart the SH holds only the smooth sky and the bounce; at 1e-2 it also took up the
    # light's share (generated tabletop: irradiance too flat, sun/sky 0.56 of the truth). si-RMSE, tabletop /
    # demo's 40 frames: 2e-2 0.155 / 0.145, 3e-2 0.148 / 0.139, 5e-2 0.142 / 0.156; the
    # demo's inserted object is 9% too bright at 2e-2 and 10% at 3e-2 (tests/test_render.py allows 10%).
    # Recordings where no light is held (corner, coloured, plane) do not change.
    sun_regularization: float = 2e-2


@dataclass
class ObjectConfig:
    mesh: str = ""
    position: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    rotation: list = field(default_factory=lambda: [0.0, 0.0, 0.0])  # degrees, scipy 'xyz'
    scale: float = 1.0
    albedo: list | str = field(default_factory=lambda: [0.8, 0.8, 0.8])   # linear RGB, or "texture" (the mesh's)
    smooth: bool = False   # shade with the vertex normals interpolated over each face (else each face's own normal)


ALBEDO_TEXTURE = "texture"   # objects.albedo: the mesh's base-colour texture instead of one colour
SHUTTER_CAMERA = "camera"    # render.shutter: the shutter time the camera gives (Frame.shutter)


@dataclass
class RenderConfig:
    shadows: str = "voxel"        # voxel | shadowmap | neural_soft | neural_shadowmap | none
    light_rays: int = 16          # voxel: rays over the dominant light's disc (sharp shadows); 0 = pure SH (paper)
    stride: int = 4               # the shadow ratio sampled every n-th pixel (full resolution along the objects'
                                  # silhouettes), whatever lighting.stride is
    gbuffer: str = "pyrender"     # pyrender (rasterised, OpenGL) | raycast (Warp rays through the objects' BVH)
    shutter: float | str = SHUTTER_CAMERA  # seconds the camera's shutter is open: the objects and their shadows
                                  # blurred by the camera's motion as the frame is (photoreg.render.motion_blur);
                                  # "camera": each frame's own (the recording's calibration, a streamed frame's), else
                                  # sharp


@dataclass
class OutputConfig:
    dir: str = "out"
    pictures_every: int = 10      # write lat-long and lit-sphere pictures every k-th frame (0 = never)
    video: bool = False           # also composite.mp4, the composites as a video (needs [[objects]])


@dataclass
class Session:
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    lighting: LightingConfig = field(default_factory=LightingConfig)
    objects: list = field(default_factory=list)   # list[ObjectConfig]
    render: RenderConfig = field(default_factory=RenderConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    device: str = "auto"
    frames: str = ""              # "", "N", "A:B" or "A:B:S"
    source: str = ""              # the session file, for messages


SHADOW_RENDERERS = ("voxel", "shadowmap", "neural_soft", "neural_shadowmap", "none")  # [render] shadows
GBUFFER_BACKENDS = ("pyrender", "raycast")   # [render] gbuffer

_CHOICES = {
    ("recording", "format"): {"auto", "native", "tum", "redwood", "7scenes"},
    ("lighting", "weighting"): {"bins", "density", "none"},
    ("lighting", "mode"): {"rgb", "white"},
    ("lighting", "denoise"): {"none", "tvl1", "guided"},
    ("lighting", "loss"): {"none", "huber", "tukey"},
    ("lighting", "albedo"): {"single", "regions"},
    ("lighting", "albedo_reference"): {"max", "largest", "mean"},
    ("lighting", "albedo_step"): {"alternate", "joint"},
    ("lighting", "select"): {"fixed", "gcv", "holdout", "aic", "bic"},
    ("render", "shadows"): set(SHADOW_RENDERERS),
    ("render", "gbuffer"): set(GBUFFER_BACKENDS),
    ("", "device"): {"auto", "cpu", "cuda"},
}


def _check_value(where: str, name: str, value, typ):
    origin = typing.get_origin(typ)
    if origin in (typing.Union, types.UnionType):   # X | Y: the first that takes the value
        for member in typing.get_args(typ):
            try:
                return _check_value(where, name, value, member)
            except ValueError:
                pass
        names = " or ".join(getattr(m, "__name__", str(m)) for m in typing.get_args(typ))
        raise ValueError(f"{where}: key '{name}' must be {names}, got {value!r}")
    if typ is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if typ is list or origin is list:
        if not isinstance(value, list):
            raise ValueError(f"{where}: key '{name}' must be a list, got {type(value).__name__}")
        return value
    if isinstance(typ, type) and isinstance(value, typ) and not (typ is int and isinstance(value, bool)):
        return value
    raise ValueError(f"{where}: key '{name}' must be {getattr(typ, '__name__', typ)}, got {value!r}")


def _fill(cls, data: dict, where: str, section: str):
    if not isinstance(data, dict):
        raise ValueError(f"{where}: [{section}] must be a table")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        name = f"{section}.{key}" if section else key
        if key not in known:
            raise ValueError(f"{where}: unknown key '{name}' (known: {', '.join(sorted(known))})")
        v = _check_value(where, name, value, hints[key])
        choices = _CHOICES.get((section, key))
        if choices and v not in choices:
            raise ValueError(f"{where}: key '{name}' must be one of {sorted(choices)}, got {v!r}")
        kwargs[key] = v
    return cls(**kwargs)


def _check_object(obj: ObjectConfig, where: str, name: str = "objects") -> None:
    """Range checks of one object; `name` says which in the messages ("objects[2]")."""
    import numpy as np

    for key, n in (("position", 3), ("rotation", 3), ("albedo", 3)):
        v = getattr(obj, key)
        if key == "albedo" and isinstance(v, str):
            if v != ALBEDO_TEXTURE:
                raise ValueError(f"{where}: {name}.albedo must be 3 finite numbers or {ALBEDO_TEXTURE!r}, got {v!r}")
            continue
        # a boolean is not a number here (true read as 1.0 before)
        if len(v) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x)
                                  for x in v):
            raise ValueError(f"{where}: {name}.{key} must be {n} finite numbers, got {v!r}")
        if key == "albedo" and not all(0 <= x <= 1 for x in v):
            raise ValueError(f"{where}: {name}.albedo must be reflectances in 0..1 (linear RGB), got {v!r}")
    if not (np.isfinite(obj.scale) and obj.scale > 0):
        raise ValueError(f"{where}: {name}.scale must be a positive finite number, got {obj.scale!r}")
    if not obj.mesh:
        raise ValueError(f"{where}: {name}.mesh is required")


def load_session(path: str | Path, files: bool = True) -> Session:
    """Parse and validate a session file; paths are resolved against its folder. files=False: the recording, meshes
    and output folder are kept as written and not looked for (a client asking a server, which has its own, for what
    the session does)."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: a folder, not a session file (.toml)")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: session file not found")
    try:
        raw = tomllib.loads(read_text(path))
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: not valid TOML: {e}") from None
    where = str(path)
    base = path.parent
    s = Session(source=where)
    sections = {"recording": RecordingConfig, "reconstruction": ReconstructionConfig, "lighting": LightingConfig,
                "render": RenderConfig, "output": OutputConfig}
    for key, value in raw.items():
        if key in sections:
            setattr(s, key, _fill(sections[key], value, where, key))
        elif key == "objects":
            if not isinstance(value, list):
                raise ValueError(f"{where}: 'objects' must be an array of tables ([[objects]])")
            s.objects = [_fill(ObjectConfig, v, where, f"objects[{i}]") for i, v in enumerate(value)]
        elif key in ("device", "frames"):
            setattr(s, key, getattr(_fill(Session, {key: value}, where, ""), key))
        else:
            raise ValueError(f"{where}: unknown section or key '{key}' "
                             f"(known: {', '.join(sorted([*sections, 'objects', 'device', 'frames']))})")
    if not s.recording.path:
        raise ValueError(f"{where}: key 'recording.path' is required")
    validate(s)   # the objects' checks among them, before their paths are resolved
    if files:
        s.recording.path = str(resolve_path(s.recording.path, base, f"{where}: recording.path"))
        if not Path(s.recording.path).exists():
            raise FileNotFoundError(f"{where}: recording.path {s.recording.path} does not exist")
        for obj in s.objects:
            obj.mesh = str(resolve_path(obj.mesh, base, f"{where}: objects.mesh"))
            if not Path(obj.mesh).is_file():
                raise FileNotFoundError(f"{where}: objects.mesh {obj.mesh} does not exist")
        s.output.dir = str(resolve_path(s.output.dir, base, f"{where}: output.dir"))
    return s


def resolve_path(p: str, base: Path, what: str) -> Path:
    """Expand ~ and $PHOTOREG_DATA-style variables ($$ for a $ of the name itself); relative paths are taken from
    `base`. A variable that is not set is an error naming it (`what`: the file and key, for the message)."""
    import os
    import re

    pieces = p.split("$$")
    unset = [m[0] or m[1] for piece in pieces for m in re.findall(r"\$\{(\w+)\}|\$(\w+)", piece)
             if (m[0] or m[1]) not in os.environ]
    if unset:
        raise ValueError(f"{what} {p!r}: environment variable {', '.join(unset)} is not set")
    q = Path(os.path.expanduser("$".join(os.path.expandvars(piece) for piece in pieces)))
    return q if q.is_absolute() else (base / q).resolve()


MAX_POSE_TIME_OFFSET = 1.0   # seconds: recording.pose_time_offset (a clock's offset, not a recording's start)
MAX_STRIDE = 64   # lighting.stride, render.stride: a sample's box grows with the stride (stride | 1 pixels square)
MAX_RAYS = 4096   # lighting.rays: the paper's 169 and the sweep's 300 well inside; 1e8 asked for 37 GB at once
MAX_BLOCK_COUNT = 1 << 20   # reconstruction.block_count: the hash map's initial blocks, 32 KB each


def check_pose_time_offset(seconds: float, what: str) -> None:
    """ValueError naming `what` unless seconds is a finite number within MAX_POSE_TIME_OFFSET of 0."""
    if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and abs(seconds) <= MAX_POSE_TIME_OFFSET):
        raise ValueError(f"{what} must be seconds in -{MAX_POSE_TIME_OFFSET:g}..{MAX_POSE_TIME_OFFSET:g}, "
                         f"got {seconds!r}")


def validate(s: Session) -> None:
    """Range checks shared by session files and command-line overrides."""
    where = s.source or "options"
    L, R = s.lighting, s.reconstruction
    try:
        parse_frames(s.frames, 0)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    for section in ("recording", "reconstruction", "lighting", "render", "output"):   # a Session built in code
        cfg = getattr(s, section)                                                     # is checked as a file's is
        hints = typing.get_type_hints(type(cfg))
        for f in dataclasses.fields(cfg):
            if isinstance(getattr(cfg, f.name), os.PathLike):   # a path built in code (recording.path, output.dir)
                setattr(cfg, f.name, os.fspath(getattr(cfg, f.name)))
            v = _check_value(where, f"{section}.{f.name}", getattr(cfg, f.name), hints[f.name])
            choices = _CHOICES.get((section, f.name))
            if choices and v not in choices:
                raise ValueError(f"{where}: key '{section}.{f.name}' must be one of {sorted(choices)}, got {v!r}")
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{where}: {section}.{f.name} must be a finite number, got {v}")
    for i, obj in enumerate(s.objects):
        _check_object(obj, where, f"objects[{i}]")
    fitted = L.bands if L.select == "fixed" else L.max_bands   # the most bands a solve may fit
    check_pose_time_offset(s.recording.pose_time_offset, f"{where}: recording.pose_time_offset")
    checks = [(1 <= L.bands <= 8, "lighting.bands must be in 1..8"),
              (1 <= L.rays <= MAX_RAYS, f"lighting.rays must be in 1..{MAX_RAYS}"),
              (2 * L.rays >= fitted ** 2,   # every transfer vector is a sum over the 2 x rays directions of one set
               f"lighting.rays must be >= {-(-fitted ** 2 // 2)} for {fitted} bands ({fitted ** 2} coefficients; the "
               f"transfer vectors span at most 2 x rays directions): more rays or fewer bands"),
              (1 <= L.stride <= MAX_STRIDE, f"lighting.stride must be in 1..{MAX_STRIDE}"),
              (L.sample_box == 0 or (L.sample_box % 2 == 1 and 1 <= L.sample_box <= 15),
               "lighting.sample_box must be 0 (stride | 1) or odd in 1..15"),
              (L.ray_length > 0, "lighting.ray_length must be > 0"),
              (L.ray_offset_voxels >= 0, "lighting.ray_offset_voxels must be >= 0"),
              (0 <= L.black_level < L.saturation_level <= 256,
               "lighting.black_level and saturation_level must be 8-bit levels, 0 <= black_level < saturation_level "
               "<= 256 (256: nothing saturates)"),
              (L.sun_candidates >= 8 and L.sun_samples >= 10 and L.sun_rays >= 1 and 0 <= L.sun_min_gain < 1,
               "lighting.sun_candidates must be >= 8, sun_samples >= 10, sun_rays >= 1 and sun_min_gain in [0, 1)"),
              (0 <= L.min_visible < 1, "lighting.min_visible must be in [0, 1)"),
              (L.regularization >= 0, "lighting.regularization must be >= 0"),
              (L.sun_regularization >= 0, "lighting.sun_regularization must be >= 0"),
              (L.sun_refine_every >= 1, "lighting.sun_refine_every must be >= 1"),
              (0.01 <= L.reference_albedo <= 1, "lighting.reference_albedo must be in [0.01, 1]"),
              (1 <= L.max_bands <= 8, "lighting.max_bands must be in 1..8"),
              (L.max_samples >= 1, "lighting.max_samples must be >= 1"),
              (0 <= L.bin_min_fraction < 1, "lighting.bin_min_fraction must be in [0, 1)"),
              (0 < L.max_normal_angle <= 180, "lighting.max_normal_angle must be in (0, 180]"),
              (L.max_depth_gap_voxels > 0, "lighting.max_depth_gap_voxels must be > 0"),
              (L.history >= 0, "lighting.history must be >= 0"),
              (L.history_view_deg >= 0, "lighting.history_view_deg must be >= 0"),
              (L.every >= 1, "lighting.every must be >= 1"),
              (L.process_noise >= 0 and L.change_threshold > 0,
               "lighting.process_noise must be >= 0 and lighting.change_threshold > 0"),
              (0 < L.new_view_share <= 1, "lighting.new_view_share must be in (0, 1]"),
              (s.render.light_rays >= 0, "render.light_rays must be >= 0"),
              (1 <= s.render.stride <= MAX_STRIDE, f"render.stride must be in 1..{MAX_STRIDE}"),
              (s.render.shutter == SHUTTER_CAMERA or (not isinstance(s.render.shutter, str)
                                                      and 0 <= s.render.shutter <= 1),
               f"render.shutter must be seconds in 0..1 or {SHUTTER_CAMERA!r}"),
              (not s.output.video or bool(s.objects), "output.video needs [[objects]]: the video shows the composites"),
              (R.voxel_size > 0, "reconstruction.voxel_size must be > 0"),
              (R.trunc_voxels > 0, "reconstruction.trunc_voxels must be > 0"),
              (1 <= R.block_count <= MAX_BLOCK_COUNT, f"reconstruction.block_count must be in 1..{MAX_BLOCK_COUNT} "
                                                      "(16^3-voxel blocks of 32 KB: 32 GB at most)"),
              (s.output.pictures_every >= 0, "output.pictures_every must be >= 0"),
              (0 < R.depth_min < R.depth_max, "reconstruction.depth_min must be > 0 and < depth_max"),
              (R.depth_filter_px == 0 or (R.depth_filter_px % 2 == 1 and 3 <= R.depth_filter_px <= 15),
               "reconstruction.depth_filter_px must be 0 (off) or odd in 3..15"),
              (R.depth_filter_m > 0, "reconstruction.depth_filter_m must be > 0"),
              (0 <= R.normal_smoothing_voxels <= 8, "reconstruction.normal_smoothing_voxels must be in 0..8")]
    for ok, msg in checks:
        if not ok:
            raise ValueError(f"{where}: {msg}")


def select_frames(spec: str, n: int, source: str) -> list[int]:
    """parse_frames of a recording (`source`, for the message) of n frames, refusing a selection of none."""
    indices = parse_frames(spec, n)
    if not indices:
        raise ValueError(f"{source}: no frames selected (recording has {n}, --frames {spec!r})")
    return indices


def parse_frames(spec: str, n: int) -> list[int]:
    """'' -> all; 'N' -> first N; 'A:B' or 'A:B:S' -> range (end exclusive, clipped to n); numbers >= 0, S >= 1."""
    if not spec:
        return list(range(n))
    try:
        parts = [int(x) if x.strip() else None for x in spec.split(":")]
    except ValueError:
        parts = []
    bad = (not 1 <= len(parts) <= 3 or (len(parts) == 1 and parts[0] is None)
           or any(x is not None and x < 0 for x in parts) or (len(parts) == 3 and parts[2] == 0))
    if bad:
        raise ValueError(f"frames (--frames): expected N, A:B or A:B:S with numbers >= 0 and S >= 1, got {spec!r}")
    if len(parts) == 1:
        return list(range(min(parts[0], n)))
    return list(range(n))[slice(*parts)]
