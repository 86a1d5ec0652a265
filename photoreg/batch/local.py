"""Local executor of `photoreg batch`: a spawn-context process pool, one pipeline per process.

Sessions that may use CUDA get the CUDA devices Warp sees round-robin ("cuda:K"); with none they run on
the CPU. Worker processes send per-frame progress through a queue handed to them at start-up.

A pipeline on a GPU is bound by its host work (the robust solves, the light search, the render stage), so
several workers share each GPU by default (default_workers: one per host core), each with one BLAS thread
(photoreg/__init__.py). On one H100 with 16 host cores (benchmarks/gpu.md, "Many sessions on one GPU" and "One
worker per host core"), 8 sessions of TUM: 8 workers ran 32.3 frames/s in all against 12.0 for one, 19.2 against
5.1 with an object inserted (with a threaded BLAS in every worker, 16 threads each, 13.3 and 9.6); 32 sessions of
100 frames: 16 workers 100.8 and 45.9 frames/s, 8 workers 64.3 and 27.8 (16 sessions), 32 workers 88.6 and 37.5.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import queue
import signal
import sys
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

from ..device import exit_with_parent
from .runner import BatchInterrupted, BatchProgress, SessionTask, failed_result, run_one

_progress_queue = None  # set in each worker process by _init_worker

GPU_MEMORY_PER_WORKER = 2 * 1024 ** 3  # bytes of GPU memory per worker (TUM at 1 cm: about 1 GB each, context included)
HOST_MEMORY_PER_WORKER = 2 * 1024 ** 3  # bytes of host memory per worker (a CPU session of TUM peaked at 0.7 GB)


def _init_worker(q, cpu_threads: int) -> None:
    """Worker start-up: the progress queue, and its share of the cores for split CPU kernel launches
    (photoreg.kernels.launch) unless PHOTOREG_CPU_THREADS is set: N workers each using every core would
    oversubscribe them N-fold. Ctrl-C is the batch's to handle (run_local stops the workers): a terminal's reaches
    every process of its group, and workers it interrupted mid-queue left the pool's join waiting for ever."""
    global _progress_queue
    _progress_queue = q
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ.setdefault("PHOTOREG_CPU_THREADS", str(cpu_threads))
    exit_with_parent()   # a batch killed with SIGKILL leaves no worker waiting for ever


