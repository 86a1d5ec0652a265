"""Ray executor of `photoreg batch` (optional extra `ray`): one remote task per session.

A task asks for one GPU when the cluster has GPUs and the session may use CUDA (Ray then sets
CUDA_VISIBLE_DEVICES, so the session runs on "cuda"), else for one CPU. A task whose worker process
dies is re-run by Ray (max_retries=1); a session that fails with an error is submitted once more.
Output folders and recordings must be on a filesystem every node sees. Progress comes back through a
Ray queue actor.
"""
from __future__ import annotations

import os
import sys

from .runner import BatchProgress, SessionTask, failed_result, run_one


def _import_ray():
    try:
        import ray
    except ImportError:
        raise RuntimeError("--executor ray needs Ray, which is not installed: "
                           "pip install 'photoreg[ray]' (or use --executor local)") from None
    return ray


def run_ray(tasks: list[SessionTask], progress: BatchProgress, workers: int | None = None,
            address: str | None = None) -> list[dict]:
    """Run the sessions as Ray tasks; results in task order. Uses the Ray instance already initialised
    in this process, else connects to `address`, else starts a local one with `workers` CPUs."""
    ray = _import_ray()
    from ray.util.queue import Queue

    started = not ray.is_initialized()
    if started and address:
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
        q = Queue(actor_options={"num_cpus": 0})
        try:
            return _gather(ray, tasks, progress, q)
        finally:
            q.shutdown()
    finally:
        if started:
            ray.shutdown()


def _gather(ray, tasks: list[SessionTask], progress: BatchProgress, q) -> list[dict]:
    """Submit every session, relay progress from `q`, resubmit a failed session once; results in task order."""
    remote = ray.remote(max_retries=1)(run_one)  # max_retries: Ray re-runs a task whose worker process died

    def submit(t: SessionTask):
        # a CPU task holds one Ray CPU: its split kernel launches (photoreg.kernels.launch) use one thread
        resources = {"num_gpus": 1} if t.session.device == "cuda" else \
            {"num_cpus": 1, "runtime_env": {"env_vars": {"PHOTOREG_CPU_THREADS": "1"}}}
        return remote.options(**resources).remote(t, q)

    pending = {submit(t): (t, 1) for t in tasks}
    results: dict[int, dict] = {}
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
    return [results[t.index] for t in tasks]
