"""Ray executor of `photoreg batch` (optional extra `ray`): one remote task per session.

On a cluster with GPUs a session that may use CUDA asks for 1/k of one GPU (Ray then sets CUDA_VISIBLE_DEVICES,
so the session runs on "cuda"): k sessions share each GPU, as the local executor's workers do (a pipeline on a
GPU is bound by its host work; photoreg.batch.local). k is local.workers_per_gpu of the GPU node with the fewest
CPUs per GPU and of the memory of the GPU a probe task lands on (the cluster's GPUs taken as alike); with a Ray
instance started here and --workers given, --workers sessions at once in all. Other sessions ask for one CPU.
A task whose worker process dies is re-run by Ray (max_retries=1); a session that fails with an error is
submitted once more. Output folders and recordings must be on a filesystem every node sees. Progress comes back
through a Ray queue actor.
"""
from __future__ import annotations

import math
import os
import socket
import sys

from .local import gpu_memory, workers_per_gpu
from .runner import BatchInterrupted, BatchProgress, SessionTask, failed_result, run_one


def _import_ray():
    try:
        import ray
    except ImportError:
        raise RuntimeError("--executor ray needs Ray, which is not installed: "
                           "pip install 'photoreg[ray]' (or use --executor local)") from None
    return ray


PROBE_TIMEOUT_S = 5.0   # a --ray-address HOST:PORT must accept a TCP connection within this (ray.init retries minutes)


def check_reachable(address: str) -> None:
    """Refuse a --ray-address HOST:PORT (or ray://HOST:PORT) where nothing accepts a connection, at once: Ray itself
    retries for minutes, and not even SIGTERM stops it. 'auto' and other forms are left to Ray."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit():
        return
    try:
        socket.create_connection((host, int(port)), timeout=PROBE_TIMEOUT_S).close()
    except OSError as e:
        raise RuntimeError(f"--ray-address {address}: nothing answers there ({e}); is the Ray head running?") from None


def run_ray(tasks: list[SessionTask], progress: BatchProgress, workers: int | None = None,
            address: str | None = None) -> list[dict]:
    """Run the sessions as Ray tasks; results in task order. Uses the Ray instance already initialised
    in this process, else connects to `address`, else starts a local one with `workers` CPUs (sessions at once)."""
    ray = _import_ray()
    from ray.util.queue import Queue

    started = not ray.is_initialized()
    if started and address:
        check_reachable(address)
        try:
            ray.init(address=address)
        except (ConnectionError, ValueError) as e:
            raise RuntimeError(f"--ray-address {address}: cannot connect to a Ray cluster there ({e})") from None
    elif started:
        ray.init(num_cpus=workers or os.cpu_count(), include_dashboard=False)
    try:
        gpus = ray.cluster_resources().get("GPU", 0)
        for t in tasks:
            if t.session.device == "cuda" and not gpus:
                raise RuntimeError(f"{t.path}: device cuda asked for, but the Ray cluster has no GPUs")
            t.session.device = "cuda" if gpus and t.session.device != "cpu" else "cpu"
        share = None
        if any(t.session.device == "cuda" for t in tasks):
            share = sessions_per_gpu(ray, workers if started and not address else None)
        print(f"batch: {len(tasks)} session(s) as Ray tasks"
              + (f", {share} at once per GPU ({gpus:g} GPU(s) in the cluster)" if share else ", one CPU each"),
              file=sys.stderr, flush=True)
        q = Queue(actor_options={"num_cpus": 0})
        try:
            return _gather(ray, tasks, progress, q, share)
        finally:
            q.shutdown()
    finally:
        if started:
            ray.shutdown()


def _gpu_memory() -> int | None:
    """Bytes of memory of the GPU this task holds, as Warp sees it; None where Warp finds no CUDA device."""
    memory = gpu_memory()
    return memory[0] if memory else None


def sessions_per_gpu(ray, workers: int | None = None) -> int:
    """Sessions each GPU takes at once (module docstring): --workers spread over the cluster's GPUs when given,
    else local.workers_per_gpu of the alive GPU node with the fewest CPUs per GPU and of the memory that a probe
    task holding one GPU reads (none: the CPUs alone)."""
    nodes = [n["Resources"] for n in ray.nodes() if n.get("Alive") and n["Resources"].get("GPU", 0) >= 1]
    if not nodes:
        return 1
    if workers:
        return max(math.ceil(workers / sum(int(r["GPU"]) for r in nodes)), 1)
    cores = min(int(r.get("CPU", 0)) // int(r["GPU"]) for r in nodes)
    memory = ray.get(ray.remote(num_gpus=1, num_cpus=0)(_gpu_memory).remote())
    return workers_per_gpu(cores, memory)


def gpu_fraction(share: int) -> float:
    """The GPU a task asks for so that `share` tasks fit on one and no more (Ray counts in 1e-4 units)."""
    return math.floor(1e4 / share) / 1e4


def _gather(ray, tasks: list[SessionTask], progress: BatchProgress, q, share: int | None = None) -> list[dict]:
    """Submit every session (one on CUDA asks for 1/`share` of a GPU), relay progress from `q`, resubmit a failed
    session once; results in task order. Ctrl-C: BatchInterrupted with every session's result (the unfinished ones
    failed)."""
    remote = ray.remote(max_retries=1)(run_one)  # max_retries: Ray re-runs a task whose worker process died

    def submit(t: SessionTask):
        # a CPU task holds one Ray CPU: its split kernel launches (photoreg.kernels.launch) use one thread
        resources = {"num_gpus": gpu_fraction(share or 1)} if t.session.device == "cuda" else \
            {"num_cpus": 1, "runtime_env": {"env_vars": {"PHOTOREG_CPU_THREADS": "1"}}}
        return remote.options(**resources).remote(t, q)

    pending = {submit(t): (t, 1) for t in tasks}
    results: dict[int, dict] = {}
    try:
        _collect(ray, pending, results, progress, q, submit)
    except KeyboardInterrupt:   # Ctrl-C: the running tasks cancelled, the report written for what finished
        for ref in pending:
            ray.cancel(ref, force=True)
        raise BatchInterrupted([results.get(t.index) or failed_result(
            t, KeyboardInterrupt("interrupted (Ctrl-C) before it finished")) for t in tasks]) from None
    return [results[t.index] for t in tasks]


def _collect(ray, pending: dict, results: dict[int, dict], progress: BatchProgress, q, submit) -> None:
    """_gather's loop: results of the `pending` tasks (ref -> (session, attempt)) into `results` as they finish, a
    failed one submitted once more."""
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.25)
        for item in q.get_nowait_batch(q.qsize()):
            progress.frame(*item)
        for ref in ready:
            t, attempt = pending.pop(ref)
            try:
                r = ray.get(ref)
            except ray.exceptions.RayError as e:
                r = failed_result(t, e)
            if r["status"] == "failed" and attempt == 1:
                print(f"batch: {t.name} failed ({r['error']}); retrying once", file=sys.stderr, flush=True)
                pending[submit(t)] = (t, 2)
                continue
            r["attempts"] = attempt
            results[t.index] = r
            progress.finished(r)
