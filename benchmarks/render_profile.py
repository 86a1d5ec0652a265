"""Where the render stage's time goes (issue 9: with an object inserted the render stage sets the frame rate).
Runs the pipeline over a session's frames on one device and profiles (cProfile) the render stage alone, after the
warm-up frames; prints and writes the functions with the most time per frame, cumulative and own:

    python3 benchmarks/render_profile.py sessions/tum_fr1_rpy.toml --device cuda --frames 0:25 --json OUT.json

`--part frame` profiles whole frames instead (every stage; a session without objects too); `--every N` holds each
estimate for N frames (lighting.every: `--every 1000` profiles frames that only take their exposure gain). With
`--async` (lighting.asynchronous) the worker thread's calls land in the profile too: Python 3.12's cProfile watches
every thread (sys.monitoring) while it runs.

On CUDA a kernel's time lands where the host waits for it (a synchronisation, a copy to the host).
"""
from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import time


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("session")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--frames", default="0:25")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--rays", type=int, default=64)
    ap.add_argument("--bands", type=int, default=3)
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--async", dest="asynchronous", action="store_true", help="lighting.asynchronous")
    ap.add_argument("--part", choices=("render", "frame"), default="render",
                    help="what to profile: the render stage or whole frames")
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument("--json")
    a = ap.parse_args()

    from photoreg.config import load_session, parse_frames
    from photoreg.io.recording import iter_frames, open_configured
    from photoreg.pipeline import Pipeline

    s = load_session(a.session)
    s.device, s.lighting.stride, s.lighting.rays, s.lighting.bands = a.device, a.stride, a.rays, a.bands
    s.lighting.every, s.lighting.asynchronous = a.every, a.asynchronous
    if not s.objects and a.part == "render":
        sys.exit(f"{a.session}: no [[objects]], no render stage to profile")
    rec = open_configured(s.recording)
    indices = parse_frames(a.frames, len(rec))
    pipe = Pipeline(s, rec.intrinsics)
    stage, prof, walls = pipe.render, cProfile.Profile(), []

    def timed(fn, *args, **kwargs):
        """fn's call profiled (cProfile follows the calling thread alone) and its wall ms kept."""
        t0 = time.perf_counter()
        out = prof.runcall(fn, *args, **kwargs)
        walls.append((time.perf_counter() - t0) * 1000.0)
        return out

    class Profiled:
        """The stage, its calls profiled (the pipeline reads its other attributes too: `last`)."""

        def __call__(self, *args, **kwargs):
            return timed(stage, *args, **kwargs)

        def __getattr__(self, name):
            return getattr(stage, name)

    for k, frame in enumerate(iter_frames(rec, indices)):
        if a.part == "frame" and k >= a.warmup:
            timed(pipe.process, frame)
            continue
        pipe.render = Profiled() if a.part == "render" and k >= a.warmup else stage
        pipe.process(frame)
    pipe.wait_for_estimate()
    pipe.close()
    n = len(walls)
    stats = pstats.Stats(prof)
    rows = []
    for (path, line, name), (_, calls, own, cum, _) in stats.stats.items():
        rows.append({"function": f"{path.split('site-packages/')[-1]}:{line}({name})", "calls_per_frame":
                     round(calls / n, 2), "own_ms": round(own * 1000 / n, 3), "cumulative_ms": round(cum * 1000 / n, 3)})
    out = {"session": a.session, "device": pipe.device, "part": a.part, "calls_profiled": n, "stride": a.stride,
           "rays": a.rays, "bands": a.bands, "every": a.every, "asynchronous": a.asynchronous, "objects": len(s.objects),
           "ms_mean": round(sum(walls) / n, 3),
           "by_cumulative": sorted(rows, key=lambda r: -r["cumulative_ms"])[:a.top],
           "by_own": sorted(rows, key=lambda r: -r["own_ms"])[:a.top]}
    print(f"{a.part} on {pipe.device}: {out['ms_mean']} ms a call (profiled, {n} calls)")
    for key in ("by_cumulative", "by_own"):
        print(f"-- {key} (ms a call)")
        for r in out[key]:
            print(f"{r['cumulative_ms']:8.2f} {r['own_ms']:8.2f} {r['calls_per_frame']:7.1f}  {r['function']}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
