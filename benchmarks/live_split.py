"""Where a live client's frame time goes on the server: the median gap between lighting replies against the
pipeline's own median frame (timings_ms.total), and the server's latency split into queue and pipeline.

  python benchmarks/live_split.py URL RECORDING [--session SESSION.toml] [--frames 100] [--color png] [--depth png16]

Streams RECORDING's first frames through a running `photoreg serve` at URL (`--async`, two frames in flight, the
frames encoded as `photoreg stream --color --depth` sends them) and prints one JSON line; the first 5 replies are
left out.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from photoreg.io.recording import ReadAhead, open_recording  # noqa: E402
from photoreg.service.client import connect, encoded_ahead, session_options  # noqa: E402

WINDOW = 2


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("url")
    ap.add_argument("recording")
    ap.add_argument("--session")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--color", default="png")
    ap.add_argument("--depth", default="png16")
    a = ap.parse_args()
    rec = open_recording(a.recording)
    options = session_options(a.session) if a.session else {}
    options.setdefault("lighting", {})["asynchronous"] = True
    client = connect(a.url, rec.intrinsics, options)
    replies, in_flight = [], 0

    def take(msg: dict) -> None:
        nonlocal in_flight
        if msg["type"] == "lighting":
            in_flight -= 1
            replies.append((time.perf_counter(), msg["latency_ms"], msg["queue_ms"], msg["timings_ms"]["total"]))

    t0 = time.perf_counter()
    frames = ReadAhead(rec, range(a.frames), threads=4)
    for _, message in encoded_ahead(frames, a.color, a.depth, 4):
        while in_flight >= WINDOW:
            take(client.recv(120))
        client.send_message(message)
        in_flight += 1
    for msg in client.finish(120):
        take(msg)
    wall = time.perf_counter() - t0
    r = np.array(replies[5:])
    print(json.dumps({"color": a.color, "depth": a.depth, "frames": len(replies),
                      "frames_per_s": round(len(replies) / wall, 1),
                      "reply_gap_ms": round(float(np.median(np.diff(r[:, 0]))) * 1000, 1),
                      "pipeline_frame_ms": round(float(np.median(r[:, 3])), 1),
                      "server_latency_ms": round(float(np.median(r[:, 1])), 1),
                      "queue_ms": round(float(np.median(r[:, 2])), 1)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
