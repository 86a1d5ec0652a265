"""`photoreg run` of this tree against an earlier commit's package, alternating: frames/s as a run's summary gives
them (wall clock, the output files included) and whether both wrote the same files.

usage: python benchmarks/run_ab.py OLD LABEL=SESSION[,FLAGS] ... [--frames A:B] [--device cuda] [--rounds 2]
       [--json OUT.json]
OLD: a folder holding an earlier commit's photoreg/ (`git archive COMMIT photoreg | tar -x -C OLD`); FLAGS: extra
`photoreg run` options, space-separated (e.g. "demo=data/demo/session.toml,--async"). The first round's outputs of
both are compared file by file (composites decoded, EXR pixels): equal where the run is deterministic (not --async).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from photoreg.io.images import read_exr  # noqa: E402


def run(code_dir: Path, session: str, flags: list[str], out: Path, frames: str, device: str) -> dict:
    """One `photoreg run` with the package in code_dir; its summary.json."""
    if out.exists():
        shutil.rmtree(out)
    env = dict(os.environ, PYTHONPATH=f"{code_dir}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    subprocess.run([sys.executable, "-m", "photoreg", "run", str(Path(session).resolve()), "--out", str(out),
                    "--frames", frames, "--device", device, "--quiet", *flags], cwd=code_dir, env=env, check=True,
                   stdout=subprocess.DEVNULL)
    return json.loads((out / "summary.json").read_text())


def largest_difference(a: Path, b: Path) -> dict:
    """Per output folder: files compared and the largest pixel difference (PNG codes, EXR values)."""
    res = {}
    for sub in ("composite", "composite_linear", "lightmap", "envmap", "sphere"):
        files = sorted(p.name for p in (a / sub).glob("*") if p.suffix in (".png", ".jpg", ".exr"))
        if not files:
            continue
        worst = 0.0
        for name in files:
            if not (b / sub / name).exists():
                worst = float("inf")
                break
            read = read_exr if name.endswith(".exr") else (lambda p: cv2.imread(str(p), cv2.IMREAD_UNCHANGED))
            x, y = np.asarray(read(a / sub / name), np.float64), np.asarray(read(b / sub / name), np.float64)
            worst = max(worst, float(np.abs(x - y).max()) if x.shape == y.shape else float("inf"))
        res[sub] = {"files": len(files), "largest_difference": worst}
    return res


def save(rows: list[dict], path: str | None) -> None:
    """Print the latest row; write every row so far to `path` (a run cut short keeps the rows it has)."""
    print(json.dumps(rows[-1]), flush=True)
    if path:
        Path(path).write_text(json.dumps(rows, indent=1) + "\n")


def ab_parser(doc: str, work: str, *positional: str) -> argparse.ArgumentParser:
    """The A/B scripts' arguments: OLD, the `positional` ones, LABEL=[SESSION][,FLAGS] runs, --frames, --device,
    --rounds, --work (default `work`) and --json."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("old")
    for name in positional:
        ap.add_argument(name)
    ap.add_argument("runs", nargs="+", help="LABEL=[SESSION][,FLAGS]")
    ap.add_argument("--frames", default="0:40")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--work", default=work)
    ap.add_argument("--json")
    return ap


def ab_rounds(args, run, figures, alternate: bool = False) -> None:
    """Each round, each of args.runs with the package in args.old and with this tree, one after the other (with
    `alternate` this tree first in even rounds): run(code folder, session, flags, output folder) gives the summary,
    figures(summary) its row, saved as they come (`save`); the first round's outputs of both are compared
    (largest_difference) where the run has a session."""
    old, work = Path(args.old).resolve(), Path(args.work)
    codes = (("old", old), ("new", REPO))
    rows = []
    for rnd in range(1, args.rounds + 1):
        for spec in args.runs:
            label, rest = spec.split("=", 1)
            session, _, flags = rest.partition(",")
            outs = {}
            for code, where in codes if rnd % 2 or not alternate else codes[::-1]:
                outs[code] = work / f"{label}_{code}_{rnd}"
                rows.append({"run": label, "code": code, "round": rnd, "flags": flags,
                             **figures(run(where, session, flags.split(), outs[code]))})
                save(rows, args.json)
            if rnd == 1 and session:
                rows.append({"run": label, "compare": largest_difference(outs["old"], outs["new"])})
                save(rows, args.json)


def main() -> int:
    args = ab_parser(__doc__, "/tmp/run_ab").parse_args()
    ab_rounds(args, lambda where, session, flags, out: run(where, session, flags, out, args.frames, args.device),
              lambda s: {"frames": s["frames_processed"], "wall_s": s["wall_s"], "frames_per_s": s["frames_per_s"],
                         "frame_ms_mean": s["timings_ms_mean"].get("total"), "device": s["device"],
                         "read_wait_s": s.get("read_wait_s"), "write_wait_s": s.get("write_wait_s")})
    return 0


if __name__ == "__main__":
    sys.exit(main())
