"""Lighting settings judged on every benchmark recording at once (issue 4): regenerates lighting_sweep.md.

A setting tuned on a few recordings often does not hold on the rest (a first look at a stronger
regularisation on tabletop, coloured, corner and the demo promised si-RMSE 0.091 -> 0.075; over all 30
recordings the mean moved by under 0.01). This runs each named set of LightingConfig overrides
(lighting_accuracy's `run`: a "reconstruction" dict inside goes to ReconstructionConfig) over the
recordings of lighting_accuracy.md (the demo, the generated scene kinds and their variants, the real
recordings) and of lighting_hdr.md (the generated tabletop under each HDR map), generating missing ones,
and writes one table with the means per group. Runs go to worker processes (--jobs; each Warp CPU launch
then takes its share of the cores) and are appended to a JSON-lines cache (a run is reused only for the same
overrides), so an interrupted sweep resumes.

Run: python benchmarks/lighting_sweep.py --config 'defaults={}' --config 'reg 0.02={"regularization": 0.02}'
     [--synth-dir /tmp/photoreg_bench] [--hdr-dir DIR] [--jobs 2] [--cache FILE] [--out FILE]
The file's text outside the generated markers (the discussion) is kept.
"""
from __future__ import annotations

import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import lighting_accuracy as la  # noqa: E402  (sets up photoreg before numpy)
import numpy as np  # noqa: E402
from lighting_hdr import hdr_recording  # noqa: E402

from photoreg.bench.score import load_gt  # noqa: E402
from photoreg.synth.scenes import SCENE_KINDS  # noqa: E402

GROUPS = ("generated", "variants", "hdr")   # groups with ground truth, each averaged; then "real"


def recordings(args) -> list[tuple[str, str, Path, int]]:
    """(group, label, folder, frames) of every benchmark recording; generated ones are made when missing."""
    synth, size = Path(args.synth_dir), args.size
    out = [("generated", "demo (10 frames)", la.REPO / "data" / "demo", 10),
           ("generated", "demo (40 frames)", la.REPO / "data" / "demo", 40)]
    out += [("generated", kind, la.ensure_synth(synth, kind, args.frames, size, args.spp)[0], args.frames)
            for kind in SCENE_KINDS]
    out += [("variants", label, path, frames)
            for label, path, frames, _ in la.variant_recordings(synth, args.frames, size, args.spp)]
    data = Path(args.data)
    out += [("hdr", hdr.stem, hdr_recording(Path(args.hdr_dir), hdr, args.frames, size, args.spp)[0], args.frames)
            for hdr in sorted((data / "hdr").glob("*.hdr"))]
    real = data / "recordings"
    out += [("real", name, real / name, args.real_frames) for name in sorted(p.name for p in real.iterdir())]
    return out


def _measure(job: tuple) -> dict:
    """One (config, recording) run: lighting_accuracy.summary's metrics."""
    config, overrides, group, label, path, frames = job
    gt = load_gt(path) if (path / "lighting_gt.json").is_file() else None
    res = la.summary(la.run(path, overrides, frames, holdout=gt is None), gt)
    return {"config": config, "group": group, "recording": label, **res}


def cell(r: dict | None) -> str:
    if r is None:
        return "-"
    if r["group"] == "real":
        return f"{la.fmt(r['flicker'], '.3f')} / {la.fmt(r['heldout'], '.3f')}"
    return f"{r['direction_deg']:.1f} / {r['irradiance_si_rmse_upper']:.3f} / {la.fmt(r['flicker'], '.3f')}"


