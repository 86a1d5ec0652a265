"""Several live clients at once: `photoreg serve` with its connections' pipelines on threads of one process (--threads)
against a process each (the default), the modes alternating over rounds (benchmarks/speed.md, "Several clients at once").

    python benchmarks/serve_clients.py RECORDING [--clients 2] [--frames 0:20] [--rounds 2] [--device cpu]
        [--meshes DIR] [--json OUT.json] [-- STREAM ARGS...]

Each run starts `photoreg serve --port P --max-clients N` (plus --threads), waits for it to listen, runs N
`photoreg stream RECORDING` at once (each with its own --out), and reads their summary.json: frames/s in all
(frames processed over the wall time from the first client's start to the last one's end, hellos included), each
client's own frames/s, its median latency and its hello's time (connect, hello, ready).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def one_run(a, processes: bool, stream_args: list[str], work: Path) -> dict:
    """One server, a.clients streams at once; the figures of the run."""
    port = free_port()
    cmd = [sys.executable, "-m", "photoreg", "serve", "--port", str(port), "--device", a.device,
           "--max-clients", str(a.clients)] + ([] if processes else ["--threads"]) + \
          (["--meshes", str(Path(a.meshes).resolve())] if a.meshes else [])
    server = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = server.stdout.readline()
        if not re.search(r"listening on ws://", line):
            sys.exit(f"the server did not start: {line!r}")
        outs = [work / f"{'proc' if processes else 'thread'}_{time.monotonic_ns()}_{k}" for k in range(a.clients)]
        t0 = time.perf_counter()
        clients = [subprocess.Popen([sys.executable, "-m", "photoreg", "stream", a.recording, "--url",
                                     f"ws://127.0.0.1:{port}", "--frames", a.frames, "--out", str(out), "--quiet",
                                     *stream_args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                   for out in outs]
        for c in clients:
            if c.wait() != 0:
                sys.exit(f"a client failed: {c.stderr.read()[-2000:]}")
        wall = time.perf_counter() - t0
    finally:
        server.terminate()
        server.wait(60)
    sums = [json.loads((out / "summary.json").read_text()) for out in outs]
    frames = sum(s["frames_processed"] for s in sums)
    return {"mode": "processes" if processes else "threads", "clients": a.clients, "wall_s": round(wall, 2),
            "frames": frames, "frames_per_s_in_all": round(frames / wall, 2),
            "client_frames_per_s": [s["frames_per_s"] for s in sums],
            "client_latency_p50_ms": [round(s["latency_ms"]["p50"]) for s in sums],
            "client_hello_ms": [s["hello_ms"] for s in sums],
            "errors": sum(len(s["errors"]) for s in sums)}


def main() -> None:
    argv = sys.argv[1:]
    stream_args = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording")
    ap.add_argument("--clients", type=int, default=2)
    ap.add_argument("--frames", default="0:20")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--meshes", help="the server's --meshes (for STREAM ARGS with a --session that inserts objects)")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.rounds):
            for processes in (False, True):
                run = {"round": r + 1, **one_run(a, processes, stream_args, Path(tmp))}
                print(json.dumps(run), flush=True)
                runs.append(run)
    if a.json:
        Path(a.json).write_text(json.dumps({"recording": a.recording, "device": a.device, "frames": a.frames,
                                            "stream_args": stream_args, "runs": runs}, indent=1))


if __name__ == "__main__":
    main()
