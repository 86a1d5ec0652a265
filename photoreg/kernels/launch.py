"""Row-split kernel launches: Warp runs a CPU launch on one thread, so on the CPU a large launch is cut
into contiguous blocks of its first dimension and the blocks are launched from a thread pool (the
ctypes call into the compiled kernel releases the GIL, so the blocks run in parallel).

A kernel launched this way takes `row0: int` as its last input and adds it to its first thread index;
every thread writes only its own rows, so the split launch gives exactly the single launch's output.
On CUDA it is one launch with row0 = 0. Threads: set_cpu_threads(n), else $PHOTOREG_CPU_THREADS,
else os.cpu_count().
"""
from __future__ import annotations

import itertools
import os
from concurrent.futures import ThreadPoolExecutor

from photoreg.device import init_warp

wp = init_warp()

BLOCKS_PER_THREAD = 4  # more blocks than threads: rows differ in cost, the pool balances them

_threads: int | None = None
_pools: dict[int, ThreadPoolExecutor] = {}


def set_cpu_threads(n: int | None) -> None:
    """Threads for CPU launches from now on (None: back to $PHOTOREG_CPU_THREADS or os.cpu_count())."""
    global _threads
    if n is not None and n < 1:
        raise ValueError(f"--threads must be >= 1, got {n}")
    _threads = n


def cpu_threads() -> int:
    """Threads a CPU launch uses when the caller names none."""
    if _threads is not None:
        return _threads
    env = os.environ.get("PHOTOREG_CPU_THREADS")
    if env:
        if not env.isdigit() or int(env) < 1:
            raise ValueError(f"PHOTOREG_CPU_THREADS must be a positive integer, got {env!r}")
        return int(env)
    return os.cpu_count() or 1


def _pool(threads: int) -> ThreadPoolExecutor:
    if threads not in _pools:
        _pools[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="photoreg-launch")
    return _pools[threads]


def launch_rows(kernel, dim: tuple[int, ...], inputs: list, outputs: list, device: str,
                threads: int | None = None) -> None:
    """wp.launch(kernel, dim, inputs=inputs + [row0], outputs=outputs), on the CPU split over `threads`
    threads (None: cpu_threads()) in contiguous blocks of dim[0]; returns when every block is done."""
    rows = int(dim[0])
    if rows == 0 or any(int(d) == 0 for d in dim[1:]):
        return
    n_blocks = 1
    if wp.get_device(device).is_cpu:   # (os.cpu_count took 20 us a launch on the H100's host, for nothing on CUDA)
        threads = cpu_threads() if threads is None else threads
        if threads < 1:
            raise ValueError(f"launch_rows: threads must be >= 1, got {threads}")
        n_blocks = min(rows, threads * BLOCKS_PER_THREAD) if threads > 1 else 1
    if n_blocks == 1:
        wp.launch(kernel, dim=tuple(dim), inputs=[*inputs, 0], outputs=outputs, device=device)
        return
    wp.load_module(kernel.module, device=device)  # compile/load once here, not concurrently in the workers
    edges = [rows * b // n_blocks for b in range(n_blocks + 1)]

    blocks = itertools.count()  # next() is atomic under the GIL: each block is taken once

    def work() -> None:
        """Launch blocks until none is left (the blocks balance the rows' costs, not one task per block: a pool
        task costs about as much as a launch, 0.1 ms, while small launches take about that)."""
        while (b := next(blocks)) < n_blocks:
            wp.launch(kernel, dim=(edges[b + 1] - edges[b], *dim[1:]), inputs=[*inputs, edges[b]],
                      outputs=outputs, device=device)

    helpers = [_pool(threads).submit(work) for _ in range(threads - 1)]
    try:
        work()  # the calling thread takes blocks too
    finally:
        for f in helpers:
            f.result()  # waits for every block; re-raises a block's error
