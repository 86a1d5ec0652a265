"""`photoreg run` / `photoreg demo`: a recording or session file in, per-frame lighting and pictures out."""
from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .config import Session, load_session, select_frames, validate
from .io.atomic import check_output_dir, finite_json, hold_folder, write_json
from .io.images import linear_to_srgb, write_exr, write_png_rgb
from .io.poses import write_tum_trajectory
from .io.video import VideoOut, frame_rate
from .io.writer import OutputWriter
from .lighting.visualize import latlong, lit_sphere, tonemap
from .types import FrameResult

# at most this many threads write a run's files (an H100 host, TUM with the bunny, --async: 22-24 frames/s, no frame
# waited for them)
WRITER_THREADS = 4
DEMO_SESSION = Path(__file__).resolve().parents[1] / "data" / "demo" / "session.toml"
# OUT/.complete: written by `photoreg batch` once a session's outputs are whole, removed by every run that starts
# writing its frames
COMPLETE_MARKER = ".complete"
# a run's per-frame files, folder -> extensions, and its other files: an earlier run's are removed as a run writes its
# first frame, so that a folder never mixes two runs (clear_earlier)
PICTURE_DIRS = {"envmap": (".exr", ".png"), "sphere": (".png",)}
COMPOSITE_DIRS = {"composite": (".png",), "composite_linear": (".exr",), "lightmap": (".exr",)}
RUN_FILES = ("lighting.jsonl", "summary.json", "composite.mp4", "composite.partial.mp4", "trajectory.txt")


@dataclass(frozen=True)
class FrameDone:
    """What the run's summary and trajectory need of a processed frame: its FrameResult, composite and all, kept for
    every frame until the end grew a run by 0.9 MB a frame at 320x240 with objects (66 GB in 10 minutes at 640x480)."""

    index: int
    timestamp: float
    weak: bool
    composited: bool
    in_view: bool             # a pixel of its composite shows an object
    pose: np.ndarray | None   # kept where the camera is tracked (trajectory.txt)


class StageTimes:
    """Each stage's ms summed over the frames (a run or a stream keeps no frame's timings): add() a frame's,
    means() over every frame added, a stage a frame did not run counting 0 there."""

    def __init__(self) -> None:
        self.total: dict[str, float] = {}
        self.frames = 0

    def add(self, timings_ms: dict[str, float]) -> None:
        self.frames += 1
        for stage, ms in timings_ms.items():
            self.total[stage] = self.total.get(stage, 0.0) + ms

    def means(self) -> dict[str, float]:
        return {k: round(v / self.frames, 3) for k, v in sorted(self.total.items())}


def session_from_args(args) -> Session:
    """Session from a .toml file or a bare recording folder, with command-line overrides applied."""
    src = Path(args.input)
    if src.suffix.lower() == ".toml":
        s = load_session(src)
    else:
        if not src.exists():
            raise FileNotFoundError(f"{src}: no such recording folder or session file")
        s = Session()
        s.recording.path = str(src.resolve())
        s.output.dir = str(Path("out") / Path(os.path.abspath(src)).name)   # `..` named, a link's own name kept
    if args.out:
        s.output.dir = args.out
    if args.frames:
        s.frames = args.frames
    if args.device:
        s.device = args.device
    if args.no_poses:
        s.recording.use_poses = False
    if args.video:
        s.output.video = True
    if args.asynchronous:
        s.lighting.asynchronous = True
    for opt, section, key in (("pose_time_offset", "recording", "pose_time_offset"),
                              ("stride", "lighting", "stride"), ("rays", "lighting", "rays"),
                              ("bands", "lighting", "bands"), ("ray_length", "lighting", "ray_length"),
                              ("every", "lighting", "every"),
                              ("depth_filter", "reconstruction", "depth_filter_px"),
                              ("normal_smoothing", "reconstruction", "normal_smoothing_voxels"),
                              ("voxel_size", "reconstruction", "voxel_size"), ("shadows", "render", "shadows"),
                              ("render_stride", "render", "stride"), ("gbuffer", "render", "gbuffer"),
                              ("shutter", "render", "shutter")):
        v = getattr(args, opt)
        if v is not None:
            setattr(getattr(s, section), key, v)
    validate(s)
    return s


