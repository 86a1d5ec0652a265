"""`photoreg bench renderers`: every registered shadow renderer on the generator's insert scenes, side by side.

Per scene kind two recordings are generated once into a cache folder: an orbit with insert renders
(accuracy: RMSE and si-RMSE in the object's region of interest against the path tracer, as
`photoreg score --composite`) and a static camera (composite flicker, metrics.image_flicker over the
pixels any renderer changed). The pipeline runs each recording once with the session's renderer; at
every frame each registered renderer is applied to the same RenderInput (RenderStage.last_input), so
all renderers see the same lighting, geometry and G-buffer and differ only in how they shadow. Timing
is the renderer call alone (the layers; the shared G-buffer and the compositing are left out), after
one untimed warm-up call per renderer (kernel compilation, weight loading). On the orbit each renderer
also runs with the generator's true light (the error left is the renderer's), and the no-shadow baseline
is scored twice: with the path tracer's own object and with that object rendered again with other seeds
(synth.generate.rerender_inserts; the baseline without the advantage of sharing the ground truth's noise).

Rows go to benchmarks/results/renderers_<device>_<spp>spp.json, the scenes run replacing their rows and the
others' kept (a file of another size or frame count is refused before any work); the report (markdown table and a
PNG of ms per frame against si-RMSE) is rebuilt from every such file, so CPU and GPU runs end up side by side.
"""
from __future__ import annotations

import importlib.util
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..io.atomic import check_output_dir, check_output_file, write_json, write_text
from ..lighting import sh
from . import metrics
from .scenes import SCENE_CACHE, cached_scene, scene_kinds

RESULTS_GLOB = "renderers_*.json"
RUN_KEYS = ("device_name", "size", "frames", "spp", "rows")   # what the report reads of a results file


def run_all_renderers(session, frames: list[int], renderers: dict,
                      light: tuple[np.ndarray, dict | None] | None = None) -> dict[str, dict[int, tuple[np.ndarray, float]]]:
    """Run the pipeline over `frames` of the session's recording; at each frame every renderer on the same
    RenderInput: {renderer: {frame: (composite linear HxWx3, ms)}}. With `light` (score.true_light: the
    generator's SH, at full band count, and sun) each renderer also runs with it in place of the estimate, as
    "<renderer>, true light" (ms of those calls: NaN)."""
    from ..io.recording import iter_frames, open_configured
    from ..pipeline import Pipeline
    from ..render.composite import composite

    rec = open_configured(session.recording)
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
            if light is not None:
                true = replace(inp, F=sh.truncate(light[0], sh.bands_of(inp.F.shape[1])), gain=1.0, sun=light[1])
                out.setdefault(f"{name}, true light", {})[frame.index] = (composite(inp.camera, fn(true)), math.nan)
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
    """Rows of one scene kind: per renderer with the estimated lighting and with the generator's (error only;
    what is left is the renderer's), the no-shadow baseline, and that baseline with an object path-traced
    again with other seeds (the noise floor: no renderer shares the ground truth's own Monte Carlo noise)."""
    from ..io.images import read_rgb, srgb_to_linear
    from ..synth.generate import rerender_inserts
    from .score import color_files, insert_truth, true_light

    truths = insert_truth(orbit)
    runs = run_all_renderers(_session_for(orbit, orbit, device), list(range(truths[-1].frame + 1)), renderers,
                             true_light(orbit))
    cams = [srgb_to_linear(read_rgb(p)) for p in color_files(static)]
    still = run_all_renderers(_session_for(static, orbit, device), list(range(len(cams))), renderers)
    region = metrics.changed_region([c for r in still.values() for c, _ in r.values()],
                                    [cams[i] for r in still.values() for i in r])

    def row(name: str, errs: list[dict], ms, flicker: float | None) -> dict:
        return {"scene": kind, "renderer": name, "ms_mean": ms, "rmse": float(np.mean([e["rmse"] for e in errs])),
                "si_rmse": float(np.mean([e["si_rmse"] for e in errs])), "flicker": flicker,
                "n_inserts": len(truths)}

    rows = []
    for name, per_frame in runs.items():
        errs = [metrics.composite_metrics(per_frame[t.frame][0], t.gt, t.roi) for t in truths]
        if name not in still:   # a true-light run: accuracy only
            rows.append(row(name, errs, None, None))
            continue
        ms = [m for _, m in per_frame.values()] + [m for _, m in still[name].values()]
        rows.append(row(name, errs, float(np.mean(ms)),
                        metrics.image_flicker([still[name][i][0] for i in sorted(still[name])], region)))
    rows.append(row("baseline: path-traced object, no shadow", [t.baseline() for t in truths], None,
                    metrics.image_flicker(cams, region)))
    if importlib.util.find_spec("mitsuba") is None:   # cached scenes on a machine without the path tracer
        print(f"bench renderers: {kind}: no row 'baseline, object path-traced with other seeds' (it needs "
              "Mitsuba 3: pip install 'photoreg[synth]')", file=sys.stderr)
        return rows
    print(f"bench renderers: {kind}: the insert frames path-traced again with other seeds", file=sys.stderr,
          flush=True)
    again = rerender_inserts(orbit)
    rows.append(row("baseline, object path-traced with other seeds", [metrics.composite_metrics(
        metrics.no_shadow_baseline(t.camera, again[t.frame], t.mask), t.gt, t.roi) for t in truths], None, None))
    return rows


