"""Composite error and render time against render.stride (the shadow ratio's sampling; the lighting keeps its own
stride): every recording runs once per render stride with everything else the same, so the lighting estimates are
equal and the composites differ by the render stride alone. Error: `photoreg score --composite` (linear RGB over
the object's region of interest against the path tracer's insert renders; the no-shadow baseline beside it).

usage: python benchmarks/render_stride.py [--strides 1,2,4,8] [--scenes tabletop,corner] [--size 320x240]
           [--frames 16] [--spp 64] [--lighting-stride 4] [--device cpu] [--demo] [--json OUT]
       (generated scenes are cached in ~/.cache/photoreg/bench_scenes, as `photoreg bench renderers` does)
"""
import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from photoreg.bench.renderers import _session_for
from photoreg.bench.scenes import SCENE_CACHE, cached_scene
from photoreg.bench.score import score_composites
from photoreg.bench.speed import device_name
from photoreg.config import load_session
from photoreg.device import resolve_device
from photoreg.runner import run_session
from photoreg.synth.generate import parse_size

REPO = Path(__file__).resolve().parents[1]


def rows_of(name: str, session, recording: Path, strides: list[int], lighting_stride: int) -> list[dict]:
    """One row per render stride: composite errors (mean over the insert frames) and the render stage's mean ms."""
    rows = []
    for rs in strides:
        session.lighting.stride, session.render.stride = lighting_stride, rs
        with tempfile.TemporaryDirectory() as out:
            session.output.dir, session.output.pictures_every = out, 0
            summary = run_session(session, quiet=True)
            sc = score_composites(out, recording)
        per = [r for r in sc["per_frame"] if "si_rmse" in r]
        t = summary["timings_ms_mean"]
        rows.append({"recording": name, "render_stride": rs, "lighting_stride": lighting_stride,
                     "rmse": float(np.mean([r["rmse"] for r in per])),
                     "si_rmse": float(np.mean([r["si_rmse"] for r in per])),
                     "baseline_si_rmse": float(np.mean([r["baseline_si_rmse"] for r in per])),
                     "render_ms": t.get("render"), "shadows_ms": t.get("render shadows"),
                     "frames_per_s": summary["frames_per_s"], "n_inserts": len(per)})
        r = rows[-1]
        print(f"{name:10s} render stride {rs}: si-RMSE {r['si_rmse']:.4f} (baseline {r['baseline_si_rmse']:.4f}), "
              f"RMSE {r['rmse']:.4f}, render {r['render_ms']:.1f} ms (shadows {r['shadows_ms']:.1f})", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--strides", default="1,2,4,8")
    ap.add_argument("--scenes", default="tabletop,corner")
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--lighting-stride", type=int, default=4)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--demo", action="store_true", help="also the embedded demo (data/demo, insert frames 10, 20)")
    ap.add_argument("--json", dest="json_out")
    a = ap.parse_args()
    strides = [int(s) for s in a.strides.split(",")]
    device = resolve_device(a.device)
    w, h = parse_size(a.size)
    rows = []
    for kind in filter(None, a.scenes.split(",")):
        orbit = cached_scene(Path(SCENE_CACHE), kind, w, h, a.frames, a.spp, inserts="auto",
                             log=lambda m: print(m, file=sys.stderr, flush=True))
        s = _session_for(orbit, orbit, device)
        rows += rows_of(kind, s, orbit, strides, a.lighting_stride)
    if a.demo:
        s = load_session(REPO / "data" / "demo" / "session.toml")
        s.device, s.frames = device, "0:21"
        rows += rows_of("demo", s, REPO / "data" / "demo", strides, a.lighting_stride)
    result = {"device": device, "device_name": device_name(device), "size": f"{w}x{h}", "frames": a.frames,
              "spp": a.spp, "command": "python benchmarks/render_stride.py " + " ".join(sys.argv[1:]), "rows": rows}
    if a.json_out:
        Path(a.json_out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
