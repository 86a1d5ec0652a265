"""`photoreg` command line: every subcommand's arguments here, its work in the owning module."""
from __future__ import annotations

import argparse
import importlib
import sys

# subcommand -> "module:function"; the function takes the parsed argparse.Namespace and returns an exit code.
HANDLERS = {
    "run": "photoreg.runner:run_command",
    "demo": "photoreg.runner:demo_command",
    "info": "photoreg.io.recording:info_command",
    "synth": "photoreg.synth.generate:synth_command",
    "score": "photoreg.bench.score:score_command",
}


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", help="output folder (overrides the session's [output] dir)")
    p.add_argument("--frames", help="frames to process: N (first N), A:B or A:B:S (0-based, end exclusive)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None, help="compute device (default auto)")
    p.add_argument("--stride", type=int, help="sample every n-th pixel for the transfer (1, 2, 4, ...)")
    p.add_argument("--rays", type=int, help="visibility rays per pixel over the hemisphere")
    p.add_argument("--bands", type=int, help="SH bands B of the lighting (B*B coefficients)")
    p.add_argument("--voxel-size", type=float, help="TSDF voxel size in metres")
    p.add_argument("--ray-length", type=float, help="visibility ray length in metres")
    p.add_argument("--no-poses", action="store_true", help="ignore recorded poses and track the camera")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="photoreg", description="Photometric registration from RGB-D recordings.")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="estimate per-frame lighting for a recording or a session file")
    p.add_argument("input", help="session file (.toml) or recording folder")
    _add_run_options(p)

    p = sub.add_parser("demo", help="run on the embedded demo recording (data/demo)")
    _add_run_options(p)

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
    p.add_argument("--camera", default="orbit", choices=["orbit", "handheld", "static"])
    p.add_argument("--direct-only", action="store_true", help="direct illumination only (no interreflection)")
    p.add_argument("--insert-frames", default="auto", help="frames re-rendered with a virtual object: list or 'auto'")
    p.add_argument("--no-noise", action="store_true", help="write clean depth only")

    p = sub.add_parser("score", help="official accuracy metrics of a run against ground truth")
    p.add_argument("out", help="output folder of a run (holds lighting.jsonl)")
    p.add_argument("--gt", required=True, help="recording folder with lighting_gt.json")
    p.add_argument("--composite", action="store_true", help="also score composites against insert renders")
    p.add_argument("--json", dest="json_out", help="write the scores to this JSON file")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    module, func = HANDLERS[args.command].split(":")
    try:
        return int(getattr(importlib.import_module(module), func)(args) or 0)
    except (ValueError, FileNotFoundError, RuntimeError) as e:
        print(f"photoreg {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
