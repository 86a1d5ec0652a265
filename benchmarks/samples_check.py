"""The lighting samples on a GPU (kernels.samples) against the host path (preprocess.strided_box,
lighting.samples.agreement) on the same ray-cast maps of a recording, and the time of each.

usage: python benchmarks/samples_check.py RECORDING [DEVICE]   (DEVICE default cuda; prints one JSON object)
After frames 0-5 are fused, at strides 1, 2, 4 and 8: whether the CANDIDATE flags equal the host's usable boxes
with a surface, how many AGREES flags differ from the host's agreement, the largest radiance difference, and the
pipeline's samples (Pipeline._samples, all of them and a held frame's 2000) both ways: the same points, the
largest radiance difference and the median ms of 30 calls, each checking the frame's pixels afresh.
"""
import json
import sys
import time

import numpy as np

from photoreg.config import Session, validate
from photoreg.io.recording import iter_frames, open_recording
from photoreg.kernels.raycast import raycast_surface
from photoreg.kernels.samples import AGREES, CANDIDATE, sample_maps
from photoreg.lighting.samples import agreement
from photoreg.pipeline import GAIN_SAMPLES, Pipeline
from photoreg.preprocess import strided_box


def median_ms(fn, n: int = 30) -> float:
    fn()
    times = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return round(float(np.median(times)), 3)


def main(path: str, device: str = "cuda") -> dict:
    s = Session()
    s.recording.path, s.device = path, device
    validate(s)
    rec = open_recording(path)
    pipe = Pipeline(s, rec.intrinsics)
    lc, rc = s.lighting, s.reconstruction
    gap = lc.max_depth_gap_voxels * rc.voxel_size
    for frame in iter_frames(rec, range(6)):
        prep, pose, _ = pipe.observe(frame, {})
    grid = pipe.volume.dense_grid()

    def fresh(*args):
        """Pipeline._samples with the frame's pixel checks made again (not the memo of the call before)."""
        pipe._checked = None
        return pipe._samples(*args)

    out = {"device": pipe.device, "recording": path}
    for st in (1, 2, 4, 8):
        maps = raycast_surface(grid, rec.intrinsics, pose, rc.depth_min, rc.depth_max, stride=st)
        found = sample_maps(prep.colour, prep.usable, prep.depth, rec.intrinsics, pose, maps, lc.max_normal_angle,
                            gap, pipe.device)
        radiance, usable, _ = strided_box(prep, st)
        r, c = np.nonzero(usable & maps.valid)
        agrees = agreement(prep.depth, rec.intrinsics, pose, r * st, c * st, maps.depth[r, c], maps.normal[r, c],
                           max(2, st), lc.max_normal_angle, gap)
        row = {"candidates_equal": bool(np.array_equal((found.flags & CANDIDATE) > 0, usable & maps.valid)),
               "candidates": int(r.size), "agree": int(agrees.sum()),
               "agree_mismatches": int((((found.flags[r, c] & AGREES) > 0) != agrees).sum()),
               "radiance_max_diff": float(np.abs(found.radiance[r, c] - radiance[r, c]).max())}
        for cap in (None, GAIN_SAMPLES):
            both = {}
            for kernel in (False, True):
                pipe.sample_kernel = kernel
                both[kernel] = (pipe._samples(prep, maps, pose, cap), median_ms(lambda: fresh(prep, maps, pose, cap)))
            (host, host_ms), (kern, kern_ms) = both[False], both[True]
            row[f"samples_{cap or 'all'}"] = {
                "n": len(host[0]), "same_points": bool(np.array_equal(host[1], kern[1])),
                "radiance_max_diff": float(np.abs(host[0] - kern[0]).max()), "host_ms": host_ms, "kernel_ms": kern_ms}
        out[f"stride_{st}"] = row
    pipe.close()
    return out


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    print(json.dumps(main(*sys.argv[1:3])))
