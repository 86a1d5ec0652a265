"""The ray-traced G-buffer (render.gbuffer = raycast) against pyrender's draw, on the frames of a session.

usage: python benchmarks/gbuffer_check.py SESSION.toml [FIRST:LAST] [DEVICE] [NPZ]
       (prints one JSON object; NPZ: the frame with the most differing pixels saved there for a closer look)
The session runs with the pyrender G-buffer on DEVICE (default cuda); at every frame the stage's own inputs (pose,
real depth, tolerance, window) also go to a raycast renderer on DEVICE and one on the CPU. Per frame: the pixels
whose coverage differs between raycast on DEVICE and the draw, those covered by one and not at all by the other
(`flipped`), and those differing between raycast on DEVICE and on the CPU (the kernel's own CUDA/CPU agreement).
"""
import json
import sys

import numpy as np

from photoreg.config import load_session, parse_frames
from photoreg.io.recording import iter_frames, open_configured
from photoreg.pipeline import Pipeline
from photoreg.render.gbuffer import GBufferRenderer


def differing(a, b) -> dict:
    """Where two G-buffers of one view differ: coverage (any, flipped, largest) and the depth where both cover."""
    d = np.abs(a.coverage - b.coverage)
    both = (a.coverage > 0) & (b.coverage > 0)
    dz = np.abs(a.depth - b.depth)[both]
    return {"pixels": int((d > 0).sum()), "flipped": int(((a.coverage > 0) != (b.coverage > 0)).sum()),
            "coverage_max": float(d.max()), "covered": int((a.coverage > 0).sum()),
            "depth_max_m": float(dz.max()) if dz.size else 0.0}


def main() -> None:
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    s = load_session(sys.argv[1])
    frames = sys.argv[2] if len(sys.argv) > 2 else "0:8"
    s.device = sys.argv[3] if len(sys.argv) > 3 else "cuda"
    s.render.gbuffer = "pyrender"
    rec = open_configured(s.recording)
    pipe = Pipeline(s, rec.intrinsics)
    stage = pipe.render
    drawn, draw = stage.gbuffer, stage.gbuffer.render
    traced = GBufferRenderer(stage.scene, rec.intrinsics, drawn.s, drawn.faces.device, "raycast")
    traced_cpu = GBufferRenderer(stage.scene, rec.intrinsics, drawn.s, "cpu", "raycast")
    rows, worst = [], (-1, None)

    def render(pose, real, tolerance, window):
        a = draw(pose, real, tolerance, window)
        b, c = traced.render(pose, real, tolerance, window), traced_cpu.render(pose, real, tolerance, window)
        row = {"draw_vs_raycast": differing(a, b), "raycast_device_vs_cpu": differing(b, c)}
        rows.append(row)
        nonlocal worst
        if row["draw_vs_raycast"]["pixels"] > worst[0]:
            worst = (row["draw_vs_raycast"]["pixels"], dict(pose=pose, real=real, tolerance=tolerance, window=window,
                                                            **{f"{k}_{n}": getattr(g, n) for k, g in
                                                               (("draw", a), ("raycast", b), ("cpu", c))
                                                               for n in ("coverage", "depth")}))
        return a

    stage.gbuffer.render = render
    for f in iter_frames(rec, parse_frames(frames, len(rec))):
        pipe.process(f)
    pipe.close()
    if len(sys.argv) > 4 and worst[1] is not None:
        np.savez_compressed(sys.argv[4], **worst[1])
    total = {k: {m: sum(r[k][m] for r in rows) for m in ("pixels", "flipped", "covered")} for k in rows[0]}
    print(json.dumps({"session": sys.argv[1], "frames": frames, "device": drawn.faces.device, "total": total,
                      "per_frame": rows}))


if __name__ == "__main__":
    main()
