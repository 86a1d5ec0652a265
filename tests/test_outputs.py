"""A run's output path: the sRGB table, files written beside the frames (OutputWriter), frames read ahead
(Ahead, ReadAhead), and a run whose writes fail."""
from __future__ import annotations

import json
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from photoreg.config import load_session
from photoreg.io.images import _srgb_oetf8, linear_to_srgb, read_exr, read_rgb
from photoreg.io.ahead import Ahead
from photoreg.io.recording import ReadAhead
from photoreg.io.writer import OutputWriter
from photoreg.runner import run_session

REPO = Path(__file__).resolve().parents[1]


def _definition(img) -> np.ndarray:
    """linear_to_srgb by its formula alone: non-finite to 0 / 1, clipped, the OETF rounded."""
    x = np.clip(np.nan_to_num(np.asarray(img, np.float32), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return _srgb_oetf8(x)


def test_srgb_table_gives_the_definitions_codes():
    """The table agrees with the formula everywhere, the values beside each of the 255 code steps included (the
    buckets that hold a step are converted by the formula; a table without that fix-up gets them wrong)."""
    codes = np.arange(1, 256) - 0.5
    y = codes / 255.0
    steps = np.where(y <= 0.04045, y / 12.92, ((y + 0.055) / 1.055) ** 2.4).astype(np.float32)
    near = np.concatenate([steps + k * np.spacing(steps) for k in range(-40, 41)])
    rng = np.random.default_rng(0)
    x = np.concatenate([near, rng.random(200_000, dtype=np.float32) ** 3,
                        np.array([0.0, -0.0, 1.0, 1.5, -2.0, np.nan, np.inf, -np.inf, 0.0031308, 1e-40], np.float32)])
    assert np.array_equal(linear_to_srgb(x), _definition(x))
    assert np.array_equal(linear_to_srgb(x.astype(np.float64)), _definition(x))   # float64 input: same codes
    img = rng.random((7, 9, 3)).astype(np.float32)
    out = linear_to_srgb(img)
    assert out.dtype == np.uint8 and out.shape == img.shape and np.array_equal(out, _definition(img))
    assert linear_to_srgb(np.array([np.nan, np.inf, -np.inf], np.float32)).tolist() == [0, 255, 0]


def test_writer_runs_jobs_in_order_and_bounds_the_queue():
    done, gate = [], threading.Event()
    w = OutputWriter(threads=1, queued=2)
    w.submit(lambda: (gate.wait(5), done.append(0)))
    w.submit(done.append, 1)
    started = time.perf_counter()
    threading.Timer(0.3, gate.set).start()
    w.submit(done.append, 2)           # two unfinished: waits for the first to end
    assert time.perf_counter() - started >= 0.25 and w.waited_s >= 0.25
    for i in range(3, 20):
        w.submit(done.append, i)
    w.close()
    assert done == list(range(20))
    with pytest.raises(RuntimeError, match="after close"):
        w.submit(done.append, 99)
    with pytest.raises(ValueError, match="threads"):
        OutputWriter(threads=0)


def test_writer_raises_the_first_error_and_keeps_the_jobs_before_it(tmp_path):
    written = []

    def write(i: int) -> None:
        if i == 3:
            raise OSError(f"{tmp_path / 'x.png'}: could not write PNG")
        time.sleep(0.01)
        written.append(i)

    w = OutputWriter(threads=2)
    with pytest.raises(OSError, match="x.png: could not write PNG"):
        for i in range(50):
            w.submit(write, i)
    with pytest.raises(OSError, match="x.png"):
        w.close()
    assert {0, 1, 2} <= set(written) and 3 not in written
    # an error already on its way out is not replaced by the writer's
    with pytest.raises(KeyError):
        with OutputWriter(threads=1) as w2:
            w2.submit(write, 3)
            time.sleep(0.05)
            raise KeyError("the caller's")


def test_work_ahead_keeps_order_raises_in_place_and_stops():
    """Ahead: results in the items' order whatever order the threads finish in; an error of the work or of drawing
    the items raised in its place, after the results before it; items drawn ahead of the caller (`depth` + 1 beyond
    the one in hand, no more), and none after close()."""
    pulled = []

    def items(n: int, bad: int | None = None):
        for i in range(n):
            pulled.append(i)
            if i == bad:
                raise ValueError(f"item {i}: unreadable")
            yield i

    def slow_first(i: int) -> int:   # later items finish first
        time.sleep(0.05 if i % 3 == 0 else 0.0)
        if i == 7:
            raise KeyError("work 7")
        return i * i

    assert list(Ahead(slow_first, items(7), threads=3, depth=3)) == [i * i for i in range(7)]
    got = []
    with pytest.raises(ValueError, match="item 4"):
        for r in Ahead(slow_first, items(10, bad=4), threads=2):
            got.append(r)
    assert got == [0, 1, 4, 9]
    got = []
    with pytest.raises(KeyError, match="work 7"):
        for r in Ahead(slow_first, items(10), threads=3, depth=4):
            got.append(r)
    assert got == [i * i for i in range(7)]
    pulled.clear()
    ahead = Ahead(slow_first, items(1000), threads=2, depth=2)
    for r in ahead:
        if r == 25:
            time.sleep(0.2)   # time to draw all it may
            assert len(pulled) == 5 + 1 + 2 + 1   # `depth` + 1 past the item in hand, no more
            break
    ahead.close()
    assert len(pulled) == 5 + 1 + 2 + 1


def test_frames_read_ahead_in_order_with_the_unreadable_ones_reported(tmp_path):
    """ReadAhead on several threads gives iter_frames' frames in order; an unreadable frame goes to on_error in its
    place (or is raised there without on_error)."""
    from photoreg.io.recording import iter_frames, open_recording
    from photoreg.types import Intrinsics
    from scenes import write_recording

    root = write_recording(tmp_path / "rec", Intrinsics(40, 30, 35.0, 35.0, 19.5, 14.5, 5000.0), 8)
    rec = open_recording(root)
    (rec.color_files[5]).write_bytes(b"not a png")
    errors, order = [], []
    frames = ReadAhead(rec, on_error=lambda i, msg: (errors.append(i), order.append(("error", i))), threads=3)
    got = []
    for f in frames:
        got.append(f)
        order.append(("frame", f.index))
    want = list(iter_frames(rec, on_error=lambda i, msg: None))
    assert [f.index for f in got] == [0, 1, 2, 3, 4, 6, 7] and errors == [5]
    assert order == [("frame", i) for i in range(5)] + [("error", 5), ("frame", 6), ("frame", 7)]
    for a, b in zip(got, want):
        assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth)
    with pytest.raises(ValueError, match=re.escape(str(rec.color_files[5]))):
        list(ReadAhead(rec, threads=2))


def test_run_skips_an_unreadable_frame_and_names_it(tmp_path, capsys):
    """`photoreg run` of a recording with a corrupt colour image: every other frame is processed in order, the bad
    one is listed in summary.json's frames_skipped with the file's error; with none readable the run is an error
    (exit status 2) that names the first, and the earlier run's lighting.jsonl and summary.json stay as they were."""
    from photoreg.cli import main
    from photoreg.io.recording import open_recording
    from photoreg.types import Intrinsics
    from scenes import write_recording

    root = write_recording(tmp_path / "rec", Intrinsics(80, 60, 70.0, 70.0, 39.5, 29.5, 5000.0), 4)
    bad = open_recording(root).color_files[1]
    bad.write_bytes(b"not a png")
    out = tmp_path / "out"
    assert main(["run", str(root), "--out", str(out), "--bands", "2", "--rays", "16", "--stride", "4",
                 "--voxel-size", "0.02", "--device", "cpu", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    records = [json.loads(line) for line in (out / "lighting.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in records] == [0, 2, 3] and summary["frames_processed"] == 3
    (skipped,) = summary["frames_skipped"]
    assert skipped["frame"] == 1 and str(bad) in skipped["error"]
    before = {name: (out / name).read_bytes() for name in ("summary.json", "lighting.jsonl")}
    for path in open_recording(root).color_files:   # none readable: the run fails and replaces nothing
        path.write_bytes(b"not a png")
    capsys.readouterr()
    assert main(["run", str(root), "--out", str(out), "--device", "cpu", "--quiet"]) == 2
    first = open_recording(root).color_files[0]
    err = capsys.readouterr().err
    assert f"no frame could be processed, all 4 selected were skipped (frame 0: {first}" in err
    assert f"nothing in {out} was replaced" in err
    assert {name: (out / name).read_bytes() for name in before} == before
    assert not (out / "lighting.jsonl.partial").exists()


def test_a_frame_without_a_pose_is_counted_as_no_composite(tmp_path, capsys):
    """The demo with frame 0's recorded pose missing: 3 frames processed, 2 composited (summary.json 'composites'),
    and `photoreg run` says so instead of leaving the video a frame short without a word."""
    import shutil

    from photoreg.cli import main

    rec = tmp_path / "demo"
    shutil.copytree(REPO / "data" / "demo", rec)
    gt = rec / "groundtruth.txt"
    gt.write_text("".join(line for line in gt.read_text().splitlines(True) if not line.startswith("0.000000")))
    session = rec / "session.toml"
    out = tmp_path / "out"
    assert main(["run", str(session), "--out", str(out), "--frames", "0:3", "--rays", "8", "--stride", "8", "--bands",
                 "2", "--device", "cpu", "--video", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_processed"] == 3 and summary["composites"] == 2 and summary["video"]["frames"] == 2
    assert "1 frame(s) without a pose have no composite" in capsys.readouterr().out


def test_a_run_leaves_only_its_own_outputs(tmp_path, capsys):
    """A run into a folder holding an earlier run's outputs: once it finishes, the earlier run's per-frame files it
    did not write again (pictures, composites, lightmaps), its video and its tracked trajectory are gone (photoreg
    score would take them for this run's), and with them a batch's completion marker; other files stay. They go as
    the run writes its first frame: one interrupted later leaves its own frames and lighting.jsonl.partial alone
    (before: written over the earlier run's, beside its lighting.jsonl and summary.json, two runs mixed); one whose
    object cannot load does not touch the folder."""
    from photoreg.cli import main
    from photoreg.runner import run_session

    bad = tmp_path.parent / f"{tmp_path.name}_bad.toml"   # a mesh that does not load: nothing starts
    text = (REPO / "data" / "demo" / "session.toml").read_text()
    bad.write_text(text.replace('path = "."', f'path = "{REPO}/data/demo"').replace('mesh = "object.obj"',
                                                                                   f'mesh = "{bad}"'))
    assert main(["run", str(bad), "--out", str(tmp_path / "never"), "--device", "cpu", "--quiet"]) == 2
    assert not (tmp_path / "never").exists()

    args = ["run", str(REPO / "data" / "demo" / "session.toml"), "--out", str(tmp_path), "--rays", "16", "--stride",
            "8", "--bands", "2", "--device", "cpu", "--quiet"]
    assert main(args + ["--frames", "3:4", "--video", "--no-poses"]) == 0
    earlier = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()}
    assert {"composite/000003.png", "envmap/000003.exr", "lightmap/000003.exr", "composite.mp4",
            "trajectory.txt"} <= earlier
    (tmp_path / "composite" / "notes.txt").write_text("mine")
    (tmp_path / ".complete").write_text("{}")
    capsys.readouterr()
    assert main(args + ["--frames", "0:2"]) == 0
    files = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()}
    assert files == {"lighting.jsonl", "summary.json", "composite/notes.txt", "envmap/000000.exr", "envmap/000000.png",
                     "sphere/000000.png", *(f"{d}/00000{i}.{e}" for i in (0, 1) for d, e in
                                            (("composite", "png"), ("composite_linear", "exr"), ("lightmap", "exr")))}
    assert f"removed {len(earlier)} file(s) an earlier run left in {tmp_path}" in capsys.readouterr().err
    import OpenEXR   # composite_linear in 16-bit floats (a third of float32's write time), the lightmap in float32

    for folder, dtype in (("composite_linear", np.float16), ("lightmap", np.float32)):
        with OpenEXR.File(str(tmp_path / folder / "000001.exr")) as f:
            assert f.channels()["RGB"].pixels.dtype == dtype
    linear = read_exr(tmp_path / "composite_linear" / "000001.exr")
    srgb = read_rgb(tmp_path / "composite" / "000001.png")
    assert np.abs(linear_to_srgb(linear).astype(int) - srgb).max() <= 1

    session = load_session(REPO / "data" / "demo" / "session.toml")
    session.output.dir, session.device, session.frames = str(tmp_path), "cpu", "0:3"
    session.lighting.rays, session.lighting.stride, session.lighting.bands = 16, 8, 2

    def interrupt(done: int, total: int) -> None:   # Ctrl-C after the first frame
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_session(session, quiet=True, on_frame=interrupt)
    files = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()}
    assert files == {"lighting.jsonl.partial", "composite/notes.txt", "envmap/000000.exr", "envmap/000000.png",
                     "sphere/000000.png", "composite/000000.png", "composite_linear/000000.exr", "lightmap/000000.exr"}


def test_a_run_holds_no_composite_past_its_writers(tmp_path, monkeypatch):
    """A run keeps of each frame only what its summary needs: by frame 20 of the demo with its object the composites
    still alive are at most those the file and video writers hold (2 per thread, and 2); before, every frame's result
    was kept to the end, composite and all (0.9 MB a frame at 320x240, 66 GB in 10 minutes at 640x480)."""
    import gc
    import weakref

    import photoreg.pipeline as pipeline_module
    from photoreg.runner import WRITER_THREADS

    alive: list[weakref.ref] = []
    most = [0]
    process = pipeline_module.Pipeline.process

    def watched(self, frame):
        gc.collect()
        most[0] = max(most[0], sum(ref() is not None for ref in alive))
        r = process(self, frame)
        alive.append(weakref.ref(r.composite))
        return r

    monkeypatch.setattr(pipeline_module.Pipeline, "process", watched)
    s = load_session(REPO / "data" / "demo" / "session.toml")
    s.output.dir, s.frames, s.output.pictures_every, s.output.video = str(tmp_path), "0:20", 0, True
    s.device, s.lighting.rays, s.lighting.stride, s.render.light_rays = "cpu", 16, 8, 8
    assert run_session(s, quiet=True)["composites"] == 20
    assert most[0] <= 2 * WRITER_THREADS + 2, most[0]


def test_run_stops_with_the_failed_write_named(tmp_path):
    """A composite folder that cannot be made (a file is in the way): the run raises that path's error, from the
    thread that wrote it."""
    s = load_session(REPO / "data" / "demo" / "session.toml")
    s.output.dir, s.frames, s.output.pictures_every = str(tmp_path), "0:6", 0
    s.lighting.rays, s.lighting.stride = 16, 8
    (tmp_path / "composite").write_text("not a folder")
    with pytest.raises(OSError, match="composite"):
        run_session(s, quiet=True)
    assert (tmp_path / "composite").read_text() == "not a folder"   # nothing written over it


def test_cli_names_the_file_it_cannot_write(tmp_path, capsys):
    """`photoreg run` stops with a one-line error naming the path (exit code 2), not a traceback."""
    from photoreg.cli import main

    (tmp_path / "composite").write_text("not a folder")
    assert main(["run", str(REPO / "data" / "demo" / "session.toml"), "--out", str(tmp_path), "--frames", "0:3",
                 "--rays", "16", "--stride", "8", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "photoreg run: error:" in err and str(tmp_path / "composite") in err and "Traceback" not in err


def test_run_names_the_outputs_it_wrote(tmp_path, capsys):
    """The run's last line lists what is in its folder: no envmap/ or sphere/ with pictures_every = 0, no composites
    without objects (nor the folder an earlier run's composites left, emptied)."""
    from photoreg.cli import main

    (tmp_path / "o" / "composite").mkdir(parents=True)
    (tmp_path / "o" / "composite" / "000000.png").write_bytes(b"an earlier run's")
    session = tmp_path / "s.toml"
    session.write_text(f'[recording]\npath = "{(REPO / "data" / "demo").as_posix()}"\n[output]\npictures_every = 0\n')
    assert main(["run", str(session), "--out", str(tmp_path / "o"), "--frames", "0:1", "--rays", "8", "--bands", "1",
                 "--quiet"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"outputs in {tmp_path / 'o'}: lighting.jsonl, summary.json"


def test_ctrl_c_ends_a_command_without_a_traceback(tmp_path, monkeypatch, capsys):
    """Ctrl-C during any command (here as the run's frames raise it): status 130 and one line, no traceback."""
    from photoreg.cli import main
    from photoreg.pipeline import Pipeline

    def interrupted(self, frame):
        raise KeyboardInterrupt

    monkeypatch.setattr(Pipeline, "process", interrupted)
    assert main(["run", str(REPO / "data" / "demo"), "--frames", "0:2", "--rays", "16", "--quiet", "--out",
                 str(tmp_path)]) == 130
    err = capsys.readouterr().err
    assert "photoreg run: interrupted" in err and "Traceback" not in err


def test_out_of_memory_ends_a_command_with_one_line(tmp_path, monkeypatch, capsys):
    """An allocation that fails (here numpy's, as the frames ask it) ends the command with status 2 and a line that
    points at the settings, not a traceback."""
    from photoreg.cli import main
    from photoreg.pipeline import Pipeline

    def too_large(self, frame):
        return np.zeros(1 << 62, np.uint8)   # 4 EiB: numpy raises MemoryError

    monkeypatch.setattr(Pipeline, "process", too_large)
    assert main(["run", str(REPO / "data" / "demo"), "--frames", "0:1", "--rays", "16", "--quiet", "--out",
                 str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "photoreg run: error: out of memory (Unable to allocate" in err and "Traceback" not in err


def test_read_exr_takes_a_luminance_image_as_grey_and_names_other_channels(tmp_path):
    """An environment map or composite saved as Y alone reads as grey; other channels are named (before: KeyError)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"Y": np.full((4, 5), 0.5, np.float32)}).write(str(tmp_path / "y.exr"))
    assert read_exr(tmp_path / "y.exr").shape == (4, 5, 3) and np.all(read_exr(tmp_path / "y.exr") == 0.5)
    OpenEXR.File(header, {"Z": np.ones((4, 5), np.float32)}).write(str(tmp_path / "z.exr"))
    with pytest.raises(ValueError, match=r"z.exr: EXR channels \['Z'\]: expected R, G and B \(or Y alone\)"):
        read_exr(tmp_path / "z.exr")


def test_a_folder_another_run_writes_is_refused(tmp_path, capsys):
    """Two runs into one output folder at once (a batch and a `photoreg run`, say): the second is refused while the
    first holds it, and touches nothing there (before: it removed the first's files and both wrote one
    lighting.jsonl.partial, the survivor holding a stray fragment that `photoreg score` then refused)."""
    import os

    from photoreg.cli import main
    from photoreg.io.atomic import hold_folder

    out = tmp_path / "out"
    out.mkdir()
    (out / "lighting.jsonl").write_text("the other run's\n")
    args = ["run", str(REPO / "data" / "demo" / "session.toml"), "--out", str(out), "--frames", "0:1", "--rays", "16",
            "--stride", "8", "--bands", "2", "--device", "cpu", "--quiet"]
    fd = hold_folder(out, "test")
    try:
        assert main(args) == 2
        assert f"output folder {out} (--out / [output] dir) is in use by another run" in capsys.readouterr().err
        assert [p.name for p in out.iterdir()] == ["lighting.jsonl"]
        assert (out / "lighting.jsonl").read_text() == "the other run's\n"
    finally:
        os.close(fd)
    assert main(args) == 0 and (out / "summary.json").is_file()

    # held through `after` too (a batch scores the outputs and marks them complete there)
    session = load_session(REPO / "data" / "demo" / "session.toml")
    session.output.dir, session.device, session.frames = str(out), "cpu", "0:1"
    session.lighting.rays, session.lighting.stride, session.lighting.bands = 16, 8, 2
    held = []

    def after(summary):
        with pytest.raises(ValueError, match="is in use by another run"):
            hold_folder(out, "test")
        held.append(summary["frames_processed"])

    run_session(session, quiet=True, after=after)
    assert held == [1]

    # a file system that takes no such lock: the run goes on, warned (before: it failed, naming no folder)
    import errno
    import fcntl

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fcntl, "flock", no_locks)
        assert main(args) == 0
    assert f"output folder {out} (--out / [output] dir) cannot be locked (No locks available)" in \
        capsys.readouterr().err



def test_a_bare_recording_s_default_output_is_named_after_its_folder(tmp_path, monkeypatch):
    """`photoreg run ..` from inside a recording writes out/<the recording's name>, not out/.. (the working folder,
    whose files of an earlier run's names it cleared: a user's trajectory.txt among them)."""
    from photoreg.cli import build_parser
    from photoreg.runner import session_from_args

    (tmp_path / "scene" / "depth").mkdir(parents=True)
    monkeypatch.chdir(tmp_path / "scene" / "depth")
    for given in ("..", "../.", str(tmp_path / "scene")):
        s = session_from_args(build_parser().parse_args(["run", given]))
        assert Path(s.output.dir) == Path("out") / "scene", given
    (tmp_path / "short").symlink_to(tmp_path / "scene")   # a link keeps its own name
    assert Path(session_from_args(build_parser().parse_args(["run", "../../short"])).output.dir) == Path("out/short")
