"""Motion blur of the inserted objects (render.shutter) against Mitsuba's renders of a moving camera.

usage: python benchmarks/motion_blur.py [--synth-dir /tmp/photoreg_blur] [--shutter 0.016]
       [--md benchmarks/motion_blur.md]

Generates the tabletop seen by a camera that orbits it and turns left and right as it goes (`photoreg synth
--camera pan`), once with the shutter open for --shutter seconds (colour and inserts averaged over it) and once for an
instant, and then
1. runs each recording's session with render.shutter 0 and --shutter and scores the composites in the objects'
   neighbourhood (`photoreg score --composite`: si-RMSE, and the correlation of the insertion, composite less
   frame, with the path tracer's, which the lighting estimate's error in brightness does not enter);
2. isolates the blur from the lighting: Mitsuba's own insertion of the instant recording (its insert render as
   layers over its frame, composite.layers_of; 1024 spp, 160x120), composited over the blurred frame and blurred by
   photoreg.render.motion_blur at several shutter times, against Mitsuba's blurred insert render (RMSE in the
   neighbourhood).
Writes the generated section of --md.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import lighting_accuracy as la  # noqa: E402  (puts the repository first on the path)

from photoreg.bench.score import insert_truth, score_composites  # noqa: E402
from photoreg.config import load_session, validate  # noqa: E402
from photoreg.io.images import read_exr, srgb_to_linear  # noqa: E402
from photoreg.io.recording import open_recording  # noqa: E402
from photoreg.render.composite import composite, layers_of  # noqa: E402
from photoreg.render.motion_blur import Motion, blurred_composite  # noqa: E402
from photoreg.runner import run_session  # noqa: E402
from photoreg.synth.generate import FPS  # noqa: E402

INSERTS = "1,8,15,22"     # frames where the pan turns fastest
ISOLATED_FRAME = 15


def synth(folder: Path, name: str, shutter: float, size: str, spp: int, frames: int, inserts: str) -> tuple[Path, str]:
    """The panning tabletop with the shutter open `shutter` seconds, in folder/name (lighting_accuracy.ensure_synth)."""
    return la.ensure_synth(folder, "tabletop", frames, size, spp, ("--camera", "pan", "--shutter", f"{shutter:g}"),
                           name, inserts)


def insertion_correlation(out: Path, recording: Path) -> float:
    """Mean over insert frames of the luminance correlation, in the objects' neighbourhood, between the composite's
    insertion (composite less frame) and the path tracer's."""
    values = []
    for t in insert_truth(recording):
        ours = read_exr(out / "composite_linear" / f"{t.frame:06d}.exr") - t.camera
        values.append(np.corrcoef((t.gt - t.camera)[t.roi].mean(-1), ours[t.roi].mean(-1))[0, 1])
    return float(np.mean(values))


def pipeline_rows(folder: Path, shutter: float, size: str, spp: int, frames: int) -> tuple[list[str], list[str]]:
    rows, commands = [], []
    for name, rec_shutter in (("shutter open", shutter), ("an instant", 0.0)):
        rec, cmd = synth(folder, f"pan_{rec_shutter:g}s", rec_shutter, size, spp, frames, INSERTS)
        commands.append(cmd)
        cells = []
        for render_shutter in (0.0, shutter):
            s = load_session(rec / "session.toml")
            s.render.shutter, s.output.pictures_every = render_shutter, 0
            s.output.dir = str(folder / f"out_{rec.name}_{render_shutter:g}")
            validate(s)
            run_session(s, quiet=True)
            m = score_composites(s.output.dir, rec)["metrics"]
            cells.append(f"{m['si_rmse']['mean']:.4f} / {insertion_correlation(Path(s.output.dir), rec):.3f}")
            baseline = m["baseline_si_rmse"]["mean"]
        rows.append(f"| {name} ({rec_shutter * 1000:g} ms) | {cells[0]} | {cells[1]} | {baseline:.4f} |")
        print(rows[-1], flush=True)
    return rows, commands


def isolated_row(folder: Path, shutter: float) -> tuple[str, list[str], list[float]]:
    made = {s: synth(folder, f"pan_hq_{s:g}s", s, "160x120", 1024, 30, str(ISOLATED_FRAME)) for s in (shutter, 0.0)}
    recs, commands = {s: r for s, (r, _) in made.items()}, [c for _, c in made.values()]
    sharp, blurred = open_recording(recs[0.0]), open_recording(recs[shutter])
    f0, f1, b1 = sharp.frame(ISOLATED_FRAME - 1), sharp.frame(ISOLATED_FRAME), blurred.frame(ISOLATED_FRAME)
    name = f"{ISOLATED_FRAME:06d}.exr"
    sharp_truth = insert_truth(recs[0.0])[0]
    layers = layers_of(sharp_truth.gt, sharp_truth.camera, sharp_truth.mask)
    cam = srgb_to_linear(b1.color).astype(np.float32)
    truth, roi = read_exr(recs[shutter] / "insert" / name), sharp_truth.roi
    times = [0.0, 0.5 * shutter, shutter, 1.5 * shutter, 2.0 * shutter]
    errors = []
    for t in times:
        out = composite(cam, layers) if not t else blurred_composite(
            cam, layers, f1.depth, sharp.intrinsics, Motion(f1.pose, f0.pose, t * FPS))[0]
        errors.append(float(np.sqrt(np.mean((out[roi] - truth[roi]) ** 2))))
    header = " | ".join(f"{t * 1000:g} ms" for t in times)
    return header, commands, errors


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--synth-dir", default="/tmp/photoreg_blur")
    ap.add_argument("--shutter", type=float, default=0.016)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--md", default=str(Path(__file__).with_name("motion_blur.md")))
    a = ap.parse_args()
    folder = Path(a.synth_dir)
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows, commands = pipeline_rows(folder, a.shutter, a.size, a.spp, a.frames)
    header, hq_commands, errors = isolated_row(folder, a.shutter)
    cmd = " ".join(["python", "benchmarks/motion_blur.py", *sys.argv[1:]])
    lines = [f"Generated by `{cmd}` ({time.perf_counter() - t0:.0f} s on this machine).", "",
             f"**The pipeline** (`photoreg run` of the recording's session, {a.size}, {a.frames} frames, {a.spp} spp; "
             f"insert frames {INSERTS}). Cells: composite si-RMSE in the objects' neighbourhood (mean over the insert "
             "frames) / correlation of the insertion (composite less frame) with the path tracer's.", "",
             f"| recording's shutter | render.shutter = 0 | render.shutter = {a.shutter:g} | no-shadow baseline |",
             "|---|---|---|---|", *rows, "",
             f"**The blur alone** (frame {ISOLATED_FRAME}, 160x120, 1024 spp): Mitsuba's insertion of the instant "
             "recording as layers over the blurred frame, blurred for each shutter time, against Mitsuba's insert "
             f"render with the shutter open {a.shutter * 1000:g} ms; RMSE in the neighbourhood.", "",
             f"| {header} |", "|" + "---|" * len(errors), "| " + " | ".join(f"{e:.4f}" for e in errors) + " |", "",
             "Recordings:", *[f"- `{c}`" for c in commands + hq_commands]]
    la.write_generated(Path(a.md), [la.START, "", *lines, "", la.END], "Motion blur")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
