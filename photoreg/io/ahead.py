"""Work done on threads ahead of the caller, handed over in order: the frames a run or a stream reads
(recording.ReadAhead) and the messages a stream encodes (service.client.encoded_ahead) while the frames before them
are processed or sent."""
from __future__ import annotations

import queue
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Generic, Iterable, Iterator, TypeVar

T = TypeVar("T")
R = TypeVar("R")


class Ahead(Generic[T, R]):
    """fn(item) for each of `items` on `threads` threads, the results handed to the caller in the items' order, each as
    soon as it and those before it are done. A thread of its own draws the items and starts their work from the
    start, keeping at most `depth` + 1 items in work or done beyond the one the caller holds (items drawn only when
    the caller asked for its next result left the threads idle while the caller worked: a run of 100 frames read on
    four threads that way waited 0.53-0.57 s for them on an H100's host, 0.02 s drawn here). An error of fn, or of
    drawing an item, is raised where its result would have come. `waited_s`: how long the caller waited for results.
    close() (and the end of the loop) stops the drawing, cancels the work not started and waits for the rest."""

    def __init__(self, fn: Callable[[T], R], items: Iterable[T], threads: int = 1, depth: int = 2,
                 name: str = "photoreg-ahead"):
        if threads < 1 or depth < 1:
            raise ValueError(f"Ahead: threads and depth must be >= 1, got {threads} and {depth}")
        self._fn = fn
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix=name)
        self._slots = threading.Semaphore(depth + 1)
        self._results: queue.Queue[Future | None] = queue.Queue()   # in the items' order; None: no more items
        self._stop = threading.Event()
        self.waited_s = 0.0
        self._drawer = threading.Thread(target=self._draw, args=(items,), name=f"{name}-draw", daemon=True)
        self._drawer.start()

    def _draw(self, items: Iterable[T]) -> None:
        try:
            items = iter(items)
            while True:
                while not self._slots.acquire(timeout=0.1):   # a slot first: no item drawn beyond them
                    if self._stop.is_set():
                        return
                if self._stop.is_set():
                    return
                try:
                    item = next(items)
                except StopIteration:
                    break
                self._results.put(self._pool.submit(self._fn, item))
        except BaseException as e:   # raised in the caller, after the results before it
            failed: Future = Future()
            failed.set_exception(e)
            self._results.put(failed)
        self._results.put(None)

    def __iter__(self) -> Iterator[R]:
        try:
            while True:
                t = time.perf_counter()
                future = self._results.get()
                try:
                    if future is None:
                        return
                    result = future.result()
                finally:
                    self.waited_s += time.perf_counter() - t
                self._slots.release()
                yield result
        finally:
            self.close()

    def close(self) -> None:
        """Stop drawing items (at most the one being drawn is waited for), cancel the work not started and wait for the
        rest; idempotent."""
        self._stop.set()
        self._drawer.join()
        while True:
            try:
                future = self._results.get_nowait()
            except queue.Empty:
                break
            if future is not None:
                future.cancel()
        self._pool.shutdown(wait=True)
