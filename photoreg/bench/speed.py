"""`photoreg bench speed`: per-stage milliseconds of the full per-frame pipeline on one device.

Frames are processed in order (fusion needs them in order); the first `warmup` frames (kernel
compilation, first allocations) are left out of the figures. The result names the device, the
Warp/Open3D versions and where fusion ran.
"""
from __future__ import annotations

import os
import platform
import sys

import numpy as np

from ..config import Session, load_session, select_frames, validate
from ..io.atomic import check_not_an_input, check_output_file, write_json

BARE_SETTINGS = (4, 64, 3)   # a recording folder's lighting stride, rays and bands (the benchmarks' live setting)
DEFAULT_FRAMES = "0:12"      # where neither --frames nor the session names frames


def device_name(device: str) -> str:
    """Human name of the Warp device the run used (GPU model, or the CPU model)."""
    from ..device import init_warp

    wp = init_warp()
    if device.startswith("cuda"):
        return wp.get_device(device).name
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "cpu"


def bench_recording(session: Session, warmup: int = 2) -> dict:
    """Run the pipeline over the session's frames; mean/median/p95 ms per stage after warm-up."""
    import open3d as o3d
    import warp as wp

    from ..io.recording import iter_frames, open_configured
    from ..kernels.launch import cpu_threads
    from ..pipeline import Pipeline
    from ..runner import track_without_poses

    if warmup < 0:
        raise ValueError(f"bench: --warmup must be >= 0, got {warmup}")
    rec = open_configured(session.recording)
    indices = select_frames(session.frames, len(rec), session.recording.path)
    if len(indices) <= warmup:
        raise ValueError(f"bench: need more than {warmup} frames (warm-up), got {len(indices)}")
    track_without_poses(session, rec, "bench")   # as photoreg run does
    pipe = Pipeline(session, rec.intrinsics)
    timings, estimated = [], []
    try:
        for k, frame in enumerate(iter_frames(rec, indices)):
            r = pipe.process(frame)
            if k >= warmup:
                timings.append(r.timings_ms)
                if r.diagnostics.estimated_frame is not None:
                    estimated.append((frame.index, r.diagnostics.estimated_frame))
            print(f"\rbench: frame {k + 1}/{len(indices)}", end="", file=sys.stderr, flush=True)
    finally:
        pipe.close()
    print(file=sys.stderr)
    lags = [i - e for i, e in estimated]
    # frames holding the lighting skip stages: every stage any frame ran, the total last
    stages = [s for s in dict.fromkeys(s for t in timings for s in t) if s != "total"] + ["total"]
    L = session.lighting
    return {
        "device": pipe.device, "device_name": device_name(pipe.device),
        "warp": wp.__version__, "open3d": o3d.__version__,
        "fusion_on": str(pipe.volume.o3d_device), "recording": session.recording.path,
        "threads": cpu_threads() if pipe.device == "cpu" else 0,
        "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),   # numpy's, as this process loaded it
        "size": f"{rec.intrinsics.width}x{rec.intrinsics.height}", "frames_timed": len(timings),
        "stride": L.stride, "rays": L.rays, "bands": L.bands, "voxel_size": session.reconstruction.voxel_size,
        "normal_smoothing_voxels": session.reconstruction.normal_smoothing_voxels,
        "ray_length": L.ray_length, "every": L.every, "asynchronous": L.asynchronous,
        "solve_process": L.asynchronous and L.solve_process, "sun": L.sun, "bounce": L.bounce,
        # frames between a frame and the one whose samples gave its lighting (0: its own), and how many estimates
        "lag_frames_mean": round(float(np.mean(lags)), 3) if lags else None,
        "estimates": len({e for _, e in estimated}),
        "bounce_observed": L.bounce and L.bounce_observed, "history": L.history,
        "sun_refine_every": L.sun_refine_every, "tracked": not session.recording.use_poses,
        "objects": len(session.objects), "shadows": session.render.shadows if session.objects else None,
        "render_stride": session.render.stride if session.objects else None,
        "gbuffer": session.render.gbuffer if session.objects else None,
        "shutter": session.render.shutter if session.objects else None,
        "ms_mean": {s: round(float(np.mean([t.get(s, 0.0) for t in timings])), 3) for s in stages},
        "ms_p95": {s: round(float(np.percentile([t.get(s, 0.0) for t in timings], 95)), 3) for s in stages},
        "ms_median": {s: round(float(np.median([t.get(s, 0.0) for t in timings])), 3) for s in stages},
        "frames_per_s": round(1000.0 / float(np.mean([t["total"] for t in timings])), 3),
        # the typical frame: one slow frame (a first allocation, a kernel built late) moves the mean only
        "frames_per_s_median": round(1000.0 / float(np.median([t["total"] for t in timings])), 3),
    }


