"""`photoreg batch` end to end with real pipelines on a tiny synthetic recording (64x48, 16 rays, 2 bands):
validation before any work, a failing session beside two good ones (local pool and Ray), the summary and
report, --resume doing no work, an edited session file running again."""
from __future__ import annotations

import importlib.util
import json
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scenes import write_recording
from servecli import free_port

from photoreg.cli import main
from photoreg.types import Intrinsics

K = Intrinsics(64, 48, 56.0, 56.0, 31.5, 23.5, 5000.0)
FRAMES = 3


def write_session(folder: Path, name: str, recording: Path, **extra_top: str) -> Path:
    """sessions/NAME.toml: first FRAMES frames of `recording` on the CPU with tiny settings, output out/NAME."""
    top = "".join(f"{k} = {v}\n" for k, v in extra_top.items())
    path = folder / "sessions" / f"{name}.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f'frames = "0:{FRAMES}"\ndevice = "cpu"\n{top}\n[recording]\npath = "{recording}"\n\n'
                    '[lighting]\nbands = 2\nrays = 16\nstride = 4\n\n[reconstruction]\nvoxel_size = 0.02\n\n'
                    f'[output]\ndir = "../out/{name}"\npictures_every = 0\n')
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return write_recording(tmp_path_factory.mktemp("rec") / "scene", K, FRAMES + 1)


@pytest.fixture
def three_sessions(tmp_path, recording) -> tuple[list[Path], Path]:
    """Sessions a and b on the good recording; 'broken' on a copy whose colour images are all corrupt, which the
    batch's checks accept (the recording opens) but the run refuses (no frame can be processed)."""
    broken_rec = tmp_path / "broken_rec"
    shutil.copytree(recording, broken_rec)
    for png in (broken_rec / "rgb").glob("*.png"):
        png.write_bytes(b"not a png")
    paths = [write_session(tmp_path, "a", recording), write_session(tmp_path, "broken", broken_rec),
             write_session(tmp_path, "b", recording)]
    return paths, tmp_path / "report"


def mtimes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


