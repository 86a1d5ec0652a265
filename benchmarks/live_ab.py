"""`photoreg serve` and `photoreg stream` of this tree against an earlier commit's package, alternating: frames/s and
latency as the streaming client's summary gives them, and whether both servers sent the same composites.

usage: python benchmarks/live_ab.py OLD RECORDING LABEL=[SESSION][,FLAGS] ... [--frames A:B] [--device cuda]
       [--rounds 2] [--meshes DIR] [--json OUT.json]
OLD: a folder holding an earlier commit's photoreg/ (`git archive COMMIT photoreg | tar -x -C OLD`). Each run starts
`photoreg serve` with one package, streams RECORDING through it with the same package's `photoreg stream` (SESSION:
its --session, none for the lighting alone; FLAGS: more `photoreg stream` options, space-separated), then stops the
server. The first round's composites of both are compared (equal where the pipeline is deterministic: not --async).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from run_ab import ab_parser, ab_rounds
from serve_clients import free_port


def run(code_dir: Path, recording: str, session: str, flags: list[str], out: Path, a) -> dict:
    """One server and one stream with the package in code_dir; the stream's summary.json."""
    if out.exists():
        shutil.rmtree(out)
    env = dict(os.environ, PYTHONPATH=f"{code_dir}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", PYTHONUNBUFFERED="1")
    port = free_port()
    meshes = ["--meshes", str(Path(a.meshes).resolve())] if a.meshes else []
    server = subprocess.Popen([sys.executable, "-m", "photoreg", "serve", "--port", str(port), "--device", a.device,
                               *meshes], cwd=code_dir, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                              text=True)
    try:
        line = server.stdout.readline()
        if "listening on ws://" not in line:
            sys.exit(f"the server ({code_dir}) did not start: {line!r}")
        subprocess.run([sys.executable, "-m", "photoreg", "stream", str(Path(recording).resolve()), "--url",
                        f"ws://127.0.0.1:{port}", "--frames", a.frames, "--out", str(out), "--quiet",
                        *(["--session", str(Path(session).resolve())] if session else []), *flags],
                       cwd=code_dir, env=env, check=True, stdout=subprocess.DEVNULL)
    finally:
        server.terminate()
        server.wait(60)
    return json.loads((out / "summary.json").read_text())


def main() -> int:
    ap = ab_parser(__doc__, "/tmp/live_ab", "recording")
    ap.add_argument("--meshes", help="the server's --meshes (the sessions' objects)")
    a = ap.parse_args()
    ab_rounds(a, lambda where, session, flags, out: run(where, a.recording, session, flags, out, a),
              lambda s: {"device": s["device"], "frames": s["frames_processed"], "dropped": s["frames_dropped"],
                         "errors": len(s["errors"]), "wall_s": s["wall_s"], "frames_per_s": s["frames_per_s"],
                         "latency_p50_ms": s["latency_ms"]["p50"], "latency_p95_ms": s["latency_ms"]["p95"],
                         "server_latency_p50_ms": s["server_latency_ms"]["p50"],
                         "frame_ms_mean": s["timings_ms_mean"].get("total")},
              alternate=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
