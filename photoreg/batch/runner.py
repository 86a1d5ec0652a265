"""`photoreg batch`: many session files, each into its own output folder, on local workers or Ray.

Every session file is validated before any work starts. A session is complete when its outputs agree
(summary.json's frames_processed equals lighting.jsonl's line count) and OUT/.complete holds the hash
of the session file that made them: --resume skips it, and an edited session file runs again.
`run_one` is the one work function both executors call; the batch folder gets batch_summary.json,
batch_report.md and, where sessions were scored against ground truth, a speed-vs-error plot.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

from ..config import Session, load_session, select_frames
from ..io.atomic import atomic_path, check_output_dir, write_json, write_text
from ..runner import COMPLETE_MARKER, COMPOSITE_DIRS, PICTURE_DIRS
PLOT_NAME = "batch_speed_vs_error.png"
TRACEBACK_LINES = 15


@dataclass
class SessionTask:
    """One session of a batch: the validated session, its file's hash and its place in the batch."""

    index: int
    path: str          # the session file, as given
    name: str          # short name for messages and the report
    session: Session
    digest: str        # session_digest: what the run's outputs follow from


def plan(paths: list[str], device: str | None = None) -> list[SessionTask]:
    """Validate every session file and open its recording; raise one ValueError listing all problems (nothing has
    run then).

    `device` (the --device option) overrides each session's device. Two sessions writing to the same
    output folder are refused, since they would overwrite each other."""
    from ..io.recording import open_configured

    errors, tasks = [], []
    for i, p in enumerate(paths):
        try:
            s = load_session(p)
            check_output_dir(s.output.dir, "[output] dir")
            rec = open_configured(s.recording)
            select_frames(s.frames, len(rec), s.recording.path)
        except (ValueError, OSError) as e:
            errors.append(str(e) if str(Path(p)) in str(e) else f"{p}: {e}")
            continue
        if device:
            s.device = device
        tasks.append(SessionTask(i, str(p), Path(p).stem, s, session_digest(s)))
    by_out: dict[str, SessionTask] = {}
    for t in tasks:
        other = by_out.setdefault(str(Path(t.session.output.dir).resolve()), t)
        if other is not t:
            same = Path(other.path).resolve() == Path(t.path).resolve()
            errors.append(f"{t.path}: listed twice" if same else
                          f"{t.path}: output.dir {t.session.output.dir} is also the output folder of {other.path}")
    if errors:
        raise ValueError(f"{len(errors)} problem(s) in the session files; nothing was run:\n  " + "\n  ".join(errors))
    stems = [t.name for t in tasks]
    for t in tasks:
        if stems.count(t.name) > 1:
            t.name = t.path
    return tasks


def session_digest(s: Session) -> str:
    """sha256 of what a session's outputs follow from: its settings as resolved (paths with their variables expanded,
    the device) and its meshes' bytes, an OBJ's material libraries and textures with them. A session file whose
    ${PHOTOREG_DATA} now points elsewhere, or whose mesh or texture was edited, is not complete any more (--resume
    runs it)."""
    from ..render.scene import obj_material_files

    h = hashlib.sha256(json.dumps(dataclasses.asdict(s), sort_keys=True, default=str).encode())
    for obj in s.objects:
        mesh = Path(obj.mesh)
        h.update(mesh.read_bytes())
        if mesh.suffix.lower() == ".obj":
            for name, file, _ in obj_material_files(mesh):
                h.update(file.read_bytes() if file is not None else b"missing " + name.encode())
    return h.hexdigest()