class Progress:
    """One status line on stderr: frames done, frames/s, time left."""

    def __init__(self, total: int, quiet: bool):
        self.total, self.quiet, self.t0, self.done = total, quiet or not total, time.perf_counter(), 0

    def step(self, note: str = "") -> None:
        self.done += 1
        if self.quiet:
            return
        el = time.perf_counter() - self.t0
        fps = self.done / el if el > 0 else 0.0
        left = (self.total - self.done) / fps if fps > 0 else 0.0
        bar = "#" * int(30 * self.done / self.total)
        print(f"\r[{bar:<30}] {self.done}/{self.total}  {fps:5.2f} frames/s  {left:5.0f} s left {note[:40]:<40}",
              end="", file=sys.stderr, flush=True)

    def close(self) -> None:
        if not self.quiet:
            print(file=sys.stderr)


def result_record(r: FrameResult) -> dict:
    """One lighting.jsonl object (DESIGN.md 'Files'), strict JSON: a non-finite number would be null."""
    return finite_json({
        "frame": r.index, "timestamp": r.timestamp, "bands": r.lighting.bands,
        "sh": np.round(r.lighting.sh, 7).tolist(), "dominant_direction": np.round(r.dominant_direction, 6).tolist(),
        "diagnostics": r.diagnostics.to_json(), "timings_ms": {k: round(v, 3) for k, v in r.timings_ms.items()},
        "pose": None if r.pose is None else np.round(r.pose, 7).tolist()})


def write_pictures(out: Path, r: FrameResult) -> None:
    """Lat-long estimate (EXR linear + PNG tonemapped) and a lit sphere seen from the frame's camera (its pose as
    the pipeline had it: recorded or tracked)."""
    name = f"{r.index:06d}"
    env = latlong(r.lighting.sh)
    write_exr(out / "envmap" / f"{name}.exr", env)
    write_png_rgb(out / "envmap" / f"{name}.png", linear_to_srgb(tonemap(env)))
    sphere = lit_sphere(r.lighting.sh, r.pose if r.pose is not None else np.eye(4))
    write_png_rgb(out / "sphere" / f"{name}.png", linear_to_srgb(tonemap(sphere)))


def write_composite(out: Path, r: FrameResult, lightmap: np.ndarray) -> None:
    """composite/NNNNNN.png (sRGB), composite_linear/NNNNNN.exr (16-bit floats) and lightmap/NNNNNN.exr: the linear
    shadow-ratio layer on real surfaces (1 = unchanged, cam * ratio = real pixel), all atomic."""
    name = f"{r.index:06d}"
    write_png_rgb(out / "composite" / f"{name}.png", linear_to_srgb(r.composite))
    write_exr(out / "composite_linear" / f"{name}.exr", r.composite, half=True)
    write_exr(out / "lightmap" / f"{name}.exr", lightmap)


def clear_earlier(out: Path, dirs: dict[str, tuple[str, ...]], files: tuple[str, ...]) -> list[Path]:
    """Remove an earlier run's outputs from `out` as this run writes its first frame's: the NNNNNN.ext files of the
    per-frame folders `dirs` (folder -> extensions) and the named `files` that are there, and a batch's completion
    marker; other files are never touched. From then on the folder holds this run's files alone, an interrupted run's
    too (its frames written over an earlier run's had left the two mixed, which photoreg score took for one run); a
    run that processes no frame replaces nothing. Returns the outputs removed (the marker aside)."""
    removed = [p for folder, exts in dirs.items() if (out / folder).is_dir() for p in (out / folder).iterdir()
               if p.suffix in exts and len(p.stem) == 6 and p.stem.isdigit()]
    removed += [out / name for name in files if (out / name).is_file()]
    for p in removed:
        p.unlink(missing_ok=True)
    (out / COMPLETE_MARKER).unlink(missing_ok=True)
    if removed:
        print(f"photoreg: removed {len(removed)} file(s) an earlier run left in {out}", file=sys.stderr)
    return removed


def track_without_poses(s: Session, rec, who: str) -> None:
    """A recording without poses has its camera tracked (recording.use_poses off), said on stderr by `who`: its
    frames are otherwise neither fused nor lit."""
    if s.recording.use_poses and not rec.has_poses:
        print(f"{who}: {s.recording.path} has no poses: tracking the camera instead", file=sys.stderr)
        s.recording.use_poses = False


