"""`photoreg` command line: every subcommand's arguments here, its work in the owning module."""
from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys

from photoreg.config import GBUFFER_BACKENDS, SHADOW_RENDERERS
from photoreg.device import open3d_message
from photoreg.render.neural_soft_weights import AXES

# subcommand -> "module:function"; the function takes the parsed argparse.Namespace and returns an exit code.
HANDLERS = {
    "run": "photoreg.runner:run_command",
    "demo": "photoreg.runner:demo_command",
    "info": "photoreg.io.recording:info_command",
    "synth": "photoreg.synth.generate:synth_command",
    "score": "photoreg.bench.score:score_command",
    "serve": "photoreg.service.server:serve_command",
    "stream": "photoreg.service.client:stream_command",
    "batch": "photoreg.batch.runner:batch_command",
    "bench": "photoreg.bench:bench_command",
    "train": "photoreg.train:train_command",
}


def _add_run_options(p: argparse.ArgumentParser, out_help: str) -> None:
    p.add_argument("--out", help=out_help)
    p.add_argument("--frames", help="frames to process: N (first N), A:B or A:B:S (0-based, end exclusive; ':' all, "
                                    "whatever the session file says)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None, help="compute device (default auto)")
    p.add_argument("--stride", type=int, help="sample every n-th pixel for the transfer (1, 2, 4, ...)")
    p.add_argument("--rays", type=int, help="visibility rays per pixel over the hemisphere")
    p.add_argument("--bands", type=int, help="SH bands B of the lighting (B*B coefficients)")
    p.add_argument("--voxel-size", type=float, help="TSDF voxel size in metres")
    p.add_argument("--ray-length", type=float, help="visibility ray length in metres")
    p.add_argument("--every", type=int, help="estimate the lighting on every n-th frame; the frames between hold it "
                                             "(lighting.every, default 1)")
    p.add_argument("--async", dest="asynchronous", action="store_true",
                   help="estimate the lighting in a worker thread beside the frames, which hold the latest finished "
                        "estimate (lighting.asynchronous; live speed)")
    p.add_argument("--depth-filter", type=int, help="bilateral depth filter window in pixels, odd, 0 = off "
                                                    "(reconstruction.depth_filter_px, default 0)")
    p.add_argument("--normal-smoothing", type=float, help="radius in voxels of the ray-cast normals' tangent mean, "
                                                          "0 = off (reconstruction.normal_smoothing_voxels, default 0)")
    p.add_argument("--no-poses", action="store_true", help="ignore recorded poses and track the camera")
    p.add_argument("--pose-time-offset", type=float, help="seconds added to the frames' times where the recorded poses "
                                                          "(TUM groundtruth.txt) are looked up: a motion-capture "
                                                          "clock's offset (recording.pose_time_offset, default 0)")
    p.add_argument("--shadows", choices=SHADOW_RENDERERS, help="shadow renderer (overrides [render] shadows)")
    p.add_argument("--render-stride", type=int, help="sample the objects' shadows every n-th pixel, full resolution "
                                                     "along their silhouettes (render.stride, default 4)")
    p.add_argument("--gbuffer", choices=GBUFFER_BACKENDS, help="the objects' G-buffer rasterised by pyrender or "
                                                               "ray-traced by Warp (render.gbuffer, default pyrender)")
    p.add_argument("--shutter", type=float, help="seconds the camera's shutter is open: the objects blurred by its "
                                                 "motion as the frame is; 0: sharp (render.shutter; default: the "
                                                 "recording's calibration's, else sharp)")
    p.add_argument("--video", action="store_true", help="also composite.mp4: the composites as a video "
                                                          "(sessions with [[objects]])")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="photoreg", description="Photometric registration from RGB-D recordings.")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="estimate per-frame lighting for a recording or a session file")
    p.add_argument("input", help="session file (.toml) or recording folder")
    _add_run_options(p, "output folder (overrides the session's [output] dir; a bare recording's default: "
                        "out/FOLDER_NAME)")

    p = sub.add_parser("demo", help="run on the embedded demo recording (data/demo)")
    _add_run_options(p, "output folder (default out/demo)")

    p = sub.add_parser("info", help="describe a recording: frames, size, intrinsics, poses, depth range")
    p.add_argument("path")

    p = sub.add_parser("synth", help="render a ground-truth RGB-D recording with Mitsuba 3")
    p.add_argument("scene", help="scene kind: tabletop, corner, plane, split_albedo, coloured")
    p.add_argument("--out", required=True)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--size", default="320x240", help="WxH")
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--env", default="procedural", help="HDR environment map path, or 'procedural'")
    p.add_argument("--yaw", type=float, default=0.0, help="environment yaw about world +z, degrees")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--camera", default="orbit", choices=["orbit", "handheld", "static", "pan"],
                   help="camera path: orbit about the scene (default), orbit with hand jitter, static, or pan (the "
                        "orbit, turning left and right as it goes)")
    p.add_argument("--direct-only", action="store_true", help="direct illumination only (no interreflection)")
    p.add_argument("--insert-frames", default="auto",
                   help="frames re-rendered with a virtual object: comma-separated list, 'auto' or 'none'")
    p.add_argument("--no-noise", action="store_true", help="write clean depth only")
    p.add_argument("--mesh", help="mesh file for the tabletop scene's mesh object (default: a procedural cylinder)")
    p.add_argument("--overexpose", type=float, default=1.0,
                   help="times the chosen exposure: above 1 the brightest surfaces saturate, as a camera's do")
    p.add_argument("--insert-texture", action="store_true",
                   help="texture the inserted cube (its session then asks for albedo = \"texture\")")
    p.add_argument("--insert-mesh", help="insert this mesh file (PLY/OBJ/OFF/GLB, scaled to a largest side of "
                                         "0.2 m, smooth normals) instead of the cube")
    p.add_argument("--shutter", type=float, default=0.0,
                   help="seconds the shutter stays open, centred on each frame's time: the camera's motion blurs the "
                        "colour and the inserts (default 0: an instant)")

    p = sub.add_parser("score", help="official accuracy metrics of a run against ground truth")
    p.add_argument("out", help="output folder of a run (holds lighting.jsonl)")
    p.add_argument("--gt", required=True, help="recording folder with lighting_gt.json")
    p.add_argument("--composite", action="store_true", help="also score composites against insert renders")
    p.add_argument("--json", dest="json_out", help="write the scores to this JSON file")

    p = sub.add_parser("serve", help="WebSocket service: per-frame lighting for live RGB-D streams (docs/protocol.md)")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default loopback only)")
    p.add_argument("--port", type=int, default=8765, help="TCP port (0: any free port)")
    p.add_argument("--token", help="clients must send this token in hello (default $PHOTOREG_TOKEN, else none)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="compute device (default auto)")
    p.add_argument("--max-clients", type=int, default=4, help="simultaneous connections; more are refused")
    p.add_argument("--queue", type=int, default=2,
                   help="frames waiting per connection; when full the oldest is dropped (latest wins)")
    p.add_argument("--idle-timeout", type=float, default=300.0,
                   help="close a connection after this many seconds without a message (0: never)")
    p.add_argument("--max-message-mb", type=float, default=32.0, help="largest message accepted, MiB")
    p.add_argument("--meshes", help="folder of meshes that clients' virtual objects may name (by file name); "
                                    "their composites are sent back (default: no objects)")
    p.add_argument("--threads", action="store_true",
                   help="run the connections' pipelines on threads of the server's process instead of a process "
                        "each: a quicker hello and less memory, but several clients take turns on one interpreter")

    p = sub.add_parser("stream", help="replay a recording through a photoreg server; save its replies")
    p.add_argument("recording", help="recording folder (format autodetected)")
    p.add_argument("--url", default="ws://127.0.0.1:8765", help="server URL (default ws://127.0.0.1:8765)")
    p.add_argument("--token", help="token the server asks for (default $PHOTOREG_TOKEN)")
    p.add_argument("--realtime", action="store_true",
                   help="send at the recording's frame times (the server drops frames it cannot keep up with)")
    p.add_argument("--window", type=int, default=2, help="frames in flight when not --realtime (default 2)")
    p.add_argument("--out", help="save lighting.jsonl, summary.json, trajectory.txt (a tracked stream) and "
                                 "composite/ (a session with objects) here")
    p.add_argument("--frames", help="frames to send: N (first N), A:B or A:B:S (0-based, end exclusive)")
    p.add_argument("--color", choices=["png", "jpeg", "rgb8"], default="png", help="colour encoding (default png)")
    p.add_argument("--depth", choices=["png16", "u16", "f32"], default="png16", help="depth encoding (default png16)")
    p.add_argument("--stride", type=int, help="sample every n-th pixel for the transfer (1, 2, 4, ...)")
    p.add_argument("--rays", type=int, help="visibility rays per pixel over the hemisphere")
    p.add_argument("--bands", type=int, help="SH bands B of the lighting (B*B coefficients)")
    p.add_argument("--voxel-size", type=float, help="TSDF voxel size in metres")
    p.add_argument("--ray-length", type=float, help="visibility ray length in metres")
    p.add_argument("--every", type=int, help="ask the server to estimate the lighting on every n-th frame only")
    p.add_argument("--async", dest="asynchronous", action="store_true",
                   help="ask the server to estimate the lighting beside the frames (lighting.asynchronous)")
    p.add_argument("--session", help="ask for what `photoreg run SESSION` does: the session file's [lighting], "
                                     "[render], the client-settable [reconstruction] keys, [[objects]] (meshes "
                                     "named by file name in the server's --meshes) and recording.use_poses = "
                                     "false as track; RECORDING is read as its [recording] says (format, "
                                     "undistort, pose_time_offset) and its frames are sent unless --frames is "
                                     "given (its device is the server's to choose)")
    p.add_argument("--render-stride", type=int, help="ask the server to sample the objects' shadows every n-th "
                                                     "pixel (render.stride, default 4)")
    p.add_argument("--composite", choices=["jpeg", "png"], help="encoding of the composites the server sends for "
                                                                "objects (default jpeg; png: lossless)")
    p.add_argument("--no-poses", action="store_true", help="ask the server to track the camera instead of "
                                                           "using recorded poses")
    p.add_argument("--pose-time-offset", type=float, help="seconds added to the frames' times where the recorded poses "
                                                          "sent are looked up (default: the --session's "
                                                          "recording.pose_time_offset, else 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("bench", help="benchmarks: speed (per-stage ms), the speed-against-error sweep, the shadow "
                                     "renderers side by side")
    bsub = p.add_subparsers(dest="bench_kind", required=True)
    b = bsub.add_parser("speed", help="per-stage milliseconds on a recording")
    b.add_argument("recording", help="recording folder, or a SESSION.toml: its objects are inserted and the "
                                     "render stage (R_TRV, G-buffer, composite) is timed too")
    b.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None)
    b.add_argument("--frames", help="frames to use (default: the session's, else 0:12)")
    b.add_argument("--warmup", type=int, default=2, help="leading frames left out of the figures")
    b.add_argument("--stride", type=int, help="lighting stride (default: the session's, else 4); every setting not "
                                              "given is the session's")
    b.add_argument("--rays", type=int, help="visibility rays (default: the session's, else 64)")
    b.add_argument("--bands", type=int, help="SH bands (default: the session's, else 3)")
    b.add_argument("--render-stride", type=int, help="sessions with objects: their shadows sampled every n-th pixel "
                                                     "(render.stride; default the session's)")
    b.add_argument("--gbuffer", choices=GBUFFER_BACKENDS, help="sessions with objects: their G-buffer's backend "
                                                               "(render.gbuffer; default the session's)")
    b.add_argument("--shutter", type=float, help="sessions with objects: seconds the shutter is open, the objects "
                                                 "motion-blurred (render.shutter; default the session's)")
    b.add_argument("--voxel-size", type=float)
    b.add_argument("--ray-length", type=float)
    b.add_argument("--every", type=int, help="estimate the lighting on every n-th frame (lighting.every)")
    b.add_argument("--async", dest="asynchronous", action="store_true",
                   help="estimate the lighting in a worker thread beside the frames (lighting.asynchronous)")
    b.add_argument("--no-solve-process", action="store_true",
                   help="with --async, the robust solves in the worker thread, not a child process "
                        "(lighting.solve_process = false)")
    b.add_argument("--normal-smoothing", type=float,
                   help="ray-cast normals' tangent mean, radius in voxels (reconstruction.normal_smoothing_voxels)")
    b.add_argument("--threads", type=int, help="CPU threads for the split kernel launches (default: all cores)")
    b.add_argument("--no-sun", action="store_true", help="without the traced light (lighting.sun = false)")
    b.add_argument("--no-history", action="store_true", help="the current view's samples only (lighting.history = 0)")
    b.add_argument("--no-poses", action="store_true", help="track the camera instead of using the recorded poses "
                                                           "(the pose stage timed)")
    b.add_argument("--no-bounce", action="store_true", help="without the bounce term (lighting.bounce = false)")
    b.add_argument("--no-observed-bounce", action="store_true",
                   help="the bounce without the fused luminance of observed hits (lighting.bounce_observed = false)")
    b.add_argument("--json", dest="json_out", help="write the figures to this JSON file")
    b = bsub.add_parser("sweep", help="speed against lighting error over stride x rays x bands x voxel size "
                                      "on generated scenes with ground truth: CSV + Pareto plot")
    b.add_argument("--scenes", default="tabletop,corner", help="scene kinds generated (once) into --synth-dir")
    b.add_argument("--synth-dir", help="scene cache folder (default ~/.cache/photoreg/bench_scenes)")
    b.add_argument("--recordings", nargs="+", help="use these recordings with lighting_gt.json instead of --scenes")
    b.add_argument("--size", default="320x240", help="WxH of generated scenes")
    b.add_argument("--frames", type=int, default=8, help="frames per recording")
    b.add_argument("--spp", type=int, default=64, help="samples per pixel of generated scenes")
    b.add_argument("--warmup", type=int, default=2, help="leading frames of each recording left out of the timings")
    b.add_argument("--strides", default="1,2,4,8")
    b.add_argument("--rays", default="16,64,169,300")
    b.add_argument("--bands", default="2,3,4,5")
    b.add_argument("--voxel-sizes", default="0.01,0.02", help="metres, comma-separated")
    b.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None)
    b.add_argument("--threads", type=int, help="CPU threads for the split kernel launches (default: all cores)")
    b.add_argument("--csv", default="benchmarks/speed_error.csv", help="results table (rows merged by device + setting)")
    b.add_argument("--plot", default="benchmarks/speed_error.png", help="Pareto plot PNG")
    b.add_argument("--plot-only", action="store_true", help="only redraw --plot from the rows in --csv")

    b = bsub.add_parser("renderers", help="every shadow renderer on generated insert scenes: ms per frame "
                                          "against composite error and flicker (benchmarks/renderers.md)")
    b.add_argument("--scenes", default="tabletop,corner,plane,split_albedo,coloured", help="scene kinds")
    b.add_argument("--renderers", help="comma-separated (default: every registered renderer)")
    b.add_argument("--synth-dir", help="scene cache folder (default ~/.cache/photoreg/bench_scenes)")
    b.add_argument("--size", default="160x120", help="WxH of generated scenes")
    b.add_argument("--frames", type=int, default=8, help="frames per generated recording")
    b.add_argument("--spp", type=int, default=32, help="samples per pixel of generated scenes")
    b.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None)
    b.add_argument("--results-dir", default="benchmarks/results",
                   help="JSON rows per device and ground-truth spp go here")
    b.add_argument("--md", help="report rebuilt from every device's rows in --results-dir (default "
                                "benchmarks/renderers.md, or renderers.md in another --results-dir)")
    b.add_argument("--plot", help="ms against si-RMSE plot (default benchmarks/renderers.png, or renderers.png in "
                                  "another --results-dir)")
    b.add_argument("--insert-mesh", help="insert this mesh file instead of the cube (photoreg synth --insert-mesh); "
                                         "its rows go to a JSON file of their own")

    p = sub.add_parser("train", help="train learned renderers' weights for a session's objects")
    tsub = p.add_subparsers(dest="train_kind", required=True)
    t = tsub.add_parser("neural_soft", help="neural soft-shadow MLP per object (cached by mesh hash)")
    t.add_argument("session", help="session file (.toml) whose [[objects]] to train")
    t.add_argument("--out", help="write weights here (default: the cache, $PHOTOREG_CACHE or ~/.cache/photoreg, "
                                 "where runs look, as in data/weights/neural_soft; a run does not read --out's folder)")
    t.add_argument("--force", action="store_true", help="train even when weights are cached")
    t.add_argument("--up", choices=("auto",) + AXES, default="auto",
                   help="the side of each mesh it stands on, by the axis of the mesh's own frame that points up "
                        "(write --up=-y for a negative one); auto: the side a run takes, whose plane the real surface "
                        "near the object fills, found in the depth of the session's first frames with a pose (its "
                        "frames' notes say which)")

    p = sub.add_parser("batch", help="run many session files, each into its own output folder (local workers or Ray)")
    p.add_argument("sessions", nargs="+", help="session files (sessions/*.toml); their keys, values, recordings "
                                               "and mesh files are checked before any runs")
    p.add_argument("--workers", type=int,
                   help="sessions run at once (default: per GPU one for every host core of its share, at most one "
                        "per 2 GB of its memory; without GPUs one per CPU core; at most one per 2 GB of free host memory; "
                        "Ray: the same share of each GPU, and "
                        "--workers sets the CPUs, so the sessions at once, of a local instance it starts)")
    p.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="local process pool (default) or Ray tasks (extra 'ray')")
    p.add_argument("--ray-address", help="connect to this Ray cluster (default: start a local Ray instance)")
    p.add_argument("--resume", action="store_true",
                   help="skip sessions whose outputs are complete and whose settings (as resolved) and meshes are "
                        "unchanged")
    p.add_argument("--out", default="out/batch",
                   help="batch report folder: batch_summary.json, batch_report.md, plot (default out/batch)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None,
                   help="compute device for every session (default: each session's own; GPUs shared round-robin)")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    module, func = HANDLERS[args.command].split(":")
    try:
        return int(getattr(importlib.import_module(module), func)(args) or 0)
    except BrokenPipeError:   # `photoreg info X | head`: the reader is gone, as with SIGPIPE's status, no message
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())   # nor one at exit, flushing stdout
        return 128 + signal.SIGPIPE
    except (ValueError, OSError, RuntimeError) as e:   # OSError: a file that cannot be read or written, named
        print(f"photoreg {args.command}: error: {open3d_message(e)}", file=sys.stderr)
        return 2
    except MemoryError as e:
        print(f"photoreg {args.command}: error: out of memory ({str(e) or 'an allocation failed'}): do the "
              "settings ask for more than this machine holds (lighting.rays, stride, history, the frames' size)?",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:   # Ctrl-C: what was written whole stays (files are renamed into place), no traceback
        print(f"\nphotoreg {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