def check_three_session_run(tmp_path: Path, report: Path, capsys) -> dict:
    """The good sessions complete with scored outputs, the broken one is reported with its error."""
    summary = json.loads((report / "batch_summary.json").read_text())
    by_name = {r["name"]: r for r in summary["sessions"]}
    assert [r["name"] for r in summary["sessions"]] == ["a", "broken", "b"]
    assert summary["counts"] == {"ok": 2, "failed": 1, "skipped": 0}
    broken = by_name["broken"]
    assert broken["status"] == "failed" and "no frame could be processed" in broken["error"]
    assert "run_session" in broken["traceback"] and not (tmp_path / "out" / "broken" / ".complete").exists()
    for name in ("a", "b"):
        r, out = by_name[name], tmp_path / "out" / name
        assert r["status"] == "ok" and r["error"] is None and r["device"] == "cpu"
        assert r["frames"] == FRAMES and r["frames_per_s"] > 0 and r["wall_s"] > 0
        assert r["accuracy"]["n_scored"] == FRAMES
        assert math.isfinite(r["accuracy"]["metrics"]["irradiance_si_rmse_sphere"]["median"])
        assert len((out / "lighting.jsonl").read_text().splitlines()) == FRAMES
        assert json.loads((out / "summary.json").read_text())["frames_processed"] == FRAMES
        assert (out / ".complete").is_file()
    md = (report / "batch_report.md").read_text()
    assert "| a | ok | cpu | 3 |" in md and "| broken | failed |" in md and "## Failures" in md
    assert (report / "batch_speed_vs_error.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    err = capsys.readouterr().err
    assert "[3/3]" in err and f"a: frame {FRAMES}/{FRAMES}" in err and "failed broken" in err
    return by_name


def test_local_batch_failure_resume_and_changed_session(three_sessions, tmp_path, capsys):
    paths, report = three_sessions
    args = ["batch", *map(str, paths), "--workers", "2", "--out", str(report)]
    assert main(args) == 1
    check_three_session_run(tmp_path, report, capsys)

    # --resume over the complete sessions: nothing runs, nothing is rewritten
    good = [str(paths[0]), str(paths[2])]
    before = mtimes(tmp_path / "out")
    assert main(["batch", *good, "--resume", "--out", str(report)]) == 0
    assert mtimes(tmp_path / "out") == before
    summary = json.loads((report / "batch_summary.json").read_text())
    assert [r["status"] for r in summary["sessions"]] == ["skipped", "skipped"]
    assert summary["sessions"][0]["frames"] == FRAMES and summary["sessions"][0]["accuracy"] is not None
    assert "skipped a" in capsys.readouterr().err

    # a session whose settings changed runs again under --resume (a comment alone changes nothing); the unchanged
    # one stays skipped
    paths[2].write_text(paths[2].read_text() + "# a comment\n")
    assert main(["batch", *good, "--resume", "--out", str(report)]) == 0
    assert [r["status"] for r in json.loads((report / "batch_summary.json").read_text())["sessions"]] == ["skipped"] * 2
    paths[2].write_text(paths[2].read_text().replace("bands = 2", "bands = 3"))
    assert main(["batch", *good, "--resume", "--out", str(report)]) == 0
    summary = json.loads((report / "batch_summary.json").read_text())
    assert [r["status"] for r in summary["sessions"]] == ["skipped", "ok"]
    assert mtimes(tmp_path / "out" / "a") == {k[2:]: v for k, v in before.items() if k.startswith("a/")}
    assert "batch: 1 session(s) on 1 worker process(es) on the CPU" in capsys.readouterr().err

    # a marker that is not the batch's (a JSON list) does not mark anything complete: a runs again, no traceback
    (tmp_path / "out" / "a" / ".complete").write_text("[1]")
    assert main(["batch", *good, "--resume", "--out", str(report)]) == 0
    summary = json.loads((report / "batch_summary.json").read_text())
    assert [r["status"] for r in summary["sessions"]] == ["ok", "skipped"]
    # a plain `photoreg run` into a complete session's folder takes the batch's marker away: it runs again
    assert main(["run", str(paths[2]), "--frames", "0:1", "--quiet"]) == 0
    assert not (tmp_path / "out" / "b" / ".complete").exists()
    assert main(["batch", *good, "--resume", "--out", str(report)]) == 0
    summary = json.loads((report / "batch_summary.json").read_text())
    assert [r["status"] for r in summary["sessions"]] == ["skipped", "ok"]
    assert summary["sessions"][1]["frames"] == FRAMES
    # files a complete run wrote, gone: not complete (before: skipped, its summary and lighting.jsonl alone counted)
    paths[2].write_text(paths[2].read_text().replace("pictures_every = 0", "pictures_every = 1"))
    assert main(["batch", str(paths[2]), "--resume", "--out", str(report)]) == 0
    assert main(["batch", str(paths[2]), "--resume", "--out", str(report)]) == 0
    assert json.loads((report / "batch_summary.json").read_text())["sessions"][0]["status"] == "skipped"
    shutil.rmtree(tmp_path / "out" / "b" / "sphere")
    assert main(["batch", str(paths[2]), "--resume", "--out", str(report)]) == 0
    assert json.loads((report / "batch_summary.json").read_text())["sessions"][0]["status"] == "ok"
    assert len(list((tmp_path / "out" / "b" / "sphere").glob("*.png"))) == FRAMES


def test_frames_a_run_skipped_leave_its_session_incomplete(tmp_path, recording, capsys):
    """A session whose run skipped an unreadable frame is done but not complete: the result and report say which
    frames, no completion marker is written, and --resume runs it again once the file is mended (before: reported ok
    with no word of it, marked complete, and --resume never ran it again)."""
    rec = tmp_path / "rec"
    shutil.copytree(recording, rec)
    png = rec / "rgb" / "000001.png"
    good = png.read_bytes()
    png.write_bytes(b"not a png")
    path = write_session(tmp_path, "gap", rec)
    report = tmp_path / "report"
    assert main(["batch", str(path), "--out", str(report)]) == 0
    r = json.loads((report / "batch_summary.json").read_text())["sessions"][0]
    assert r["status"] == "ok" and r["frames"] == FRAMES - 1 and r["frames_skipped"] == [1]
    assert r["error"].startswith("1 frame(s) skipped, the first: frame 1: ")
    assert "1 frame(s) skipped" in (report / "batch_report.md").read_text()
    assert not (tmp_path / "out" / "gap" / ".complete").exists()
    png.write_bytes(good)
    assert main(["batch", str(path), "--resume", "--out", str(report)]) == 0
    r = json.loads((report / "batch_summary.json").read_text())["sessions"][0]
    assert r["status"] == "ok" and r["frames"] == FRAMES and r["frames_skipped"] == [] and r["error"] is None
    assert (tmp_path / "out" / "gap" / ".complete").is_file()


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_ctrl_c_stops_the_batch_and_reports_what_finished(tmp_path, executor):
    """Ctrl-C in a terminal (SIGINT to the batch's process group) while its workers run: the workers are stopped, the
    report lists every session as interrupted, and the batch exits 130 at once (before: it hung joining workers
    interrupted mid-queue, or printed their tracebacks, and wrote no report; with Ray it wrote none till 2026-11-29)."""
    import os
    import signal
    import subprocess

    demo = Path(__file__).resolve().parents[1] / "data" / "demo"
    paths = []
    for name in ("one", "two"):
        text = (demo / "session.toml").read_text().replace('path = "."', f'path = "{demo}"')
        text = text.replace('mesh = "object.obj"', f'mesh = "{demo / "object.obj"}"')
        paths.append(tmp_path / f"{name}.toml")
        paths[-1].write_text(text.replace('dir = "out"', f'dir = "{tmp_path / name}"'))
    report = tmp_path / "report"
    if executor == "ray":
        pytest.importorskip("ray", reason="ray not installed: the Ray executor is optional")
    proc = subprocess.Popen([sys.executable, "-m", "photoreg", "batch", *map(str, paths), "--workers", "2",
                             "--device", "cpu", "--out", str(report), "--executor", executor], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            cwd=Path(__file__).resolve().parents[1],
                            # as a terminal's: a test run started in the background (`pytest &`) ignores SIGINT, and
                            # its children would too, Python then installing no KeyboardInterrupt
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        for line in proc.stderr:   # the workers are at work
            if ": frame " in line:
                break
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130 and "Traceback" not in err, err
    assert "batch: interrupted: 0 ok, 2 failed, 0 skipped" in out
    summary = json.loads((report / "batch_summary.json").read_text())
    assert [r["error"] for r in summary["sessions"]] == [
        "KeyboardInterrupt: interrupted (Ctrl-C) before it finished"] * 2
    assert not any((tmp_path / name / ".complete").exists() for name in ("one", "two"))
    deadline = time.monotonic() + 20   # no worker left behind (stopped ones are reaped within a few seconds)
    while True:
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline, "a process of the batch's group outlived it"
        time.sleep(0.2)


def test_a_dead_worker_s_sessions_run_again(tmp_path, recording):
    """A worker process killed mid-batch (SIGKILL: out of memory, an operator) breaks the pool and every session in
    it: they go on in new worker processes and finish, the one it ran on its second attempt, the queued ones on their
    first (before: each of them failed with BrokenProcessPool, the queued ones too, which had not started)."""
    import os
    import signal
    import subprocess

    paths = [write_session(tmp_path, name, recording) for name in ("a", "b", "c")]
    proc = subprocess.Popen([sys.executable, "-m", "photoreg", "batch", *map(str, paths), "--workers", "1",
                             "--out", str(tmp_path / "report")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=Path(__file__).resolve().parents[1])
    try:
        lines = []
        for line in proc.stderr:   # a session at work: its worker process killed
            lines.append(line)
            if ": frame " in line:
                break
        workers = [int(p) for p in os.listdir("/proc") if p.isdigit() and _parent(int(p)) == proc.pid
                   and b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()]
        assert len(workers) == 1, workers
        os.kill(workers[0], signal.SIGKILL)
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = "".join(lines) + err
    assert proc.returncode == 0, err
    assert "a worker process died; " in err and " go on in new worker processes" in err
    sessions = json.loads((tmp_path / "report" / "batch_summary.json").read_text())["sessions"]
    # the session it ran used an attempt; those still queued did not (they would fail with it if it died again)
    assert [r["status"] for r in sessions] == ["ok"] * 3, sessions
    assert sorted(r["attempts"] for r in sessions) == [1, 1, 2], sessions


def _parent(pid: int) -> int | None:
    """The parent process id of `pid` (Linux /proc), None where it is gone."""
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None


def test_invalid_sessions_reported_before_any_work(tmp_path, recording, capsys):
    good = write_session(tmp_path, "good", recording)
    unknown = write_session(tmp_path, "unknown", recording, colour='"red"')
    wrong_type = write_session(tmp_path, "wrong_type", recording)
    wrong_type.write_text(wrong_type.read_text().replace("rays = 16", 'rays = "many"'))
    missing = write_session(tmp_path, "missing", tmp_path / "no_such_recording")
    twin = write_session(tmp_path, "twin", recording)
    twin.write_text(twin.read_text().replace("out/twin", "out/good"))
    frames = write_session(tmp_path, "frames", recording)
    frames.write_text(frames.read_text().replace('frames = "0:3"', 'frames = "abc"'))
    corrupt_rec = tmp_path / "corrupt_rec"   # the recording opens at the start: its calibration is read
    shutil.copytree(recording, corrupt_rec)
    (corrupt_rec / "intrinsics.json").write_text("{not json")
    corrupt = write_session(tmp_path, "corrupt", corrupt_rec)
    none = write_session(tmp_path, "none", recording)   # selects no frame of the recording's 4
    none.write_text(none.read_text().replace('frames = "0:3"', 'frames = "50:60"'))
    into_file = write_session(tmp_path, "into_file", recording)   # its output folder a file (before: failed running)
    into_file.write_text(into_file.read_text().replace('dir = "../out/into_file"', 'dir = "good.toml"'))
    report = tmp_path / "report"
    args = ["batch", *map(str, [good, unknown, wrong_type, missing, twin, frames, corrupt, none, into_file, good]),
            "--out", str(report)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "9 problem(s)" in err and f"{recording}: no frames selected (recording has 4, --frames '50:60')" in err
    assert f"{into_file}: output folder {good} ([output] dir) is a file" in err
    assert f"{good}: listed twice" in err and f"{frames}: frames (--frames): expected N" in err
    assert f"{corrupt_rec / 'intrinsics.json'}:1: not valid JSON" in err
    assert f"{unknown}: unknown section or key 'colour'" in err
    assert f"{wrong_type}: key 'lighting.rays' must be int" in err
    assert f"{missing}: recording.path" in err and "does not exist" in err
    assert f"{twin}: output.dir" in err and str(good) in err
    assert not (tmp_path / "out").exists() and not report.exists()


def test_option_errors(tmp_path, recording, capsys, monkeypatch):
    s = str(write_session(tmp_path, "a", recording))
    assert main(["batch", s, "--workers", "0"]) == 2
    assert main(["batch", s, "--ray-address", "auto"]) == 2
    err = capsys.readouterr().err
    if importlib.util.find_spec("ray") is not None:   # nothing at the address: refused at once, not after minutes
        port = free_port()
        assert main(["batch", s, "--executor", "ray", "--ray-address", f"127.0.0.1:{port}", "--out",
                     str(tmp_path / "report")]) == 2
        assert f"--ray-address 127.0.0.1:{port}: nothing answers there" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "ray", None)   # as if Ray were not installed
    assert main(["batch", s, "--executor", "ray", "--out", str(tmp_path / "report")]) == 2
    err += capsys.readouterr().err
    assert "--workers must be >= 1" in err and "--ray-address needs --executor ray" in err
    assert "pip install 'photoreg[ray]'" in err and not (tmp_path / "out").exists()
    (tmp_path / "report_file").write_text("a file")   # refused before any session runs
    assert main(["batch", s, "--out", str(tmp_path / "report_file")]) == 2
    assert "report_file (--out) is a file" in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_ground_truth_that_does_not_score_leaves_the_run_done(tmp_path, recording, capsys):
    """A recording whose ground truth cannot be scored (a scene.json, but not the generator's): the session's
    run is ok and complete (--resume skips it), its error says why it was not scored."""
    odd = tmp_path / "odd_rec"
    shutil.copytree(recording, odd)
    (odd / "scene.json").write_text("{}")
    session, report = write_session(tmp_path, "odd", odd), tmp_path / "report"
    assert main(["batch", str(session), "--out", str(report)]) == 0
    row = json.loads((report / "batch_summary.json").read_text())["sessions"][0]
    assert row["status"] == "ok" and row["accuracy"] is None and row["frames"] == FRAMES
    assert row["error"].startswith(f"not scored: {odd}") and "not as `photoreg synth` writes it" in row["error"]
    assert main(["batch", str(session), "--out", str(report), "--resume"]) == 0
    assert json.loads((report / "batch_summary.json").read_text())["sessions"][0]["status"] == "skipped"


@pytest.mark.slow
def test_ray_batch_retries_failure_once(three_sessions, tmp_path, capsys):
    ray = pytest.importorskip("ray", reason="Ray is not installed (extra 'ray': pip install 'photoreg[ray]')")
    paths, report = three_sessions
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        assert main(["batch", *map(str, paths), "--executor", "ray", "--out", str(report)]) == 1
    finally:
        ray.shutdown()
    by_name = check_three_session_run(tmp_path, report, capsys)
    assert by_name["broken"]["attempts"] == 2 and by_name["a"]["attempts"] == 1


def test_local_workers_share_the_cores(monkeypatch):
    """Each local worker gets its share of the cores for split CPU launches (N workers x all cores would
    oversubscribe them), unless PHOTOREG_CPU_THREADS is already set."""
    import os

    from photoreg.batch import local
    from photoreg.kernels.launch import cpu_threads

    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    assert [local.cpu_share(w) for w in (1, 2, 3, 8, 16)] == [8, 4, 2, 1, 1]
    monkeypatch.delenv("PHOTOREG_CPU_THREADS", raising=False)
    local._init_worker(None, 3)
    assert os.environ["PHOTOREG_CPU_THREADS"] == "3" and cpu_threads() == 3
    monkeypatch.setenv("PHOTOREG_CPU_THREADS", "5")
    local._init_worker(None, 3)
    assert cpu_threads() == 5


def test_default_workers_share_each_gpu():
    """Without --workers: on GPUs one worker per host core of each GPU's share, at most one per
    GPU_MEMORY_PER_WORKER of its memory, at least one per GPU; without GPUs one per core; either way at most one per
    HOST_MEMORY_PER_WORKER of the host memory available (a 16-core host with little of it must not run 16)."""
    from photoreg.batch import local

    gib = 1024 ** 3
    assert local.default_workers(16, [80 * gib]) == 16         # one H100 on a 16-core host
    assert local.default_workers(16, [80 * gib, 80 * gib]) == 16
    assert local.default_workers(16, [6 * gib]) == 3           # a small GPU: its memory bounds the count
    assert local.default_workers(2, [80 * gib]) == 2
    assert local.default_workers(3, [80 * gib, 80 * gib]) == 2  # a core each: the share rounds down
    assert local.default_workers(1, [gib, gib]) == 2           # at least one per GPU
    assert local.default_workers(6, []) == 6
    assert local.default_workers(16, [80 * gib], host_memory=9 * gib) == 4
    assert local.default_workers(6, [], host_memory=5 * gib) == 2
    assert local.default_workers(6, [], host_memory=gib) == 1
    assert local.default_workers(6, [], host_memory=64 * gib) == 6
    assert local.available_memory() > 0   # Linux: MemAvailable


def test_gpu_fraction_fits_exactly_that_many_sessions():
    """A session task's share of a GPU (Ray counts resources in 1e-4 units): `share` of them fit on one, no more."""
    from photoreg.batch.ray_executor import gpu_fraction

    for share in range(1, 40):
        units = round(gpu_fraction(share) * 1e4)
        assert share * units <= 10_000 < (share + 1) * units


@pytest.mark.slow
def test_ray_sessions_share_each_gpu():
    """On a Ray cluster with GPUs, sessions share each GPU as local workers do: a node of 16 CPUs and one GPU takes
    16 at once (a probe task reads the GPU's memory; here Warp finds no CUDA device behind the GPU Ray was told of,
    so the CPUs alone count), --workers spread over the GPUs when this process started Ray with them; Ray runs
    that many tasks of gpu_fraction at once on the GPU."""
    ray = pytest.importorskip("ray", reason="Ray is not installed (extra 'ray': pip install 'photoreg[ray]')")
    from photoreg.batch.ray_executor import gpu_fraction, sessions_per_gpu

    ray.init(num_cpus=16, num_gpus=1, include_dashboard=False, log_to_driver=False)
    try:
        assert sessions_per_gpu(ray) == 16
        assert sessions_per_gpu(ray, workers=3) == 3

        @ray.remote(num_cpus=0)
        class Gate:
            def __init__(self):
                self.started, self.open = 0, False

            def enter(self):
                self.started += 1

            def count(self):
                return self.started

            def release(self):
                self.open = True

            def is_open(self):
                return self.open

        gate = Gate.remote()

        @ray.remote(num_cpus=0, num_gpus=gpu_fraction(3))
        def session(g):   # holds its share of the GPU until the gate opens
            ray.get(g.enter.remote())
            while not ray.get(g.is_open.remote()):
                time.sleep(0.05)

        refs = [session.remote(gate) for _ in range(4)]
        deadline = time.time() + 60
        while ray.get(gate.count.remote()) < 3 and time.time() < deadline:
            time.sleep(0.1)
        time.sleep(2)
        assert ray.get(gate.count.remote()) == 3   # three at once; the fourth waits for a share of the GPU
        gate.release.remote()
        ray.get(refs)
        assert ray.get(gate.count.remote()) == 4
    finally:
        ray.shutdown()


def test_photoreg_sets_one_blas_thread_before_numpy_loads():
    """Importing photoreg (as scripts and spawned batch workers do first) gives numpy's BLAS one thread unless
    OPENBLAS_NUM_THREADS is set, on a many-core host too (here one of 16 cores, as os.cpu_count says): its numpy
    then sees it."""
    import os
    import subprocess

    code = "import os; os.cpu_count = lambda: 16; import photoreg, numpy; print(os.environ['OPENBLAS_NUM_THREADS'])"
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "1"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OPENBLAS_NUM_THREADS": "3"},
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "3"


def test_the_digest_follows_an_obj_s_material_and_texture(tmp_path):
    """--resume's session digest changes with an OBJ's texture image or material library (before: the .obj's bytes
    alone, so an edited texture left its session complete)."""
    import trimesh
    from PIL import Image

    from photoreg.batch.runner import session_digest
    from photoreg.config import ObjectConfig, Session

    box = trimesh.creation.box(extents=(1, 1, 1))
    box.visual = trimesh.visual.TextureVisuals(uv=box.vertices[:, :2] + 0.5,
                                               image=Image.fromarray(np.full((4, 4, 3), 200, np.uint8)))
    box.export(tmp_path / "box.obj")
    s = Session(objects=[ObjectConfig(mesh=str(tmp_path / "box.obj"), albedo="texture")])
    before = session_digest(s)
    assert session_digest(s) == before
    (image,) = tmp_path.glob("*.png")
    Image.fromarray(np.full((4, 4, 3), 100, np.uint8)).save(image)
    assert session_digest(s) != before
    edited = session_digest(s)
    (mtl,) = tmp_path.glob("*.mtl")
    mtl.write_text(mtl.read_text() + "\n# an edit\n")
    assert session_digest(s) != edited
