"""Output files written beside the frames: a run's per-frame files (composites, light maps, pictures, video
frames) are encoded and written in threads while the next frames are processed. PNG encoding, OpenEXR's
compression and numpy's colour transfer release the interpreter lock, and they took longer than the frame
itself where the frame is fast (640x480 with an object: a composite's PNG and two EXRs 120-140 ms on the
2-core CPU, against 25-40 ms for the whole frame on an H100)."""
from __future__ import annotations

import sys
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable


class OutputWriter:
    """Runs write jobs in `threads` threads, in the order given when `threads` is 1 (a video's frames), at most
    `queued` at once: submit waits while that many are unfinished, so the frames in memory stay bounded. The first
    failed job's error is raised by the next submit and by close; the jobs queued before it still run, so what was
    computed is written. `waited_s`: how long submit waited for a free slot (the writes setting the pace). A context
    manager: leaving it waits for every job (and raises their first error unless an error is already on its way out,
    which it then only reports on stderr)."""

    def __init__(self, threads: int = 1, queued: int | None = None, name: str = "photoreg-writer"):
        if threads < 1:
            raise ValueError(f"OutputWriter: threads must be >= 1, got {threads}")
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix=name)
        self._slots = threading.BoundedSemaphore(queued or 2 * threads)
        self._error: BaseException | None = None
        self._closed = False
        self.waited_s = 0.0

    def submit(self, job: Callable[..., object], *args) -> None:
        """Queue job(*args); waits while `queued` jobs are unfinished."""
        if self._closed:
            raise RuntimeError("OutputWriter: submit after close")
        self._raise()
        t = time.perf_counter()
        self._slots.acquire()
        self.waited_s += time.perf_counter() - t
        try:
            future = self._pool.submit(job, *args)
        except BaseException:
            self._slots.release()
            raise
        future.add_done_callback(self._done)

    def _done(self, future: Future) -> None:
        self._slots.release()
        if self._error is None and not future.cancelled() and future.exception() is not None:
            self._error = future.exception()

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error

    def close(self) -> None:
        """Wait for every queued job; raise the first failed one's error. Idempotent."""
        if not self._closed:
            self._closed = True
            self._pool.shutdown(wait=True)
        self._raise()

    def __enter__(self) -> "OutputWriter":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.close()
            return
        try:
            self.close()
        except BaseException as e:   # the error on its way out says more; this one is reported, not raised
            if e is not value:
                print(f"photoreg: an output write failed too: {e}", file=sys.stderr)
