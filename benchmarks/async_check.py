"""lighting.asynchronous on a device: with the worker waited for after every frame, frame k + 1 must hold the in-line
pipeline's lighting of frame k (the worker runs the same stages on the same state, only in another thread: on CUDA it
launches Warp kernels there too), exactly with the solves in the worker thread, to rounding with them in the child
process (lighting.solve_process, the default: its unpickled arrays sum in another order); running free, every
frame's lighting must be finite and come from an earlier frame.

usage: python benchmarks/async_check.py RECORDING [FRAMES] [DEVICE]   (prints one JSON object; DEVICE default cuda)
"""
import json
import sys

import numpy as np

from photoreg.config import Session
from photoreg.io.recording import iter_frames, open_recording
from photoreg.pipeline import Pipeline


def run(rec, frames, device: str, asynchronous: bool, wait: bool, process: bool = True):
    s = Session()
    s.recording.path = str(rec.path)
    s.device, s.lighting.asynchronous, s.lighting.solve_process = device, asynchronous, process
    pipe = Pipeline(s, rec.intrinsics)
    out = []
    for f in iter_frames(rec, frames):
        out.append(pipe.process(f))
        if wait:
            pipe.wait_for_estimate()
    pipe.close()
    return out


def main() -> None:
    rec = open_recording(sys.argv[1])
    frames = list(range(int(sys.argv[2]) if len(sys.argv) > 2 else 8))
    device = sys.argv[3] if len(sys.argv) > 3 else "cuda"
    inline = run(rec, frames, device, False, False)
    waited = run(rec, frames, device, True, True)
    threaded = run(rec, frames, device, True, True, process=False)
    free = run(rec, frames, device, True, False)
    diff = [float(np.abs(w.lighting.sh - i.lighting.sh).max()) for w, i in zip(waited[1:], inline)]
    diff_thread = [float(np.abs(w.lighting.sh - i.lighting.sh).max()) for w, i in zip(threaded[1:], inline)]
    est = [r.diagnostics.estimated_frame for r in free]
    print(json.dumps({"recording": str(rec.path), "frames": len(frames), "device": device,
                      "waited_estimated_frames": [r.diagnostics.estimated_frame for r in waited],
                      "waited_vs_inline_one_frame_later_max_abs_diff": max(diff),
                      "waited_in_the_worker_thread_vs_inline_max_abs_diff": max(diff_thread),
                      "free_estimated_frames": est,
                      "free_finite": bool(all(np.isfinite(r.lighting.sh).all() for r in free)),
                      "free_from_earlier_frames": bool(all(e <= r.index for e, r in zip(est, free)) and est == sorted(est))}))


if __name__ == "__main__":
    main()
