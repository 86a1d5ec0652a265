"""`photoreg bench sweep`: speed against lighting error over stride x rays x bands x voxel size.

Recordings with ground truth (generated once with `photoreg synth` into a cache folder, or given) are
fused once per voxel size: one pipeline preprocesses and fuses each frame, and one pipeline per setting
(stride, rays, bands), sharing that volume, ray casts, samples, computes the transfer and solves on it
(Pipeline.observe / Pipeline.estimate), keeping its own temporal filter and exposure state. A setting's
frame time is the shared stages (preprocess, pose, fuse, dense export; the export counted in the ray
cast stage as in `bench speed`) plus its own; the first `warmup` frames of each recording are left
out of the timings. Errors are medians over all frames of all recordings (photoreg.bench.metrics).

Rows go to a CSV keyed by device + benchmark (size, scenes, frames) + setting (re-runs replace their rows, other
rows are kept) and a plot of frames/s against direction error and si-RMSE marks each series' Pareto front (a device
on one benchmark).
"""
from __future__ import annotations

import csv
import io
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..config import Session, validate
from ..io.atomic import atomic_path, check_output_file, write_text
from . import metrics
from .scenes import SCENE_CACHE, cached_scene, scene_kinds

DEFAULT_SCENES = ("tabletop", "corner")
STAGES = ("preprocess", "pose", "fuse", "raycast", "sample", "transfer", "solve", "sun", "total")
# a row is one setting on one device over one benchmark (its scenes and frames): a re-run replaces it, other rows stay
KEY = ("device", "device_name", "threads", "size", "scenes", "frames", "stride", "rays", "bands", "voxel_size")
COLUMNS = (*KEY, "frames_per_s", *(f"ms_{s}" for s in STAGES), "direction_deg", "si_rmse_upper", "si_rmse_sphere",
           "frames_timed", "warp", "open3d", "fusion_on", "date")


@dataclass(frozen=True)
class Setting:
    """One point of the grid."""

    stride: int
    rays: int
    bands: int
    voxel_size: float

    @property
    def label(self) -> str:
        return f"s{self.stride} r{self.rays} b{self.bands} v{self.voxel_size:g}"


def grid(strides, rays, bands, voxel_sizes) -> list[Setting]:
    """Every combination, voxel size outermost (the order the sweep fuses in)."""
    return [Setting(int(s), int(r), int(b), float(v))
            for v in voxel_sizes for s in strides for r in rays for b in bands]


def pareto_front(speed, error) -> np.ndarray:
    """Mask of the points no other point beats: none has speed >= and error <= with one of them strict.
    Points with a non-finite speed or error are never on the front."""
    s, e = np.asarray(speed, dtype=np.float64), np.asarray(error, dtype=np.float64)
    ok = np.isfinite(s) & np.isfinite(e)
    front = ok.copy()
    for i in np.flatnonzero(ok):
        beats = ok & (s >= s[i]) & (e <= e[i]) & ((s > s[i]) | (e < e[i]))
        front[i] = not beats.any()
    return front


def _session(st: Setting, device: str) -> Session:
    s = Session()
    s.device = device
    s.lighting.stride, s.lighting.rays, s.lighting.bands = st.stride, st.rays, st.bands
    s.reconstruction.voxel_size = st.voxel_size
    validate(s)
    return s