def speed_command(args) -> int:
    from ..kernels.launch import set_cpu_threads

    if args.json_out:
        check_output_file(args.json_out, "--json")
    if args.threads is not None:
        set_cpu_threads(args.threads)
    if args.recording.lower().endswith(".toml"):   # a session: its objects are inserted, the render stage timed too
        s = load_session(args.recording)            # and its settings kept but for the options given
    else:
        s = Session()
        s.recording.path = args.recording
        s.lighting.stride, s.lighting.rays, s.lighting.bands = BARE_SETTINGS
    s.device = args.device or s.device
    s.frames = args.frames or s.frames or DEFAULT_FRAMES
    for value, section, key in ((args.stride, "lighting", "stride"), (args.rays, "lighting", "rays"),
                                (args.bands, "lighting", "bands"), (args.every, "lighting", "every"),
                                (args.ray_length, "lighting", "ray_length"), (args.render_stride, "render", "stride"),
                                (args.gbuffer, "render", "gbuffer"), (args.shutter, "render", "shutter"),
                                (args.voxel_size, "reconstruction", "voxel_size"),
                                (args.normal_smoothing, "reconstruction", "normal_smoothing_voxels")):
        if value is not None:
            setattr(getattr(s, section), key, value)
    for flag, key, value in ((args.no_sun, "sun", False), (args.no_bounce, "bounce", False),
                             (args.no_observed_bounce, "bounce_observed", False),
                             (args.asynchronous, "asynchronous", True), (args.no_solve_process, "solve_process", False),
                             (args.no_history, "history", 0)):
        if flag:
            setattr(s.lighting, key, value)
    if args.no_poses:
        s.recording.use_poses = False
    if args.json_out:   # not the session file nor a file of its recording
        check_not_an_input(args.json_out, "--json", {"the input's": args.recording,
                                                      "the recording's": s.recording.path})
    validate(s)
    res = bench_recording(s, warmup=args.warmup)
    stages = "  ".join(f"{k} {v:.1f}" for k, v in res["ms_mean"].items())
    render = (f", {res['objects']} object(s) inserted ({res['shadows']}, render stride {res['render_stride']}, "
              f"G-buffer {res['gbuffer']})"
              if res["objects"] else ", no objects")
    mode = (f" asynchronous ({res['estimates']} estimates, lighting {res['lag_frames_mean']} frames old on average, "
            f"solved in {'a child process' if res['solve_process'] else 'the worker thread'})"
            if res["asynchronous"] else "")
    print(f"{res['device_name']} ({res['device']}, {res['threads']} CPU threads, BLAS threads {res['blas_threads']}), "
          f"{res['size']} stride {res['stride']} "
          f"rays {res['rays']} bands {res['bands']}, every {res['every']}{mode}, sun {res['sun']}, "
          f"bounce {res['bounce']} (observed {res['bounce_observed']}), "
          f"history {res['history']}{', camera tracked' if res['tracked'] else ''}{render}: {res['frames_per_s']} "
          f"frames/s (median frame: "
          f"{res['frames_per_s_median']})\n  mean ms: {stages}")
    if args.json_out:
        write_json(args.json_out, res)
    return 0