def main() -> int:
    ap = la.synth_arguments(__doc__.split("\n")[0])
    ap.add_argument("--config", action="append", required=True, metavar="NAME=JSON",
                    help="a named set of LightingConfig overrides (repeat; the first is the reference column)")
    ap.add_argument("--data", default=os.environ.get("PHOTOREG_DATA", "/work/shared/data"))
    ap.add_argument("--hdr-dir", default=None, help="folder of the HDR tabletops (default: --synth-dir)")
    ap.add_argument("--real-frames", type=int, default=20)
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--cache", default=None, help="JSON-lines cache of finished runs (default: OUT.jsonl in /tmp)")
    ap.add_argument("--out", default=str(la.REPO / "benchmarks" / "lighting_sweep.md"))
    args = ap.parse_args()
    args.hdr_dir = args.hdr_dir or args.synth_dir
    configs = {}
    for item in args.config:
        name, sep, text = item.partition("=")
        try:
            overrides = json.loads(text) if sep else None
        except json.JSONDecodeError as e:
            ap.error(f"--config {item!r}: the overrides are not JSON ({e})")
        if not name or not isinstance(overrides, dict):
            ap.error(f"--config {item!r}: expected NAME={{JSON object of LightingConfig overrides}}")
        configs[name] = overrides
    cache = Path(args.cache or f"/tmp/{Path(args.out).stem}.jsonl")
    done = {}
    if cache.is_file():
        for line in cache.read_text().splitlines():
            r = json.loads(line)
            if r.get("overrides") == configs.get(r["config"]):   # a cached run of these very overrides
                done[r["config"], r["recording"]] = r
    recs = recordings(args)
    jobs = [(name, overrides, group, label, path, frames) for name, overrides in configs.items()
            for group, label, path, frames in recs if (name, label) not in done]
    print(f"{len(jobs)} runs ({len(done)} cached in {cache})", flush=True)
    t0 = time.perf_counter()
    # inherited by the workers: the cores shared out between them
    os.environ.setdefault("PHOTOREG_CPU_THREADS", str(max(1, (os.cpu_count() or 1) // max(1, args.jobs))))
    with ProcessPoolExecutor(max(1, args.jobs)) as ex, cache.open("a") as log:
        for job, r in zip(jobs, ex.map(_measure, jobs)):
            r["overrides"] = job[1]
            done[r["config"], r["recording"]] = r
            log.write(json.dumps(r) + "\n")
            log.flush()
            print(f"{r['config']:24s} {r['recording']:34s} {cell(r)}", flush=True)

    names = list(configs)
    command = ("python benchmarks/lighting_sweep.py " + " ".join(f"--config '{n}={json.dumps(configs[n])}'"
                                                                  for n in names)
               + f" --synth-dir {args.synth_dir}"
               + (f" --hdr-dir {args.hdr_dir}" if args.hdr_dir != args.synth_dir else "")
               + f" --frames {args.frames} --size {args.size} --spp {args.spp}"
               + f" --real-frames {args.real_frames}")
    lines = [la.START, "", f"Generated by `{command}` ({time.perf_counter() - t0:.0f} s with {args.jobs} workers on "
             f"a {os.cpu_count()}-core CPU). Cells: direction deg / si-RMSE upper / flicker (medians over frames, "
             "lighting_accuracy.md's metrics); real recordings: flicker / held-out residual. Groups: the demo and "
             "the generated scene kinds, their variants (other sun azimuths, camera, size, 40 frames), the "
             "generated tabletop under each HDR map of the shared data, the real recordings.", "",
             "| recording | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for group in GROUPS:
        labels = [label for g, label, _, _ in recs if g == group]
        for label in labels:
            lines.append(f"| {label} | " + " | ".join(cell(done.get((n, label))) for n in names) + " |")
        means = []
        for n in names:
            rows = [done[n, label] for label in labels if (n, label) in done]
            means.append(" / ".join(f"{np.mean([r[k] for r in rows]):{f}}" for k, f in
                                    (("direction_deg", ".1f"), ("irradiance_si_rmse_upper", ".3f"),
                                     ("flicker", ".3f"))) if rows else "-")
        lines.append(f"| **mean, {group}** | " + " | ".join(f"**{m}**" for m in means) + " |")
    for _, label, _, _ in (r for r in recs if r[0] == "real"):
        lines.append(f"| {label} (real) | " + " | ".join(cell(done.get((n, label))) for n in names) + " |")
    lines += ["", "The recordings' commands are in lighting_accuracy.md and lighting_hdr.md; the settings are "
              "LightingConfig's (photoreg/config.py).", "", la.END]
    la.write_generated(Path(args.out), lines, "Lighting settings over every benchmark recording (issue 4)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