def run_sweep(recordings, settings: list[Setting], device: str = "auto", frames: int = 8, warmup: int = 2,
              progress=None) -> list[dict]:
    """Run every setting on the first `frames` frames of each recording; one result row per setting."""
    import open3d as o3d
    import warp as wp

    from ..io.recording import iter_frames, open_recording
    from ..pipeline import Pipeline
    from .score import load_gt
    from .speed import device_name

    if frames <= warmup:
        raise ValueError(f"sweep: --frames {frames} must exceed the {warmup} warm-up frames")
    if not settings:
        raise ValueError("sweep: empty grid")
    recs = []
    for path in recordings:
        rec = open_recording(path)
        if not rec.has_poses:
            raise ValueError(f"{path}: the sweep needs a recording with poses (groundtruth.txt)")
        if len(rec) <= warmup:
            raise ValueError(f"{path}: {len(rec)} frames, need more than the {warmup} warm-up frames")
        recs.append((Path(path), rec, load_gt(path)))
    times = {st: [] for st in settings}
    errors = {st: [] for st in settings}
    fusion_on, resolved = "", ""
    t_begin = time.perf_counter()
    for voxel in dict.fromkeys(st.voxel_size for st in settings):
        group = [st for st in settings if st.voxel_size == voxel]
        for path, rec, gt in recs:
            front = Pipeline(_session(group[0], device), rec.intrinsics)
            resolved, fusion_on = front.device, str(front.volume.o3d_device)
            pipes = {st: Pipeline(_session(st, device), rec.intrinsics, volume=front.volume) for st in group}
            indices = list(range(min(frames, len(rec))))
            for k, frame in enumerate(iter_frames(rec, indices)):
                shared: dict[str, float] = {}
                t0 = time.perf_counter()
                prep, pose, notes = front.observe(frame, shared)
                t1 = time.perf_counter()
                front.volume.dense_grid()  # the export every setting's ray cast stage would otherwise do first
                wp.synchronize_device(front.device)
                export_ms = (time.perf_counter() - t1) * 1000.0
                shared_ms = (time.perf_counter() - t0) * 1000.0
                for st, pipe in pipes.items():
                    r = pipe.estimate(frame, prep, pose, notes, {})
                    if k >= warmup:
                        t = {s: shared.get(s, 0.0) + r.timings_ms.get(s, 0.0) for s in STAGES}
                        t["raycast"] += export_ms
                        t["total"] = shared_ms + r.timings_ms["total"]
                        times[st].append(t)
                    sh_est = r.lighting.sh
                    errors[st].append(metrics.lighting_metrics(sh_est, gt) if np.isfinite(sh_est).all() else None)
                if progress:
                    progress(f"voxel {voxel:g} {path.name}: frame {k + 1}/{len(indices)}, {len(group)} settings, "
                             f"{time.perf_counter() - t_begin:.0f} s")
    common = {"device": resolved, "device_name": device_name(resolved),
              "threads": _threads_used(resolved), "size": "+".join(dict.fromkeys(
                  f"{rec.intrinsics.width}x{rec.intrinsics.height}" for _, rec, _ in recs)),
              "scenes": "+".join(p.name for p, _, _ in recs),
              "frames": "+".join(str(min(frames, len(rec))) for _, rec, _ in recs), "warp": wp.__version__,
              "open3d": o3d.__version__, "fusion_on": fusion_on,
              "date": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%MZ")}
    rows = []
    for st in settings:
        ms = {f"ms_{s}": float(np.mean([t[s] for t in times[st]])) for s in STAGES}
        ok = [e for e in errors[st] if e is not None]
        med = {k: float(np.median([e[key] for e in ok])) if ok else float("nan")
               for k, key in (("direction_deg", "direction_deg"), ("si_rmse_upper", "irradiance_si_rmse_upper"),
                              ("si_rmse_sphere", "irradiance_si_rmse_sphere"))}
        rows.append({**common, "stride": st.stride, "rays": st.rays, "bands": st.bands, "voxel_size": st.voxel_size,
                     "frames_per_s": 1000.0 / ms["ms_total"], **ms, **med, "frames_timed": len(times[st])})
    return rows


def _threads_used(device: str) -> int:
    """CPU threads of the split launches (0 on a GPU)."""
    from ..kernels.launch import cpu_threads

    return cpu_threads() if device == "cpu" else 0


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def read_csv(path: Path) -> list[dict]:
    """Rows (strings, every column of COLUMNS) of a table written by merge_csv."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no speed/error table")
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [k for k in KEY if k not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: not a speed/error table (columns {missing} missing)")
        rows = [{c: r.get(c) or "" for c in COLUMNS} for r in reader]
    for line, r in enumerate(rows, 2):
        try:
            float(r["voxel_size"]), int(r["stride"]), int(r["rays"]), int(r["bands"])
        except ValueError:
            raise ValueError(f"{path}:{line}: not a whole row of a speed/error table (stride {r['stride']!r}, rays "
                             f"{r['rays']!r}, bands {r['bands']!r}, voxel_size {r['voxel_size']!r})") from None
    return rows


def merge_csv(path: Path, rows: list[dict]) -> list[dict]:
    """Write `rows` into the CSV at `path` (atomically), replacing rows with the same KEY and keeping the
    others; returns every row as read back (strings)."""
    path = Path(path)
    new = [{c: _cell(r.get(c, "")) for c in COLUMNS} for r in rows]
    keys = {tuple(r[k] for k in KEY) for r in new}
    old = [r for r in read_csv(path) if tuple(r[k] for k in KEY) not in keys] if path.is_file() else []
    merged = sorted(old + new, key=lambda r: (r["device"], r["device_name"], r["threads"], r["size"], r["scenes"],
                                               r["frames"], float(r["voxel_size"]), int(r["stride"]), int(r["rays"]),
                                               int(r["bands"])))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows(merged)
    write_text(path, buf.getvalue())
    return merged


def series_label(row: dict) -> str:
    """Plot series of a row: the device by name, with the CPU thread count, and the benchmark (size, scenes, frames):
    the rows of one series compare alike."""
    dev = row["device"]
    extra = f", {row['threads']} threads" if dev == "cpu" else ""
    return f"{row['device_name']} ({dev}{extra}, {row['size']}, {row['scenes']} x {row['frames']} frames)"


def fronts(rows: list[dict], error: str) -> dict[str, list[dict]]:
    """Each series' Pareto-front rows for one error column, fastest first."""
    out = {}
    for label in dict.fromkeys(series_label(r) for r in rows):
        rs = [r for r in rows if series_label(r) == label]
        mask = pareto_front([float(r["frames_per_s"]) for r in rs], [float(r[error]) for r in rs])
        out[label] = sorted((r for r, m in zip(rs, mask) if m), key=lambda r: -float(r["frames_per_s"]))
    return out


def plot_pareto(rows: list[dict], path: Path) -> None:
    """PNG: frames/s against direction error and against si-RMSE, one colour per series, fronts joined."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    labels = list(dict.fromkeys(series_label(r) for r in rows))
    colours = plt.get_cmap("tab10")
    for ax, (col, name) in zip(axes, (("direction_deg", "direction error (deg, median)"),
                                      ("si_rmse_upper", "irradiance si-RMSE (upper hemisphere, median)"))):
        front = fronts(rows, col)
        for i, label in enumerate(labels):
            rs = [r for r in rows if series_label(r) == label]
            ax.scatter([float(r[col]) for r in rs], [float(r["frames_per_s"]) for r in rs], s=14, alpha=0.45,
                       color=colours(i % 10), label=label)
            f = sorted(front[label], key=lambda r: float(r[col]))
            ax.plot([float(r[col]) for r in f], [float(r["frames_per_s"]) for r in f], "-o", ms=7,
                    mfc="none", color=colours(i % 10), label=f"Pareto front, {label}")
            for r in f:
                ax.annotate(f"s{r['stride']} r{r['rays']} b{r['bands']} v{r['voxel_size']}",
                            (float(r[col]), float(r["frames_per_s"])), fontsize=6, xytext=(3, 3),
                            textcoords="offset points")
        ax.set_yscale("log")
        ax.set_xlabel(name)
        ax.set_ylabel("frames/s, full per-frame pipeline")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7, loc="best")
    fig.suptitle("photoreg bench sweep: speed against lighting error (s = stride, r = rays, b = bands, v = voxel m)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def _ints(text: str, what: str) -> list[int]:
    try:
        v = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--{what}: expected comma-separated integers, got {text!r}") from None
    if not v or min(v) < 1:
        raise ValueError(f"--{what}: expected positive integers, got {text!r}")
    return list(dict.fromkeys(v))   # each once


def _floats(text: str, what: str) -> list[float]:
    try:
        v = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--{what}: expected comma-separated numbers, got {text!r}") from None
    if not v or min(v) <= 0:
        raise ValueError(f"--{what}: expected positive numbers, got {text!r}")
    return list(dict.fromkeys(v))   # each once


def sweep_command(args) -> int:
    from ..kernels.launch import set_cpu_threads
    from ..synth.generate import parse_size

    if args.plot_only:
        rows = read_csv(Path(args.csv))
        plot_pareto(rows, Path(args.plot))
        print(f"wrote {args.plot} from {args.csv} ({len(rows)} rows)")
        return 0
    check_output_file(args.csv, "--csv")
    check_output_file(args.plot, "--plot")
    if Path(args.csv).is_file():
        read_csv(Path(args.csv))   # the table the rows are merged into: checked before hours of work
    if args.threads is not None:
        set_cpu_threads(args.threads)
    if args.warmup < 0:
        raise ValueError(f"--warmup must be >= 0, got {args.warmup}")
    kinds = None if args.recordings else scene_kinds(args.scenes)   # checked before any scene is rendered
    settings = grid(_ints(args.strides, "strides"), _ints(args.rays, "rays"), _ints(args.bands, "bands"),
                    _floats(args.voxel_sizes, "voxel-sizes"))
    for st in settings:   # every combination checked before scenes are rendered and frames run
        try:
            _session(st, args.device or "auto")
        except ValueError as e:
            raise ValueError(f"--strides / --rays / --bands / --voxel-sizes: the setting {st.label}: {e}") from None

    def log(msg: str) -> None:
        print(f"sweep: {msg}", file=sys.stderr, flush=True)

    if args.recordings:
        recordings = [Path(p) for p in args.recordings]
    else:
        width, height = parse_size(args.size)
        recordings = [cached_scene(Path(args.synth_dir or SCENE_CACHE), k, width, height, args.frames, args.spp,
                                   log=log) for k in kinds]
    log(f"{len(settings)} settings x {len(recordings)} recordings x up to {args.frames} frames each")
    rows: list[dict] = []
    # a voxel size at a time, its rows written as it ends: an interrupted sweep loses the running one's alone
    for voxel in dict.fromkeys(st.voxel_size for st in settings):
        group = run_sweep(recordings, [st for st in settings if st.voxel_size == voxel],
                          device=args.device or "auto", frames=args.frames, warmup=args.warmup, progress=log)
        merged = merge_csv(Path(args.csv), group)
        rows += group
    plot_pareto(merged, Path(args.plot))
    for st, r in zip(settings, rows):
        print(f"{r['device']:7s} {st.label:22s} {r['frames_per_s']:8.2f} frames/s"
              f"  direction {r['direction_deg']:6.2f} deg  si-RMSE {r['si_rmse_upper']:.4f}  transfer {r['ms_transfer']:.1f} ms  total {r['ms_total']:.1f} ms")
    for col in ("direction_deg", "si_rmse_upper"):
        for label, f in fronts(merged, col).items():
            print(f"Pareto front ({col}), {label}: " + "; ".join(
                f"s{r['stride']} r{r['rays']} b{r['bands']} v{r['voxel_size']} {float(r['frames_per_s']):.2f}/s "
                f"{float(r[col]):.3g}" for r in f))
    print(f"wrote {args.csv} ({len(merged)} rows) and {args.plot}")
    return 0
