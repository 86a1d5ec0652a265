"""Where a connection's pipeline runs (ServerConfig.processes): a thread of its own, or a process of its own.

In one process every connection's pipeline shares the interpreter lock, and much of a frame is Python and small
numpy calls on the host (on a GPU most of it), so connections take turns. With a process per connection they run
side by side, as `photoreg batch`'s workers do (benchmarks/gpu.md, "One worker per host core"), each client with
its own memory (and CUDA context). A process's start (importing photoreg, its device, a first pipeline: 1.9 s on the
2-core CPU, more with CUDA) is paid ahead of a hello: the server keeps one spare process warmed (warm()) for the
next connection. Either way a connection's calls run one at a time, in order, and return futures.
"""
from __future__ import annotations

import multiprocessing as mp
import signal
import threading
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..config import Session
from ..device import exit_with_parent
from ..io.images import linear_to_srgb
from ..pipeline import Pipeline
from ..runner import result_record
from ..types import Frame, FrameResult, Intrinsics

WARM_INTRINSICS = Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, 1000.0)
# The connection's pipeline, on the one thread that runs its calls: the connection's own thread, or the main thread
# of its own process; thread-local, so the two modes share these functions.
_local = threading.local()


def _child_start() -> None:
    """A connection's process ignores SIGINT: Ctrl-C in a terminal reaches the whole process group, and the
    server's own handler finishes the frames in work and closes the pipelines (a child stopped mid-frame
    would answer nothing). It ends when the server is gone (exit_with_parent)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    exit_with_parent()


def _warm_here(device: str) -> None:
    """A throwaway pipeline on `device`: the first one in a process loads the kernels (about 1 s on the CPU), a
    hello's then takes about 0.1 s."""
    session = Session(device=device)
    session.reconstruction.block_count = 16
    Pipeline(session, WARM_INTRINSICS).close()


def _open_here(session: Session, intrinsics: Intrinsics) -> None:
    _local.pipeline = Pipeline(session, intrinsics)


@dataclass
class CompositePatch:
    """A frame's composite as its pipeline hands it to the server: the linear pixels of a box; outside the box the
    composite is the frame's own colour. Only the box crosses from a connection's process (TUM with the bunny: a
    third of the frame's 3.7 MB) and only the box is converted to sRGB."""

    box: tuple[int, int, int, int]   # x0, y0, x1, y1 (exclusive)
    linear: np.ndarray               # (y1 - y0, x1 - x0, 3) float32

    def over(self, color: np.ndarray) -> np.ndarray:
        """The composite in 8-bit sRGB: the frame's colour (H, W, 3 uint8) with the box's pixels converted."""
        x0, y0, x1, y1 = self.box
        out = color.copy()
        out[y0:y1, x0:x1] = linear_to_srgb(self.linear)
        return out


def _patch(result: FrameResult) -> CompositePatch | None:
    """The frame's composite as a CompositePatch: the box outside which it is the frame's own colour
    (FrameResult.composite_region), or all of it where the pipeline gives none."""
    if result.composite is None:
        return None
    H, W = result.composite.shape[:2]
    x0, y0, x1, y1 = result.composite_region if result.composite_region is not None else (0, 0, W, H)
    return CompositePatch((x0, y0, x1, y1), result.composite[y0:y1, x0:x1])


def _reply_here(frame: Frame) -> tuple[dict, int, CompositePatch | None]:
    """(lighting record, frame index, the composite or None) of one frame: the server converts and encodes the
    composite for the client while the pipeline runs the next frame."""
    result = _local.pipeline.process(frame)
    return result_record(result), result.index, _patch(result)


def _close_here() -> None:
    pipeline = getattr(_local, "pipeline", None)
    if pipeline is not None:
        pipeline.close()


class PipelineHost:
    """One connection's pipeline on a thread of its own, or in a spawned child process (`processes`)."""

    def __init__(self, processes: bool):
        self.processes = processes
        self.executor: Executor = (ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"), initializer=_child_start)
                                   if processes else ThreadPoolExecutor(1, thread_name_prefix="photoreg-conn"))
        self.ready = False

    def warm(self, device: str) -> Future:
        """Start the child process now and its device (processes mode): a hello then only builds the pipeline."""
        return self.executor.submit(_warm_here, device)

    def open(self, session: Session, intrinsics: Intrinsics) -> Future:
        """Build the pipeline (a future of None); the connection is ready when it is done."""
        try:
            return self.executor.submit(_open_here, session, intrinsics)
        except RuntimeError as e:   # multiprocessing: the main module is still being imported
            if not self.processes:
                raise
            raise RuntimeError("a connection's process could not start: a spawned child imports the main script "
                               "again, so a script that starts the server at import needs `if __name__ == "
                               "\"__main__\":` round that code (or ServerConfig(processes=False))") from e

    def process(self, frame: Frame) -> Future:
        """A future of (lighting record, frame index, the composite as a CompositePatch or None); calls run in order,
        one at a time, so a frame handed in while another runs is taken up as soon as that one is done."""
        return self.executor.submit(_reply_here, frame)

    def close(self) -> None:
        """After the calls in work (a hello's included), close the pipeline if one was built (its lighting worker
        and solve process) and end the thread or the child process (one that died is only reaped)."""
        try:
            self.executor.submit(_close_here).result()
        except Exception:  # noqa: BLE001 - the child is gone (BrokenProcessPool): nothing left to close
            pass
        self.executor.shutdown(wait=True)
