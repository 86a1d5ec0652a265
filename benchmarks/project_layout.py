"""CPU time of the transfer's projection (kernels.transfer._project) in its two thread layouts on the same inputs:
a point's coefficients in one thread (the CPU's, _project_group) against a thread per coefficient (the GPU's), and
that both give the same bits. The inputs: the samples and occlusion flags of a recording's frame after `--frames`
frames fused (the session's settings, 5 bands by default here).

usage: python3 benchmarks/project_layout.py SESSION_OR_RECORDING [--frames N] [--bands B] [--repeat R]"""
from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("input")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--bands", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()

    import photoreg.kernels.transfer as transfer
    from photoreg.cli import build_parser
    from photoreg.io.recording import iter_frames, open_configured
    from photoreg.kernels.launch import launch_rows
    from photoreg.pipeline import Pipeline
    from photoreg.runner import session_from_args

    s = session_from_args(build_parser().parse_args(["run", args.input, "--device", "cpu", "--bands",
                                                     str(args.bands)]))
    rec = open_configured(s.recording)
    pipe = Pipeline(s, rec.intrinsics)
    calls = []
    real = transfer.radiance_transfer

    def kept(*a, **k):   # the pipeline's own transfer call of the last frame, its inputs and flags
        r = real(*a, **k)
        calls.append((a, k, r))
        return r

    transfer.radiance_transfer = kept
    import photoreg.pipeline as pipeline_module
    pipeline_module.radiance_transfer = kept
    for frame in iter_frames(rec, range(args.frames)):
        pipe.process(frame)
    pipe.close()
    a, k, res = calls[-1]
    wp = transfer.wp
    n = wp.array(np.asarray(a[2], np.float32), dtype=wp.vec3)
    w = wp.array(np.asarray(a[3], np.float32), dtype=wp.vec3)
    y = wp.array(np.asarray(a[4], np.float32), dtype=wp.float32)
    N, K = n.shape[0], y.shape[1]
    times, outs = {}, {}
    for _ in range(args.repeat):
        for name, group in (("point per thread (CPU)", K), ("coefficient per thread (GPU)", 1)):
            tr, vis = wp.zeros((N, K), dtype=wp.float32), wp.zeros(N, dtype=wp.float32)
            t0 = time.process_time()
            launch_rows(transfer._project, (N, -(-K // group)), device="cpu", threads=1,
                        inputs=[n, w, y, res.occlusion_wp, transfer.REAL, 4.0 / w.shape[0], group],
                        outputs=[tr, vis])
            times.setdefault(name, []).append((time.process_time() - t0) * 1000)
            outs[name] = (tr.numpy(), vis.numpy())
    same = all(np.array_equal(x, z) for x, z in zip(*outs.values()))
    print(f"{N} samples, {K} coefficients, {w.shape[0]} rays; CPU ms (median of {args.repeat}, one thread): "
          + ", ".join(f"{name} {np.median(v):.1f}" for name, v in times.items()) + f"; bit for bit the same: {same}")


if __name__ == "__main__":
    main()
