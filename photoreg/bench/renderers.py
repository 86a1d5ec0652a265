"""`photoreg bench renderers`: every registered shadow renderer on the generator's insert scenes, side by side.

Per scene kind two recordings are generated once into a cache folder: an orbit with insert renders
(accuracy: RMSE and si-RMSE in the object's region of interest against the path tracer, as
`photoreg score --composite`) and a static camera (composite flicker, metrics.image_flicker over the
pixels any renderer changed). The pipeline runs each recording once with the session's renderer; at
every frame each registered renderer is applied to the same RenderInput (RenderStage.last_input), so
all renderers see the same lighting, geometry and G-buffer and differ only in how they shadow. Timing
is the renderer call alone (the layers; the shared G-buffer and the compositing are left out), after
one untimed warm-up call per renderer (kernel compilation, weight loading).

Rows go to benchmarks/results/renderers_<device>.json; the report (markdown table and a PNG of
ms per frame against si-RMSE) is rebuilt from every such file, so CPU and GPU runs end up side by side.
"""
from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from ..io.atomic import write_json, write_text
from . import metrics

RESULTS_GLOB = "renderers_*.json"


def scene_recordings(kind: str, cache: Path, size: tuple[int, int], frames: int, spp: int) -> tuple[Path, Path]:
    """(orbit recording with inserts, static recording) of `kind`, generated once into `cache`."""
    from ..synth.generate import SynthConfig, generate

    w, h = size
    paths = []
    for camera, inserts in (("orbit", "auto"), ("static", "none")):
        out = cache / f"{kind}_{camera}_{w}x{h}_{frames}f_{spp}spp"
        if not (out / "rgb.txt").is_file():
            print(f"bench renderers: generating {out.name} (once)", file=sys.stderr, flush=True)
            tmp = out.with_name(out.name + ".partial")
            if tmp.exists():
                shutil.rmtree(tmp)
            generate(SynthConfig(scene=kind, out=str(tmp), frames=frames, width=w, height=h, spp=spp,
                                 camera=camera, insert_frames=inserts), log=None)
            tmp.rename(out)
        paths.append(out)
    return paths[0], paths[1]