def completed_result(task: SessionTask) -> dict | None:
    """The result recorded by the run that completed this session's outputs, or None when they are missing (the
    per-frame files its summary counts included), disagree, or were made from other settings (session_digest)."""
    out = Path(task.session.output.dir)
    try:
        marker = json.loads((out / COMPLETE_MARKER).read_text())
        summary = json.loads((out / "summary.json").read_text())
        with open(out / "lighting.jsonl") as f:
            lines = sum(1 for line in f if line.strip())
    except (OSError, ValueError):
        return None
    if not isinstance(marker, dict) or not isinstance(summary, dict):
        return None
    if marker.get("session_sha256") != task.digest or summary.get("frames_processed") != lines:
        return None
    every = task.session.output.pictures_every
    pictures, composites = -(-lines // every) if every else 0, summary.get("composites") or 0
    wanted = [(d, suffix, pictures) for d, suffixes in PICTURE_DIRS.items() for suffix in suffixes] + \
        [(d, suffix, composites) for d, suffixes in COMPOSITE_DIRS.items() for suffix in suffixes]
    if any(n and sum(1 for _ in (out / d).glob(f"[0-9]*{suffix}")) < n for d, suffix, n in wanted) or (
            isinstance(summary.get("video"), dict) and not (out / str(summary["video"].get("file"))).is_file()):
        return None
    return marker.get("result")


def failed_result(task: SessionTask, error: BaseException, wall_s: float | None = None) -> dict:
    """A session's result for an error: message and the tail of its traceback."""
    tb = "".join(traceback.format_exception(error)).rstrip().splitlines()
    return {"session": task.path, "name": task.name, "out": task.session.output.dir, "status": "failed",
            "error": f"{type(error).__name__}: {error}", "traceback": "\n".join(tb[-TRACEBACK_LINES:]),
            "device": task.session.device, "frames": 0, "frames_skipped": [], "wall_s": wall_s,
            "frames_per_s": None, "accuracy": None, "attempts": 1}


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C during a batch's runs: the executor stopped its workers; `results` (in task order) hold the sessions
    that finished and, failed as interrupted, those that did not."""

    def __init__(self, results: list[dict]):
        super().__init__()
        self.results = results


def accuracy_summary(scores: dict) -> dict:
    """The part of photoreg.bench.score's result kept per session: counts and metric summaries."""
    lt = scores["lighting"]
    return {"n_scored": lt["n_scored"], "nonfinite_fraction": lt["nonfinite_fraction"], "metrics": lt["metrics"]}


def run_one(task: SessionTask, progress=None) -> dict:
    """Run one session (the work unit of both executors) and return its result; never raises.

    Writes the run's outputs, scores them where the recording has lighting_gt.json (ground truth that cannot be
    scored is the result's error, the run still ok), then writes the completion marker. `progress` (anything with
    put(), e.g. a queue) receives (index, done, total) after each frame. wall_s covers the whole session (start-up
    and scoring included); frames_per_s is the runner's figure for the frame loop alone."""
    from ..bench.score import score
    from ..runner import run_session

    out = Path(task.session.output.dir)
    t0 = time.perf_counter()
    try:
        (out / COMPLETE_MARKER).unlink(missing_ok=True)
        on_frame = None if progress is None else (lambda done, total: progress.put((task.index, done, total)))
        outcome: dict = {}

        def finish(summary: dict) -> None:   # the folder still the run's: no other run's files scored or marked
            accuracy, notes = None, []
            skipped = summary["frames_skipped"]
            if skipped:   # frames that could not be read: the run is done, but not complete (--resume runs it again)
                notes.append(f"{len(skipped)} frame(s) skipped, the first: frame {skipped[0]['frame']}: "
                             f"{skipped[0]['error']}")
            if (Path(task.session.recording.path) / "lighting_gt.json").is_file():
                try:   # ground truth that does not score leaves the run done, its outputs whole
                    accuracy = accuracy_summary(score(out, task.session.recording.path))
                except (ValueError, OSError) as e:
                    notes.append(f"not scored: {e}")
            result = outcome["result"] = {
                "session": task.path, "name": task.name, "out": str(out), "status": "ok",
                "error": "; ".join(notes) or None, "traceback": None, "device": summary["device"],
                "frames": summary["frames_processed"], "frames_skipped": [sk["frame"] for sk in skipped],
                "wall_s": round(time.perf_counter() - t0, 3), "frames_per_s": summary["frames_per_s"],
                "accuracy": accuracy, "attempts": 1}
            if not skipped:
                write_json(out / COMPLETE_MARKER, {"session_sha256": task.digest, "result": result})

        run_session(task.session, quiet=True, on_frame=on_frame, after=finish)
        return outcome["result"]
    except Exception as e:  # noqa: BLE001 - a failing session is reported, the batch goes on
        return failed_result(task, e, round(time.perf_counter() - t0, 3))


class BatchProgress:
    """Progress on stderr: one line per finished session ([done/total]) and, every `every_s` seconds
    and at its last frame, each running session's frame count."""

    def __init__(self, tasks: list[SessionTask], every_s: float = 2.0, stream=None):
        self.names = {t.index: t.name for t in tasks}
        self.total, self.done, self.every_s = len(tasks), 0, every_s
        self.stream = stream or sys.stderr
        self._last: dict[int, float] = {}

    def _print(self, text: str) -> None:
        print(f"batch: {text}", file=self.stream, flush=True)

    def frame(self, index: int, done: int, total: int) -> None:
        now = time.monotonic()
        if done == total or now - self._last.get(index, -1e9) >= self.every_s:
            self._last[index] = now
            self._print(f"{self.names[index]}: frame {done}/{total}")

    def finished(self, result: dict) -> None:
        self.done += 1
        head = f"[{self.done}/{self.total}] {result['status']} {result['name']}"
        if result["status"] == "failed":
            self._print(f"{head}: {result['error']}")
        elif result["status"] == "skipped":
            self._print(f"{head}: outputs complete in {result['out']}")
        else:
            self._print(f"{head}: {result['frames']} frames in {result['wall_s']:.1f} s "
                        f"({result['frames_per_s']} frames/s) -> {result['out']}")


def _median(result: dict, metric: str):
    m = (result.get("accuracy") or {}).get("metrics", {}).get(metric)
    return None if m is None else m["median"]


def plot_speed_vs_error(path: Path, results: list[dict], metrics: list[str]) -> None:
    """One panel per lighting metric: each scored session's frames/s against its median error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(metrics), figsize=(4.5 * len(metrics), 3.8), squeeze=False)
    for ax, metric in zip(axes[0], metrics):
        for r in results:
            y = _median(r, metric)
            if y is not None and r["frames_per_s"]:
                ax.scatter(r["frames_per_s"], y)
                ax.annotate(r["name"], (r["frames_per_s"], y), fontsize=8, xytext=(3, 3), textcoords="offset points")
        ax.set_xlabel("frames/s")
        ax.set_ylabel(f"{metric} (median)")
        ax.grid(alpha=0.3)
    fig.suptitle("speed vs error per session")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def _cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value).replace("|", "\\|").replace("\n", " ")


def format_report(summary: dict, metrics: list[str], plot: str | None) -> str:
    """batch_report.md: counts, one table row per session, the plot, failures with traceback tails."""
    rows = summary["sessions"]
    c = summary["counts"]
    lines = ["# photoreg batch report", "",
             f"{len(rows)} sessions: {c['ok']} ok, {c['failed']} failed, {c['skipped']} skipped "
             f"(executor {summary['executor']}, {summary['wall_s']:.1f} s). Skipped sessions show the figures of "
             "the run that completed their outputs.", ""]
    head = ["session", "status", "device", "frames", "wall s", "frames/s", *[f"{m} (median)" for m in metrics],
            "output", "error"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        error = r["error"] if r["error"] is None or len(r["error"]) <= 120 else r["error"][:117] + "..."
        cells = [r["name"], r["status"], r["device"], r["frames"], r["wall_s"], r["frames_per_s"],
                 *[_median(r, m) for m in metrics], r["out"], error]
        lines.append("| " + " | ".join(_cell(x) for x in cells) + " |")
    if plot:
        lines += ["", f"![speed vs error]({plot})"]
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        lines += ["", "## Failures"]
        for r in failed:
            lines += ["", f"### {r['name']} ({r['session']})", "", "```", r["traceback"] or r["error"], "```"]
    return "\n".join(lines) + "\n"


def write_reports(report_dir: str | Path, results: list[dict], executor: str, wall_s: float) -> dict:
    """batch_summary.json, batch_report.md and the speed-vs-error plot (when any session has accuracy)."""
    from ..bench.score import LIGHTING_METRICS

    report_dir = Path(report_dir)
    counts = {k: sum(r["status"] == k for r in results) for k in ("ok", "failed", "skipped")}
    summary = {"executor": executor, "wall_s": round(wall_s, 3), "counts": counts, "sessions": results}
    write_json(report_dir / "batch_summary.json", summary)
    metrics = [m for m in LIGHTING_METRICS if any(_median(r, m) is not None for r in results)]
    if metrics:
        plot_speed_vs_error(report_dir / PLOT_NAME, results, metrics)
    write_text(report_dir / "batch_report.md", format_report(summary, metrics, PLOT_NAME if metrics else None))
    return summary


def batch_command(args) -> int:
    """CLI entry: validate all sessions, skip complete ones with --resume, run the rest, write the reports.
    Exit code 1 when any session failed (the others' outputs stand)."""
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    if args.ray_address and args.executor != "ray":
        raise ValueError("--ray-address needs --executor ray")
    check_output_dir(args.out, "--out")
    t0 = time.perf_counter()
    tasks = plan(args.sessions, args.device)
    progress = BatchProgress(tasks)
    results: dict[int, dict] = {}
    todo = []
    for t in tasks:
        previous = completed_result(t) if args.resume else None
        if previous is None:
            todo.append(t)
        else:
            results[t.index] = {**previous, "status": "skipped"}
            progress.finished(results[t.index])
    interrupted = False
    if todo:
        try:
            if args.executor == "ray":
                from .ray_executor import run_ray
                done = run_ray(todo, progress, args.workers, args.ray_address)
            else:
                from .local import run_local
                done = run_local(todo, progress, args.workers)
        except BatchInterrupted as e:   # Ctrl-C: the finished sessions still get their report
            done, interrupted = e.results, True
        results.update((t.index, r) for t, r in zip(todo, done))
    ordered = [results[t.index] for t in tasks]
    summary = write_reports(args.out, ordered, args.executor, time.perf_counter() - t0)
    c = summary["counts"]
    print(f"batch: {'interrupted: ' if interrupted else ''}{c['ok']} ok, {c['failed']} failed, {c['skipped']} "
          f"skipped; report in {Path(args.out) / 'batch_report.md'}")
    return 130 if interrupted else 1 if c["failed"] else 0