def load_runs(results_dir: Path) -> dict[Path, dict]:
    """Every renderers_*.json in `results_dir` by path; ValueError naming a file that is not such a result."""
    runs = {}
    for p in sorted(results_dir.glob(RESULTS_GLOB)):
        try:
            run = json.loads(p.read_text())
            if not isinstance(run, dict) or not all(k in run for k in RUN_KEYS):
                raise ValueError(f"needs the keys {', '.join(RUN_KEYS)}")
        except ValueError as e:
            raise ValueError(f"{p}: not a `photoreg bench renderers` result ({e})") from None
        runs[p] = run
    return runs


def write_report(results_dir: Path, md: Path, png: Path) -> None:
    """benchmarks/renderers.md and the PNG from every renderers_*.json in `results_dir`."""
    from ..synth.scenes import INSERT_MESH_SCALE

    runs = list(load_runs(results_dir).values())
    lines = ["# Shadow renderers side by side", "",
             "Written by `photoreg bench renderers` from benchmarks/results/renderers_*.json. Every renderer "
             "runs on the same frames, lighting and G-buffer (photoreg/bench/renderers.py says how); error in "
             "linear RGB over the object's region of interest (mask dilated 40 px) against the path tracer, "
             "mean over the insert frames; flicker on a static camera over the pixels the insertion changed "
             "(the baseline row: the camera frames' own flicker there, i.e. render noise). ms: the renderer "
             "call alone, mean per frame. '<renderer>, true light': the same renderer on the same frames given "
             "the generator's lighting (its SH and sun) instead of the estimate, so the error left is the "
             "renderer's. The baseline pastes the path tracer's own object, Monte Carlo noise included, which no "
             "renderer can match; 'baseline, object path-traced with other seeds' pastes the object rendered "
             "again with other seeds: the same baseline as an exact renderer would score it.", ""]
    for run in runs:
        lines += [f"## {run['device_name']} ({run['device']}), ground truth at {run['spp']} spp, inserted "
                  + (f"{run['insert']} (largest side {INSERT_MESH_SCALE:g} m, smooth normals)" if run.get("insert")
                     else "cube"), "",
                  f"Command: `{run['command']}`; {run['date']}; Warp {run['warp']}, Open3D {run['open3d']}; "
                  f"{run['size']}, {run['frames']} frames per recording, {run['spp']} spp."
                  + (f" Note: {run['note']}." if run.get("note") else ""), "",
                  "| scene | renderer | ms/frame | RMSE | si-RMSE | flicker |", "|---|---|---:|---:|---:|---:|"]
        for r in run["rows"]:   # None: a figure the run could not make (JSON keeps no NaN)
            cells = ["-" if r.get(k) is None else format(r[k], spec)
                     for k, spec in (("ms_mean", ".1f"), ("rmse", ".4f"), ("si_rmse", ".4f"), ("flicker", ".4f"))]
            lines.append(f"| {r['scene']} | {r['renderer']} | " + " | ".join(cells) + " |")
        lines.append("")
    write_text(md, "\n".join(lines))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10.5, 4.5))
    markers = "osD^v<>"
    for k, run in enumerate(runs):
        names = sorted({r["renderer"] for r in run["rows"] if r["ms_mean"] is not None})
        for j, name in enumerate(names):
            rs = [r for r in run["rows"] if r["renderer"] == name and r["si_rmse"] is not None]
            ax.scatter([r["ms_mean"] for r in rs], [r["si_rmse"] for r in rs], marker=markers[k % len(markers)],
                       color=f"C{j}", label=f"{name} ({run['device_name']}, {run['spp']} spp"
                                           + (f", {run['insert']})" if run.get("insert") else ")"))
    ax.set_xscale("log")
    ax.set_xlabel("renderer ms per frame (log)")
    ax.set_ylabel("composite si-RMSE in the ROI (lower is better)")
    ax.set_title("Shadow renderers: speed against error (one point per scene kind)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))   # outside: the points stay visible
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
    from ..render.registry import RENDERERS, get_renderer
    from ..synth.generate import parse_size
    from .speed import device_name

    names = [n.strip() for n in args.renderers.split(",")] if args.renderers else sorted(RENDERERS)
    unknown = [n for n in names if n not in RENDERERS]
    if unknown:
        raise ValueError(f"--renderers: unknown renderer(s) {', '.join(map(repr, unknown))}; choose from "
                         f"{', '.join(sorted(RENDERERS))}")
    renderers = {n: get_renderer(n) for n in names}
    kinds = scene_kinds(args.scenes)
    w, h = parse_size(args.size)
    # the report is rebuilt from --results-dir's rows alone: the committed one only from the committed rows
    committed = Path(args.results_dir).resolve() == (Path("benchmarks") / "results").resolve()
    args.md = args.md or ("benchmarks/renderers.md" if committed else str(Path(args.results_dir) / "renderers.md"))
    args.plot = args.plot or ("benchmarks/renderers.png" if committed else
                              str(Path(args.results_dir) / "renderers.png"))
    check_output_file(args.md, "--md")
    check_output_file(args.plot, "--plot")
    check_output_dir(args.results_dir, "--results-dir")
    cache = Path(args.synth_dir or SCENE_CACHE)

    def log(msg: str) -> None:
        print(f"bench renderers: {msg}", file=sys.stderr, flush=True)

    device = resolve_device(args.device or "auto")
    results = Path(args.results_dir)
    mesh = f"_{Path(args.insert_mesh).stem}" if args.insert_mesh else ""
    target = results / f"renderers_{device.split(':')[0]}_{args.spp}spp{mesh}.json"
    earlier = load_runs(results)   # every file the report reads, checked before any work
    kept = []   # the earlier run's rows of the scenes this one does not run again
    if target in earlier:
        run = earlier[target]
        if (run["size"], run["frames"]) != (f"{w}x{h}", args.frames):
            raise ValueError(f"{target} holds a {run['size']} run of {run['frames']} frames, this one is {w}x{h} of "
                             f"{args.frames}: give another --results-dir, or move that file")
        kept = [r for r in run["rows"] if r["scene"] not in kinds]
    rows = []
    for kind in kinds:
        orbit = cached_scene(cache, kind, w, h, args.frames, args.spp, inserts="auto", log=log,
                             insert_mesh=args.insert_mesh)
        static = cached_scene(cache, kind, w, h, args.frames, args.spp, camera="static", log=log)
        rows += bench_scene(kind, orbit, static, device, renderers)
    run = {"device": device, "device_name": device_name(device), "warp": wp.__version__, "open3d": o3d.__version__,
           "command": "photoreg " + " ".join(sys.argv[1:]), "date": datetime.date.today().isoformat(),
           "size": f"{w}x{h}", "frames": args.frames, "spp": args.spp, "rows": kept + rows,
           "insert": Path(args.insert_mesh).name if args.insert_mesh else None}
    write_json(target, run)
    write_report(results, Path(args.md), Path(args.plot))
    for r in rows:
        ms = "-" if r["ms_mean"] is None else f"{r['ms_mean']:8.1f}"
        flicker = "-" if r["flicker"] is None else f"{r['flicker']:.4f}"
        print(f"{r['scene']:12s} {r['renderer']:48s} ms {ms}  rmse {r['rmse']:.4f}  si-rmse {r['si_rmse']:.4f}  "
              f"flicker {flicker}")
    print(f"report: {args.md}, {args.plot}")
    return 0