def run_all_renderers(session, frames: list[int], renderers: dict) -> dict[str, dict[int, tuple[np.ndarray, float]]]:
    """Run the pipeline over `frames` of the session's recording; at each frame every renderer on the same
    RenderInput: {renderer: {frame: (composite linear HxWx3, ms)}}."""
    from ..io.recording import iter_frames, open_recording
    from ..pipeline import Pipeline
    from ..render.composite import composite

    rec = open_recording(session.recording.path, fmt=session.recording.format)
    pipe = Pipeline(session, rec.intrinsics)
    if pipe.render is None:
        raise ValueError(f"{session.source}: the session has no [[objects]] to render")
    out: dict[str, dict[int, tuple[np.ndarray, float]]] = {name: {} for name in renderers}
    warm: set[str] = set()
    for k, frame in enumerate(iter_frames(rec, frames)):
        pipe.process(frame)
        inp = pipe.render.last_input
        if inp is None:
            continue
        for name, fn in renderers.items():
            if name not in warm:
                fn(inp)
                warm.add(name)
            t0 = time.perf_counter()
            layers = fn(inp)
            ms = (time.perf_counter() - t0) * 1000.0
            out[name][frame.index] = (composite(inp.camera, layers), ms)
        print(f"\rbench renderers: {Path(session.recording.path).name} frame {k + 1}/{len(frames)}", end="",
              file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return out


def _session_for(recording: Path, objects_from: Path, device: str):
    """The generator's session of `objects_from` (its insert object) on `recording`."""
    from ..config import load_session

    s = load_session(objects_from / "session.toml")
    s.recording.path, s.recording.format, s.device = str(recording), "native", device
    return s


def bench_scene(kind: str, orbit: Path, static: Path, device: str, renderers: dict) -> list[dict]:
    """Rows (one per renderer, plus the no-shadow baseline) of one scene kind."""
    from ..io.images import read_exr, read_rgb, srgb_to_linear
    from .score import color_files

    inserts = sorted(int(p.stem) for p in (orbit / "insert").glob("*.exr") if p.stem.isdigit())
    runs = run_all_renderers(_session_for(orbit, orbit, device), list(range(max(inserts) + 1)), renderers)
    n_static = len(color_files(static))
    still = run_all_renderers(_session_for(static, orbit, device), list(range(n_static)), renderers)
    cams = [srgb_to_linear(read_rgb(p)) for p in color_files(static)]
    region = np.any([np.abs(c[0] - cams[i]).max(axis=-1) > 1e-3
                     for r in still.values() for i, c in r.items()], axis=0)
    rows = []
    rgb = color_files(orbit)
    base = []
    for name, per_frame in runs.items():
        errs = []
        for i in inserts:
            gt = read_exr(orbit / "insert" / f"{i:06d}.exr")
            mask = cv2.imread(str(orbit / "insert_mask" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
            roi = metrics.roi_mask(mask)
            errs.append(metrics.composite_metrics(per_frame[i][0], gt, roi))
            if len(base) < len(inserts):
                camera = srgb_to_linear(read_rgb(rgb[i]))
                base.append(metrics.composite_metrics(metrics.no_shadow_baseline(camera, gt, mask), gt, roi))
        ms = [m for _, m in per_frame.values()] + [m for _, m in still[name].values()]
        rows.append({"scene": kind, "renderer": name, "ms_mean": float(np.mean(ms)),
                     "rmse": float(np.mean([e["rmse"] for e in errs])),
                     "si_rmse": float(np.mean([e["si_rmse"] for e in errs])),
                     "flicker": metrics.image_flicker([still[name][i][0] for i in sorted(still[name])], region),
                     "n_inserts": len(inserts)})
    rows.append({"scene": kind, "renderer": "baseline: path-traced object, no shadow", "ms_mean": None,
                 "rmse": float(np.mean([b["rmse"] for b in base])),
                 "si_rmse": float(np.mean([b["si_rmse"] for b in base])),
                 "flicker": metrics.image_flicker(cams, region), "n_inserts": len(inserts)})
    return rows


def write_report(results_dir: Path, md: Path, png: Path) -> None:
    """benchmarks/renderers.md and the PNG from every renderers_*.json in `results_dir`."""
    runs = [json.loads(p.read_text()) for p in sorted(results_dir.glob(RESULTS_GLOB))]
    lines = ["# Shadow renderers side by side", "",
             "Written by `photoreg bench renderers` from benchmarks/results/renderers_*.json. Every renderer "
             "runs on the same frames, lighting and G-buffer (photoreg/bench/renderers.py says how); error in "
             "linear RGB over the object's region of interest (mask dilated 40 px) against the path tracer, "
             "mean over the insert frames; flicker on a static camera over the pixels the insertion changed "
             "(the baseline row: the camera frames' own flicker there, i.e. render noise). ms: the renderer "
             "call alone, mean per frame.", ""]
    for run in runs:
        lines += [f"## {run['device_name']} ({run['device']})", "",
                  f"Command: `{run['command']}`; {run['date']}; Warp {run['warp']}, Open3D {run['open3d']}; "
                  f"{run['size']}, {run['frames']} frames per recording, {run['spp']} spp."
                  + (f" Note: {run['note']}." if run.get("note") else ""), "",
                  "| scene | renderer | ms/frame | RMSE | si-RMSE | flicker |", "|---|---|---:|---:|---:|---:|"]
        for r in run["rows"]:
            ms = "-" if r["ms_mean"] is None else f"{r['ms_mean']:.1f}"
            lines.append(f"| {r['scene']} | {r['renderer']} | {ms} | {r['rmse']:.4f} | {r['si_rmse']:.4f} | "
                         f"{r['flicker']:.4f} |")
        lines.append("")
    write_text(md, "\n".join(lines))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    markers = "osD^v<>"
    for k, run in enumerate(runs):
        names = sorted({r["renderer"] for r in run["rows"] if r["ms_mean"] is not None})
        for j, name in enumerate(names):
            rs = [r for r in run["rows"] if r["renderer"] == name]
            ax.scatter([r["ms_mean"] for r in rs], [r["si_rmse"] for r in rs], marker=markers[k % len(markers)],
                       color=f"C{j}", label=f"{name} ({run['device_name']})")
    ax.set_xscale("log")
    ax.set_xlabel("renderer ms per frame (log)")
    ax.set_ylabel("composite si-RMSE in the ROI (lower is better)")
    ax.set_title("Shadow renderers: speed against error (one point per scene kind)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = png.with_name(png.stem + ".partial.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(png)


def renderers_command(args) -> int:
    """CLI entry of `photoreg bench renderers`: run, write the device's JSON, rebuild the report."""
    import datetime

    import open3d as o3d
    import warp as wp

    from ..device import resolve_device
    from ..render.registry import RENDERERS
    from .speed import device_name

    names = args.renderers.split(",") if args.renderers else sorted(RENDERERS)
    unknown = [n for n in names if n not in RENDERERS]
    if unknown:
        raise ValueError(f"--renderers: unknown {unknown} (registered: {', '.join(sorted(RENDERERS))})")
    w, h = (int(x) for x in args.size.lower().split("x"))
    cache = Path(args.synth_dir or Path.home() / ".cache" / "photoreg" / "bench_scenes")
    cache.mkdir(parents=True, exist_ok=True)
    device = resolve_device(args.device or "auto")
    rows = []
    for kind in args.scenes.split(","):
        orbit, static = scene_recordings(kind, cache, (w, h), args.frames, args.spp)
        rows += bench_scene(kind, orbit, static, device, {n: RENDERERS[n] for n in names})
    results = Path(args.results_dir)
    run = {"device": device, "device_name": device_name(device), "warp": wp.__version__, "open3d": o3d.__version__,
           "command": "photoreg " + " ".join(sys.argv[1:]), "date": datetime.date.today().isoformat(),
           "size": f"{w}x{h}", "frames": args.frames, "spp": args.spp, "rows": rows}
    write_json(results / f"renderers_{device.split(':')[0]}.json", run)
    write_report(results, Path(args.md), Path(args.plot))
    for r in rows:
        ms = "-" if r["ms_mean"] is None else f"{r['ms_mean']:8.1f}"
        print(f"{r['scene']:12s} {r['renderer']:40s} ms {ms}  rmse {r['rmse']:.4f}  si-rmse {r['si_rmse']:.4f}  "
              f"flicker {r['flicker']:.4f}")
    print(f"report: {args.md}, {args.plot}")
    return 0
