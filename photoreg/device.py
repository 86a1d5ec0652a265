"""Device selection, Warp start-up (one kernel cache folder, chosen once per process) and the host allocator."""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import re
import threading
import time
from pathlib import Path

_WARP_READY = False
_MALLOC_TUNED = False
# glibc mallopt parameters (malloc.h) and the values set: blocks up to 32 MB (glibc's ceiling for the threshold) come
# from the heap, and up to 256 MB of freed heap stays in the process
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_MALLOC_SETTINGS = ((_M_MMAP_THRESHOLD, 32 << 20), (_M_TRIM_THRESHOLD, 256 << 20), (_M_TOP_PAD, 16 << 20))


def keep_frame_memory() -> bool:
    """Let glibc keep freed frame-sized blocks for the next frame instead of handing them back to the kernel: by
    default a block above its mmap threshold (128 kB to start) goes back on free, so every frame's new 1-4 MB arrays
    (linear colour, box filter, depth) fault their pages in afresh. TUM 640x480 on the 2-core CPU, frames that hold
    the lighting: preprocess 1.7-2.6 -> 0.9-1.0 ms, lighting samples 3.8 -> 3.0 ms. Once per process; False where
    the C library is not glibc (nothing changed)."""
    global _MALLOC_TUNED
    if not _MALLOC_TUNED:
        try:
            mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
        except (OSError, AttributeError):
            return False
        _MALLOC_TUNED = all(mallopt(param, value) == 1 for param, value in _MALLOC_SETTINGS)
    return _MALLOC_TUNED


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
        raise ValueError(f"device (--device, a session's device) must be auto, cpu or cuda, got {device!r}")
    if device == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if device.startswith("cuda"):
        if not wp.is_cuda_available():
            raise RuntimeError("device cuda asked for (--device, a session's device), but Warp finds no CUDA "
                               "device/driver on this machine")
        return "cuda:0" if device == "cuda" else device
    return "cpu"


def open3d_device(warp_device: str):
    """The Open3D core device matching a Warp device string (CPU when Open3D lacks CUDA)."""
    import open3d as o3d

    if warp_device.startswith("cuda") and o3d.core.cuda.is_available():
        return o3d.core.Device("CUDA:" + warp_device.split(":")[1])
    return o3d.core.Device("CPU:0")


def open3d_message(error: BaseException) -> str:
    """An Open3D error's own words: its terminal colour codes and the '[Open3D Error] (C++ signature) file:line:'
    before them dropped (other errors' text as it is)."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(error)).strip()
    if text.startswith("[Open3D Error]"):
        text = text.rsplit(": ", 1)[-1]
    return text


PARENT_POLL_S = 1.0   # how often a child process looks whether its parent still lives


def exit_with_parent() -> None:
    """In a child process (a pool's initializer): end it once its parent is gone. A parent killed with SIGKILL tells
    its children nothing, and a pool's worker waits on the parent's pipe for ever (a server's connection processes
    held 1.2 GB, orphaned, until killed by hand)."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="photoreg-parent-watch").start()