def writer_threads() -> int:
    """Threads writing a run's files beside the frames: half the threads CPU kernel launches may use (the frames
    keep the rest; a batch worker's share of the cores), at most WRITER_THREADS, at least one."""
    from .kernels.launch import cpu_threads

    return max(1, min(WRITER_THREADS, cpu_threads() // 2))


def run_session(s: Session, quiet: bool = False, on_frame: Callable[[int, int], None] | None = None,
                after: Callable[[dict], None] | None = None) -> dict:
    """Process a session; returns the summary (also written to summary.json).

    on_frame(frames done, frames selected) is called after each frame (batch progress from worker processes). The
    output folder is held (io.atomic.hold_folder) while the frames run and `after(summary)` runs (a batch scores the
    outputs and marks them complete): another run into it is refused."""
    from .io.recording import open_configured
    from .pipeline import Pipeline

    rec = open_configured(s.recording)
    indices = select_frames(s.frames, len(rec), s.recording.path)
    track_without_poses(s, rec, "photoreg")
    for warning in rec.warnings:
        print(f"photoreg: {s.recording.path}: {warning}", file=sys.stderr)
    out = Path(s.output.dir)
    check_output_dir(out, "--out / [output] dir")
    pipe = Pipeline(s, rec.intrinsics)   # bad objects fail here, before the output folder is touched
    out.mkdir(parents=True, exist_ok=True)
    try:
        lock = hold_folder(out, "--out / [output] dir")
    except BaseException:
        pipe.close()
        raise
    try:
        summary = _run_frames(s, rec, indices, pipe, out, quiet, on_frame)
        if after is not None:
            after(summary)
        return summary
    finally:
        if lock is not None:
            os.close(lock)


def _run_frames(s: Session, rec, indices: list[int], pipe, out: Path, quiet: bool,
                on_frame: Callable[[int, int], None] | None) -> dict:
    """run_session's frames into the output folder `out` it holds: lighting.jsonl, the pictures and composites,
    summary.json."""
    from .io.recording import ReadAhead, depth_units_warning

    skipped: list[dict] = []
    results: list[FrameDone] = []
    stage_ms = StageTimes()
    progress = Progress(len(indices), quiet)
    fps = frame_rate(rec.timestamps[indices])
    video = VideoOut(out / "composite.mp4", rec.intrinsics.width, rec.intrinsics.height, fps) if s.output.video else None
    partial = out / "lighting.jsonl.partial"
    t0 = time.perf_counter()
    # frames read ahead and files written beside the frames (the video's frames in order, in a thread of their own)
    threads = writer_threads()
    with open(partial, "w") as f, OutputWriter(threads, name="photoreg-files") as files, \
            OutputWriter(1, name="photoreg-video") as frames:
        reader = ReadAhead(rec, indices, on_error=lambda i, msg: skipped.append({"frame": i, "error": msg}),
                           threads=threads)
        try:
            for frame in reader:
                if not results and (units := depth_units_warning(frame.depth, rec.intrinsics.depth_scale)):
                    print(f"photoreg: {rec.depth_files[frame.index]}: {units}", file=sys.stderr)
                    rec.warnings.append(f"frame {frame.index}: {units}")   # summary.json's recording_warnings
                r = pipe.process(frame)
                if not results:   # the folder becomes this run's (its own partial video is being written)
                    clear_earlier(out, {**PICTURE_DIRS, **COMPOSITE_DIRS}, tuple(
                        n for n in RUN_FILES if video is None or n != video.tmp.name))
                results.append(FrameDone(r.index, r.timestamp, r.diagnostics.weak, r.composite is not None,
                                         bool(r.objects_in_view), r.pose if pipe.tracker is not None else None))
                stage_ms.add(r.timings_ms)
                f.write(json.dumps(result_record(r), allow_nan=False) + "\n")
                f.flush()
                k = s.output.pictures_every
                if k and (len(results) - 1) % k == 0:
                    files.submit(write_pictures, out, r)
                if r.composite is not None:
                    files.submit(write_composite, out, r, pipe.render.last.ratio)
                    if video is not None:
                        frames.submit(video.write, r.composite)
                progress.step(f"frame {frame.index}" + (" (weak)" if r.diagnostics.weak else ""))
                if on_frame is not None:
                    on_frame(len(results), len(indices))
        finally:
            reader.close()
            pipe.close()
    progress.close()
    if video is not None and not video.close():
        video = None
    if not results:   # an earlier run's outputs stand; a batch or a script must not take this run for a success
        partial.unlink(missing_ok=True)
        first = f" (frame {skipped[0]['frame']}: {skipped[0]['error']})" if skipped else ""
        raise ValueError(f"{s.recording.path}: no frame could be processed, all {len(skipped)} selected were "
                         f"skipped{first}; nothing in {out} was replaced")
    os.replace(partial, out / "lighting.jsonl")
    wall = time.perf_counter() - t0
    for sk in skipped:
        print(f"photoreg: skipped frame {sk['frame']}: {sk['error']}", file=sys.stderr)
    summary = {
        "recording": s.recording.path, "recording_warnings": rec.warnings, "device": pipe.device,
        "frames_processed": len(results),
        "frames_skipped": skipped, "wall_s": round(wall, 3),
        "frames_per_s": round(len(results) / wall, 3) if wall > 0 else None,
        # of wall_s: waiting for frames to be read, and for a free slot of the file writers (0: neither set the pace)
        "read_wait_s": round(reader.waited_s, 3), "write_wait_s": round(files.waited_s + frames.waited_s, 3),
        "weak_frames": [r.index for r in results if r.weak],
        "objects": len(s.objects), "shadows": s.render.shadows if s.objects else None,
        # frames composited (a frame without a pose, recorded or tracked, has no composite and no video frame)
        "composites": sum(r.composited for r in results) if s.objects else None,
        "objects_in_view": sum(r.in_view for r in results) if s.objects else None,   # composites showing an object
        "video": None if video is None else {"file": video.path.name, "frames": video.frames, "fps": round(fps, 3)},
        "timings_ms_mean": stage_ms.means(),
        "settings": {"lighting": vars(s.lighting), "reconstruction": vars(s.reconstruction),
                     "use_poses": s.recording.use_poses, "undistort": s.recording.undistort,
                     "pose_time_offset": s.recording.pose_time_offset, "frames": s.frames,
                     "render": vars(s.render) if s.objects else None},
    }
    if pipe.tracker is not None:
        summary["tracking"] = pipe.tracker.report()
        # the tracked trajectory as TUM lines (what trajectory evaluation tools read), frames that failed left out
        write_tum_trajectory(out / "trajectory.txt", [(r.timestamp, r.pose) for r in results if r.pose is not None])
        if rec.has_poses:  # recorded poses were withheld: score the tracked trajectory against them
            from .recon.tracking import ate_against

            summary["tracking"].update(ate_against({r.index: r.pose for r in results if r.pose is not None},
                                                   rec.poses))
    write_json(out / "summary.json", summary)
    return summary


def against_recorded(tracking: dict) -> str:
    """The printed end of a tracked run's or stream's line: its score against the recording's poses, if any."""
    if tracking.get("ate_rmse_m") is None:
        return ""
    return (f"; against the recording's poses: positions {tracking['ate_rmse_m'] * 1000:.1f} mm, orientations "
            f"{tracking['rotation_rmse_deg']:.2f} deg RMSE")


def print_summary(summary: dict, out: str) -> None:
    t = summary["timings_ms_mean"]
    stages = "  ".join(f"{k} {v:.1f}" for k, v in t.items() if k != "total")
    print(f"{summary['frames_processed']} frames on {summary['device']} at {summary['frames_per_s']} frames/s; "
          f"{len(summary['weak_frames'])} weak, {len(summary['frames_skipped'])} skipped")
    if summary.get("objects") and summary["composites"] < summary["frames_processed"]:
        print(f"{summary['frames_processed'] - summary['composites']} frame(s) without a pose have no composite "
              "(lighting.jsonl's notes say why)")
    if summary.get("composites") and not summary["objects_in_view"]:
        tracked = (" A tracked run's (--no-poses) world is its first camera's frame (x right, y down, z forward), "
                   "not the recording's." if "tracking" in summary else "")
        print(f"photoreg: warning: no composite shows an object: check the objects' positions.{tracked}",
              file=sys.stderr)
    if "tracking" in summary:
        tr = summary["tracking"]
        failed = len(tr["failures"]) + tr.get("failures_not_listed", 0)
        print(f"tracked {tr['frames']} frames, {failed} failed, {tr['unconfirmed']} unconfirmed{against_recorded(tr)}")
    print(f"mean ms per stage: {stages}  (total {t.get('total', 0):.1f})")
    def written(name: str) -> bool:   # a folder an earlier run's files were cleared from is not this run's output
        p = Path(out) / name
        return p.is_file() or p.is_dir() and any(p.iterdir())

    names = ("lighting.jsonl", "summary.json", "envmap/", "sphere/", "composite/", "composite_linear/", "lightmap/",
             "composite.mp4", "trajectory.txt")
    print(f"outputs in {out}: {', '.join(n for n in names if written(n))}")


def run_command(args) -> int:
    s = session_from_args(args)
    summary = run_session(s, quiet=args.quiet)
    print_summary(summary, s.output.dir)
    return 0


def demo_command(args) -> int:
    if not DEMO_SESSION.is_file():
        raise FileNotFoundError(f"{DEMO_SESSION}: the embedded demo is missing from this checkout")
    args.input = str(DEMO_SESSION)
    if not args.out:
        args.out = "out/demo"
    return run_command(args)
