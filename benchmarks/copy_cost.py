"""What a copy costs on this machine's host: frame-sized numpy work (a 640x480x3 float32 copy, isfinite, zeros, ones,
render.composite.composite of a 325 x 297 region) with the minor page faults per call, and, on a GPU, the fixed host
time of Warp uploads and read-backs, one by one against packed (photoreg.kernels.packing).

usage: python benchmarks/copy_cost.py [DEVICE]   (DEVICE default cuda:0; "cpu" times the host part alone; one JSON object)
"""
import json
import resource
import sys
import time

import numpy as np

from photoreg.kernels.packing import Packed, upload, wp
from photoreg.render.composite import Layers, composite


def per_call(f, n: int = 100) -> float:
    """Mean ms a call of f over n calls (after one), the device's work included."""
    f()
    wp.synchronize()
    t0 = time.perf_counter()
    for _ in range(n):
        f()
    wp.synchronize()
    return round((time.perf_counter() - t0) / n * 1e3, 4)


def faults(f, n: int = 100) -> float:
    """Minor page faults a call of f (fresh pages that each large allocation may touch)."""
    f()
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        f()
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0) / n


def main() -> None:
    dev = sys.argv[1] if len(sys.argv) > 1 else "cuda:0"
    rng = np.random.default_rng(0)
    cam = rng.random((480, 640, 3)).astype(np.float32)
    layers = Layers(rng.random((480, 640, 3)).astype(np.float32), rng.random((480, 640)).astype(np.float32),
                    rng.random((480, 640, 3)).astype(np.float32), [], (100, 100, 425, 397))
    host = {"copy": lambda: np.array(cam), "isfinite": lambda: np.isfinite(cam).all(),
            "zeros_filled": lambda: np.zeros(cam.shape, np.float32).fill(1), "ones": lambda: np.ones(cam.shape, np.float32),
            "composite": lambda: composite(cam, layers)}
    out = {"device": dev, "host_ms": {k: per_call(f) for k, f in host.items()},
           "host_minor_faults": {k: faults(f) for k, f in host.items()}}
    if not wp.get_device(dev).is_cpu:
        small, frame = np.ones((100, 3), np.float32), np.ones((480, 640), np.float32)
        a_small, a_frame = wp.array(small, dtype=wp.vec3, device=dev), wp.array(frame, dtype=wp.float32, device=dev)
        maps = [((120, 160), wp.float32), ((120, 160), wp.vec3), ((120, 160), wp.vec3)]   # stride 4 at 640x480
        one_by_one, packed = [wp.empty(s, dtype=d, device=dev) for s, d in maps], Packed(maps, dev)
        device = {"upload_small": lambda: wp.array(small, dtype=wp.vec3, device=dev),
                  "upload_frame": lambda: wp.array(frame, dtype=wp.float32, device=dev),
                  "upload_4_small_one_by_one": lambda: [wp.array(small, dtype=wp.vec3, device=dev) for _ in range(4)],
                  "upload_4_small_packed": lambda: upload([small] * 4, [wp.vec3] * 4, dev),
                  "read_small": lambda: a_small.numpy(), "read_frame": lambda: a_frame.numpy(),
                  "read_3_maps_one_by_one": lambda: [a.numpy() for a in one_by_one],
                  "read_3_maps_packed": lambda: packed.numpy(),
                  "alloc_3_maps_one_by_one": lambda: [wp.empty(s, dtype=d, device=dev) for s, d in maps],
                  "alloc_3_maps_packed": lambda: Packed(maps, dev)}
        out["device_name"] = wp.get_device(dev).name
        out["warp_ms"] = {k: per_call(f) for k, f in device.items()}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
