"""Device selection and Warp start-up (one kernel cache folder, chosen once per process)."""
from __future__ import annotations

import os
from pathlib import Path

_WARP_READY = False


def warp_cache_dir() -> Path:
    """Kernel cache: $PHOTOREG_WARP_CACHE, else ~/.cache/photoreg/warp (compiled once, reused)."""
    return Path(os.environ.get("PHOTOREG_WARP_CACHE", Path.home() / ".cache" / "photoreg" / "warp"))


def init_warp():
    """Initialise Warp once with the project's kernel cache; returns the warp module."""
    global _WARP_READY
    import warp as wp

    if not _WARP_READY:
        cache = warp_cache_dir()
        cache.mkdir(parents=True, exist_ok=True)
        wp.config.kernel_cache_dir = str(cache)
        wp.config.log_level = wp.LOG_WARNING  # no start-up banner or per-module load lines on stdout
        wp.init()
        _WARP_READY = True
    return wp


def resolve_device(device: str = "auto") -> str:
    """'auto' | 'cpu' | 'cuda' -> Warp device string ('cpu' or 'cuda:0'); clear error if CUDA is absent."""
    wp = init_warp()
    if device not in ("auto", "cpu", "cuda") and not device.startswith("cuda:"):
        raise ValueError(f"--device must be auto, cpu or cuda, got {device!r}")
    if device == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if device.startswith("cuda"):
        if not wp.is_cuda_available():
            raise RuntimeError("--device cuda asked for, but Warp finds no CUDA device/driver on this machine")
        return "cuda:0" if device == "cuda" else device
    return "cpu"


def open3d_device(warp_device: str):
    """The Open3D core device matching a Warp device string (CPU when Open3D lacks CUDA)."""
    import open3d as o3d

    if warp_device.startswith("cuda") and o3d.core.cuda.is_available():
        return o3d.core.Device("CUDA:" + warp_device.split(":")[1])
    return o3d.core.Device("CPU:0")