def cpu_share(workers: int) -> int:
    """CPU threads per worker: the cores split evenly, at least one."""
    return max(1, (os.cpu_count() or 1) // max(workers, 1))


def workers_per_gpu(cores: int, memory: int | None) -> int:
    """Sessions one GPU takes at once: one per host core of its share (`cores`), at most one per
    GPU_MEMORY_PER_WORKER of its `memory` (bytes; None: not known), at least one."""
    n = cores
    if memory is not None:
        n = min(n, memory // GPU_MEMORY_PER_WORKER)
    return max(n, 1)


def default_workers(cores: int, gpu_memory: list[int], host_memory: int | None = None) -> int:
    """Workers when --workers is not given: per GPU (`gpu_memory`: each one's bytes) workers_per_gpu of its share
    of the `cores`; without GPUs one per core; at most one per HOST_MEMORY_PER_WORKER of the `host_memory`
    available (bytes; None: not known), at least one."""
    if not gpu_memory:
        n = max(cores, 1)
    else:
        share = max(cores // len(gpu_memory), 1)
        n = sum(workers_per_gpu(share, m) for m in gpu_memory)
    if host_memory is not None:
        n = min(n, max(host_memory // HOST_MEMORY_PER_WORKER, 1))
    return n


def available_memory() -> int | None:
    """Bytes of host memory available for new processes (MemAvailable of /proc/meminfo; None where there is none)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def gpu_memory() -> list[int]:
    """Bytes of memory of each CUDA device Warp sees (none: an empty list)."""
    from ..device import init_warp

    wp = init_warp()
    return [int(wp.get_device(f"cuda:{i}").total_memory) for i in range(wp.get_cuda_device_count())]


def _run(task: SessionTask) -> dict:
    _progress_queue.put((task.index, None, None))   # started: a worker that dies now takes this session with it
    return run_one(task, _progress_queue)


def assign_devices(tasks: list[SessionTask]) -> list[int]:
    """Set each session's device to 'cuda:K' round-robin over Warp's CUDA devices unless it asks for the
    CPU ('auto' falls back to the CPU when there is none, 'cuda' is then an error); returns the memory (bytes)
    of each GPU used (none: an empty list)."""
    wanted = [t for t in tasks if t.session.device != "cpu"]
    memory = gpu_memory() if wanted else []
    n = len(memory)
    for k, t in enumerate(wanted):
        if n:
            t.session.device = f"cuda:{k % n}"
        elif t.session.device == "cuda":
            raise RuntimeError(f"{t.path}: device cuda asked for, but Warp finds no CUDA device on this machine")
        else:
            t.session.device = "cpu"
    return memory


def _drain(q, progress: BatchProgress, started: set[int]) -> None:
    """Relay the workers' progress; the sessions a worker started join `started`."""
    while True:
        try:
            index, done, total = q.get_nowait()
        except queue.Empty:
            return
        if done is None:
            started.add(index)
        else:
            progress.frame(index, done, total)


def run_local(tasks: list[SessionTask], progress: BatchProgress, workers: int | None = None) -> list[dict]:
    """Run the sessions in `workers` processes (default: default_workers); results in task order. A worker process
    that dies (killed, out of memory) breaks the pool and every session in it: they go on in a new pool, those that
    had started run once more (as the Ray executor retries a task) and fail where a worker dies under them again;
    those still queued are only rescheduled."""
    memory = assign_devices(tasks)
    workers = min(workers or default_workers(os.cpu_count() or 1, memory, available_memory()), len(tasks))
    print(f"batch: {len(tasks)} session(s) on {workers} worker process(es)"
          + (f" sharing {len(memory)} GPU(s)" if memory else " on the CPU"), file=sys.stderr, flush=True)
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    results: dict[int, dict] = {}

    def new_pool() -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                                   initargs=(q, cpu_share(workers)))

    pool = new_pool()
    pending, stopped, started = {}, False, set()

    def settle(f) -> tuple[SessionTask, int] | None:
        """Record the result of finished future f; (its session, the attempt to make next) instead where its pool
        broke: a session that had started has used an attempt, a queued one has not."""
        t, attempt = pending.pop(f)
        try:
            r = f.result()
        except BrokenProcessPool as e:   # a worker process died: every session of the pool lands here
            if t.index not in started:
                return t, attempt
            if attempt == 1:
                return t, 2
            r = failed_result(t, RuntimeError(f"its worker process died, twice ({e})"))
        except Exception as e:  # noqa: BLE001 - a failure the worker could not report as a result
            r = failed_result(t, e)
        r["attempts"] = attempt
        results[t.index] = r
        progress.finished(r)
        return None

    try:
        pending = {pool.submit(_run, t): (t, 1) for t in tasks}
        while pending:
            finished, _ = wait(pending, timeout=0.25, return_when=FIRST_COMPLETED)
            _drain(q, progress, started)
            again = [a for a in map(settle, finished) if a is not None]
            if again:   # the pool is broken: its other sessions end alike, at once
                again += [a for a in map(settle, wait(pending)[0]) if a is not None]
                again.sort(key=lambda a: a[0].index)
                print(f"batch: a worker process died; {', '.join(t.name for t, _ in again)} go on in new worker "
                      "processes", file=sys.stderr, flush=True)
                started.difference_update(t.index for t, _ in again)
                pool.shutdown(wait=True)
                pool = new_pool()
                pending = {pool.submit(_run, t): (t, attempt) for t, attempt in again}
    except KeyboardInterrupt:
        # the queued sessions cancelled, the running ones' workers stopped (their outputs are written whole or not
        # at all, without the completion marker: --resume runs them again); Python 3.14's terminate_workers()
        # does this, earlier versions have no public way
        stopped = True
        processes = list((getattr(pool, "_processes", None) or {}).values())   # shutdown() forgets them
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        for t, _ in pending.values():
            results[t.index] = failed_result(t, KeyboardInterrupt("interrupted (Ctrl-C) before it finished"))
        raise BatchInterrupted([results[t.index] for t in tasks]) from None
    finally:
        if not stopped:
            pool.shutdown(wait=True)
    return [results[t.index] for t in tasks]
