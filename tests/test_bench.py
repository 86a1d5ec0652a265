"""`photoreg bench sweep` (CSV rows, merge, Pareto front and plot), `photoreg bench speed` on a session, and
the row-split CPU launches (photoreg.kernels.launch) that must give exactly the single launch's output."""
from __future__ import annotations

import csv
import json
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from photoreg.bench import metrics
from photoreg.bench.score import load_gt
from photoreg.bench.sweep import COLUMNS, KEY, STAGES, _floats, _ints, fronts, merge_csv, pareto_front, read_csv
from photoreg.cli import main
from photoreg.config import Session
from photoreg.io.recording import iter_frames, open_recording
from photoreg.kernels.launch import cpu_threads, launch_rows, set_cpu_threads
from photoreg.kernels.raycast import raycast_surface
from photoreg.kernels.transfer import _occlusion, make_direction_set, radiance_transfer
from photoreg.pipeline import Pipeline
from photoreg.recon.fusion import FusionConfig, TSDFVolume
from photoreg.synth.analytic import box_room
from photoreg.synth.cameras import default_intrinsics, look_at
from tests.scenes import write_recording

K80 = default_intrinsics(80, 60, hfov_deg=70.0)


@pytest.fixture(autouse=True)
def default_threads():
    """`--threads` sets a process-wide default: back to the default after each test."""
    yield
    set_cpu_threads(None)


# --- Pareto front -----------------------------------------------------------------------------------

def test_pareto_front_on_hand_made_points():
    #        fps   error
    pts = [(10.0, 5.0),   # 0 front: fastest
           (5.0, 2.0),    # 1 front
           (4.0, 3.0),    # 2 beaten by 1 (slower and worse)
           (10.0, 6.0),   # 3 beaten by 0 (same speed, worse)
           (1.0, 1.0),    # 4 front: most accurate
           (8.0, np.nan),  # 5 no error: never on the front
           (5.0, 2.0),    # 6 a tie with 1: neither beats the other
           (0.5, 1.0)]    # 7 beaten by 4 (same error, slower)
    fps, err = zip(*pts)
    assert pareto_front(fps, err).tolist() == [True, True, False, False, True, False, True, False]
    assert pareto_front([], []).tolist() == []


def test_fronts_per_series_and_merge_keeps_other_rows(tmp_path):
    def row(device, stride, fps, err, name="X", scenes="tabletop"):
        return {"device": device, "device_name": name, "threads": 2 if device == "cpu" else 0, "size": "80x60",
                "scenes": scenes, "frames": "8", "stride": stride, "rays": 16, "bands": 3, "voxel_size": 0.02,
                "frames_per_s": fps, "direction_deg": err, "si_rmse_upper": err / 100}

    path = tmp_path / "t.csv"
    merge_csv(path, [row("cpu", 1, 1.0, 2.0), row("cpu", 2, 3.0, 5.0), row("cpu", 4, 2.0, 6.0)])
    merged = merge_csv(path, [row("cuda:0", 1, 90.0, 2.0, "GPU"), row("cpu", 2, 4.0, 1.0)])  # replaces cpu s2
    assert len(merged) == 4 and [r["stride"] for r in merged if r["device"] == "cpu"] == ["1", "2", "4"]
    with path.open() as f:
        back = list(csv.DictReader(f))
    assert tuple(back[0]) == COLUMNS and back == merged
    f = fronts(merged, "direction_deg")
    assert [r["stride"] for r in f["X (cpu, 2 threads, 80x60, tabletop x 8 frames)"]] == ["2"]  # 4/s at 1 deg wins
    assert [r["frames_per_s"] for r in f["GPU (cuda:0, 80x60, tabletop x 8 frames)"]] == ["90"]
    # another benchmark's row of the same setting is kept beside it, in a series of its own (before: it replaced the
    # tabletop's, and one front compared the two scenes' errors)
    merged = merge_csv(path, [row("cpu", 2, 9.0, 0.5, scenes="corner")])
    assert len(merged) == 5 and [r["stride"] for r in fronts(merged, "direction_deg")[
        "X (cpu, 2 threads, 80x60, corner x 8 frames)"]] == ["2"]
    assert [r["stride"] for r in fronts(merged, "direction_deg")["X (cpu, 2 threads, 80x60, tabletop x 8 frames)"]] \
        == ["2"]
    path.write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="not a speed/error table"):
        merge_csv(path, [row("cpu", 1, 1.0, 2.0)])


# --- the sweep end to end --------------------------------------------------------------------------

def test_sweep_writes_rows_and_plot(tmp_path, capsys):
    """A 2 x 1 x 2 x 1 grid on a tiny analytic recording with exact ground truth (tests/scenes.py), more frames asked
    for than it has."""
    rec = write_recording(tmp_path / "rec", K80, 5)
    csv_path, plot = tmp_path / "out" / "speed_error.csv", tmp_path / "out" / "speed_error.png"
    assert main(["bench", "sweep", "--recordings", str(rec), "--frames", "9", "--warmup", "2", "--strides", "2,4",
                 "--rays", "16", "--bands", "2,3", "--voxel-sizes", "0.02", "--device", "cpu", "--threads", "2",
                 "--csv", str(csv_path), "--plot", str(plot)]) == 0
    with csv_path.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4 and {(r["stride"], r["bands"]) for r in rows} == {("2", "2"), ("2", "3"), ("4", "2"),
                                                                             ("4", "3")}
    assert len({tuple(r[k] for k in KEY) for r in rows}) == 4
    for r in rows:
        assert r["device"] == "cpu" and r["threads"] == "2" and r["size"] == "80x60" and r["frames_timed"] == "3"
        assert r["frames"] == "5"   # the recording's 5 frames, not the 9 asked for
        ms = {s: float(r[f"ms_{s}"]) for s in STAGES}
        assert all(v >= 0 for v in ms.values()) and ms["transfer"] > 0
        assert sum(v for s, v in ms.items() if s != "total") <= ms["total"] + 1e-6
        assert float(r["frames_per_s"]) == pytest.approx(1000.0 / ms["total"], rel=1e-4)
        # a box on a floor (4 normals; tests/test_robust.py: within 35 degrees at 5 bands)
        assert float(r["direction_deg"]) < 40.0 and 0.0 <= float(r["si_rmse_upper"]) < 0.5
    # the sweep's shared volume changes nothing: a plain pipeline run of one setting scores the same
    s = Session()
    s.device, s.lighting.stride, s.lighting.rays, s.lighting.bands = "cpu", 4, 16, 3
    s.reconstruction.voxel_size = 0.02
    recording = open_recording(rec)
    pipe, gt = Pipeline(s, recording.intrinsics), load_gt(rec)
    per = [metrics.lighting_metrics(pipe.process(f).lighting.sh, gt) for f in iter_frames(recording, range(5))]
    row = next(r for r in rows if (r["stride"], r["bands"]) == ("4", "3"))
    assert float(row["direction_deg"]) == pytest.approx(np.median([m["direction_deg"] for m in per]), rel=1e-5)
    assert float(row["si_rmse_upper"]) == pytest.approx(
        np.median([m["irradiance_si_rmse_upper"] for m in per]), rel=1e-5)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and plot.stat().st_size > 20000
    out = capsys.readouterr().out
    assert "Pareto front (direction_deg)" in out and f"wrote {csv_path}" in out
    # GPU rows merged in later (another machine's run): redrawn as a second series
    gpu = {**rows[0], "device": "cuda:0", "device_name": "NVIDIA H100", "threads": "0", "frames_per_s": "120"}
    merge_csv(csv_path, [gpu])
    plot.unlink()
    assert main(["bench", "sweep", "--plot-only", "--csv", str(csv_path), "--plot", str(plot)]) == 0
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "5 rows" in capsys.readouterr().out
    assert set(fronts(read_csv(csv_path), "si_rmse_upper")) == {
        f"{rows[0]['device_name']} (cpu, 2 threads, 80x60, rec x 5 frames)",
        "NVIDIA H100 (cuda:0, 80x60, rec x 5 frames)"}


def test_sweep_option_errors(tmp_path, capsys):
    assert main(["bench", "sweep", "--strides", "2,x", "--csv", str(tmp_path / "a.csv")]) == 2
    assert "--strides" in capsys.readouterr().err
    rec = write_recording(tmp_path / "rec", K80, 2)
    assert main(["bench", "sweep", "--recordings", str(rec), "--frames", "2", "--warmup", "2", "--device", "cpu",
                 "--csv", str(tmp_path / "a.csv"), "--plot", str(tmp_path / "a.png")]) == 2
    assert "warm-up" in capsys.readouterr().err
    # the outputs and the table the rows merge into are checked before any work (a sweep may take hours)
    sweep = ["bench", "sweep", "--recordings", str(rec), "--frames", "2", "--device", "cpu"]
    (tmp_path / "folder").mkdir()
    assert main(sweep + ["--csv", str(tmp_path / "folder"), "--plot", str(tmp_path / "a.png")]) == 2
    assert f"{tmp_path / 'folder'} (--csv) is a folder, not a file" in capsys.readouterr().err
    (tmp_path / "cut.csv").write_text("device,device_name,threads,size,scenes,frames,voxel_size,stride,rays,bands\n"
                                      "cpu,x,1,8x6,")
    assert main(sweep + ["--csv", str(tmp_path / "cut.csv"), "--plot", str(tmp_path / "a.png")]) == 2
    assert f"{tmp_path / 'cut.csv'}:2: not a whole row of a speed/error table" in capsys.readouterr().err
    assert main(["bench", "speed", str(rec), "--json", str(tmp_path / "cut.csv" / "x.json")]) == 2
    assert f"(--json): {tmp_path / 'cut.csv'} is a file, not a folder" in capsys.readouterr().err
    index = next(p for p in sorted(Path(rec).iterdir()) if p.suffix == ".txt")   # an input of the run: refused
    kept = index.read_bytes()
    assert main(["bench", "speed", str(rec), "--json", str(index)]) == 2
    assert f"{index} (--json) is the input's file" in capsys.readouterr().err and index.read_bytes() == kept
    # every setting of the grid checked before a scene is rendered (before: after, and without naming the options)
    scenes = tmp_path / "scenes"
    assert main(["bench", "sweep", "--scenes", "plane", "--size", "32x24", "--frames", "3", "--spp", "1",
                 "--synth-dir", str(scenes), "--strides", "4", "--rays", "16", "--bands", "3,40", "--csv",
                 str(tmp_path / "b.csv"), "--plot", str(tmp_path / "b.png")]) == 2
    err = capsys.readouterr().err
    assert "--strides / --rays / --bands / --voxel-sizes: the setting s4 r16 b40 v0.01: " in err
    assert "lighting.bands must be in 1..8" in err and not scenes.exists()
    # scene kinds and the warm-up checked before a scene is rendered (before: 'plane' rendered, then 'bogus' refused)
    common = ["--size", "32x24", "--frames", "3", "--spp", "1", "--synth-dir", str(scenes), "--csv",
              str(tmp_path / "b.csv"), "--plot", str(tmp_path / "b.png")]
    assert main(["bench", "sweep", "--scenes", "plane,bogus", *common]) == 2
    assert "--scenes: unknown scene kind(s) 'bogus'" in capsys.readouterr().err and not scenes.exists()
    assert main(["bench", "sweep", "--scenes", "plane", "--warmup", "-1", *common]) == 2
    assert "--warmup must be >= 0, got -1" in capsys.readouterr().err and not scenes.exists()
    assert _ints("8,8,4", "strides") == [8, 4] and _floats("0.02,0.020", "voxel-sizes") == [0.02]   # each once


def test_an_interrupted_sweep_keeps_the_voxel_sizes_it_finished(tmp_path, monkeypatch):
    """Ctrl-C during the second voxel size: the first one's rows are in the CSV already (before: nothing was kept of
    an hour's sweep). The sweep's work stands in for run_sweep here; the whole sweep runs in the test above."""
    import photoreg.bench.sweep as sweep

    def fake(recordings, settings, **kwargs):
        if settings[0].voxel_size == 0.03:
            raise KeyboardInterrupt
        return [{"device": "cpu", "device_name": "X", "threads": 2, "size": "80x60", "scenes": "rec", "frames": "5",
                 "stride": st.stride, "rays": st.rays, "bands": st.bands, "voxel_size": st.voxel_size,
                 "frames_per_s": 1.0, "direction_deg": 1.0, "si_rmse_upper": 0.1} for st in settings]

    monkeypatch.setattr(sweep, "run_sweep", fake)
    rec = write_recording(tmp_path / "rec", K80, 3)
    csv_path = tmp_path / "t.csv"
    with pytest.raises(KeyboardInterrupt):
        sweep.sweep_command(SimpleNamespace(plot_only=False, csv=str(csv_path), plot=str(tmp_path / "p.png"),
                                            threads=None, warmup=0, recordings=[str(rec)], scenes="", strides="4,8",
                                            rays="16", bands="3", voxel_sizes="0.02,0.03", device="cpu", frames=3))
    assert sorted((r["stride"], r["voxel_size"]) for r in read_csv(csv_path)) == [("4", "0.02"), ("8", "0.02")]


# --- row-split CPU launches ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def room_grid():
    scene, intr = box_room(), default_intrinsics(160, 120, hfov_deg=70.0)
    poses = [look_at([-0.6, 0.0, 1.4], [0.8, 0.1, 0.1]), look_at([0.1, -0.3, 1.5], [0.0, 0.0, 0.0]),
             look_at([0.0, 0.2, 1.3], [0.7, -0.7, 0.2])]
    vol = TSDFVolume(FusionConfig(voxel_size=0.02), "cpu")
    for p in poses:
        vol.integrate(scene.render_depth(intr, p)[0], intr, p)
    return vol.dense_grid(), intr, poses


@pytest.mark.parametrize("threads", [2, 3, 7])
def test_split_launches_equal_the_single_launch(room_grid, threads):
    grid, intr, poses = room_grid
    dirs, Y = make_direction_set(16, 3, seed=0)

    def run(n):
        maps = raycast_surface(grid, intr, poses[0], 0.1, 4.0, threads=n)
        tr = radiance_transfer(grid, maps.vertex_wp, maps.normal_wp, dirs, Y, offset=0.02, ray_length=0.5,
                               virtual=grid, threads=n, hit_distances=True)  # the grid as its own 'virtual' layer
        return maps, tr

    (m1, t1), (mn, tn) = run(1), run(threads)
    assert m1.valid.mean() > 0.5 and 0.2 < t1.visible_fraction[m1.valid.ravel()].mean() < 1.0
    for a, b in [(m1.depth, mn.depth), (m1.vertex, mn.vertex), (m1.normal, mn.normal), (t1.transfer, tn.transfer),
                 (t1.visible_fraction, tn.visible_fraction), (t1.occlusion_wp.numpy(), tn.occlusion_wp.numpy()),
                 (t1.transfer_rv, tn.transfer_rv), (t1.visible_fraction_rv, tn.visible_fraction_rv),
                 (t1.hit_distance_wp.numpy(), tn.hit_distance_wp.numpy())]:
        np.testing.assert_array_equal(a, b)


def test_thread_settings(monkeypatch):
    monkeypatch.setenv("PHOTOREG_CPU_THREADS", "3")
    assert cpu_threads() == 3
    set_cpu_threads(5)
    try:
        assert cpu_threads() == 5
    finally:
        set_cpu_threads(None)
    monkeypatch.setenv("PHOTOREG_CPU_THREADS", "zero")
    with pytest.raises(ValueError, match="PHOTOREG_CPU_THREADS"):
        cpu_threads()
    with pytest.raises(ValueError, match="threads"):
        set_cpu_threads(0)
    with pytest.raises(ValueError, match="threads"):
        launch_rows(_occlusion, (4, 4), [], [], "cpu", threads=0)


def test_bench_speed_times_the_render_stage_of_a_session(tmp_path, capsys):
    """`photoreg bench speed` on a session file inserts its objects and times the render stage (R_TRV, G-buffer,
    composite) with the rest; on the recording alone there is no render stage (that run also without the
    observed bounce: --no-observed-bounce reaches the session and the figures say so; with --async: the
    estimates collected and the lighting's age in frames are reported; and with --no-poses: the camera tracked, its
    pose stage timed)."""
    demo = Path(__file__).resolve().parents[1] / "data" / "demo"
    for src, name in ((demo / "session.toml", "session"), (demo, "recording")):
        out = tmp_path / f"{name}.json"
        off = ["--no-observed-bounce", "--async", "--no-poses"] if name == "recording" else []
        assert main(["bench", "speed", str(src), "--device", "cpu", "--frames", "0:3", "--warmup", "1",
                     "--rays", "16", "--json", str(out)] + off) == 0
        res = json.loads(out.read_text())
        assert res["bounce"] and res["bounce_observed"] == (name == "session")
        assert res["asynchronous"] == res["tracked"] == (name == "recording")
        assert (res["ms_mean"]["pose"] > 1.0) == (name == "recording")   # an alignment, against a matrix handed on
        if name == "session":   # every frame estimated in line: its own lighting
            assert res["estimates"] == 2 and res["lag_frames_mean"] == 0
        else:                   # the timed frames hold frame 0's in-line estimate or a later one of the worker
            assert 1 <= res["estimates"] <= 2 and 0 < res["lag_frames_mean"] <= 2
        if name == "session":
            assert res["objects"] == 1 and res["shadows"] == "voxel" and res["ms_mean"]["render"] > 0
        else:
            assert res["objects"] == 0 and res["shadows"] is None and "render" not in res["ms_mean"]
        assert res["frames_timed"] == 2 and res["frames_per_s"] > 0
        # the BLAS threads this process runs with (photoreg set them at import), in the JSON and the printed line
        assert res["blas_threads"] == os.environ["OPENBLAS_NUM_THREADS"]
        assert f"BLAS threads {res['blas_threads']})" in capsys.readouterr().out


def test_bench_speed_tracks_a_recording_without_poses(tmp_path, capsys):
    """A recording without poses is timed with the camera tracked, as `photoreg run` processes it (before: no frame
    was fused or lit, and the benchmark printed thousands of frames/s); a selection past its end and a negative
    warm-up are refused by name."""
    rec = write_recording(tmp_path / "rec", K80, 4, with_gt=False)
    (rec / "groundtruth.txt").unlink()
    out = tmp_path / "figures.json"
    assert main(["bench", "speed", str(rec), "--device", "cpu", "--frames", "0:4", "--warmup", "1", "--rays", "16",
                 "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert "has no poses: tracking the camera instead" in capsys.readouterr().err
    assert res["tracked"] and res["ms_mean"]["fuse"] > 0 and res["ms_mean"]["solve"] > 0
    assert main(["bench", "speed", str(rec), "--device", "cpu", "--frames", "10:20"]) == 2
    assert "no frames selected (recording has 4, --frames '10:20')" in capsys.readouterr().err
    assert main(["bench", "speed", str(rec), "--device", "cpu", "--warmup", "-3"]) == 2
    assert "--warmup must be >= 0, got -3" in capsys.readouterr().err


def test_bench_speed_keeps_the_session_s_settings_but_the_options_given(tmp_path):
    """A session's own lighting settings and frames are what `photoreg bench speed` times, each replaced only by an
    option given (before, the options' defaults, stride 4 / 64 rays / 3 bands, every frame, the traced light, frames
    0:12, replaced them silently)."""
    demo = Path(__file__).resolve().parents[1] / "data" / "demo"
    session = tmp_path / "s.toml"
    session.write_text(f'frames = "0:3"\ndevice = "cpu"\n[recording]\npath = "{demo}"\n[lighting]\nstride = 8\n'
                       'rays = 16\nbands = 2\nevery = 2\nsun = false\n')
    out = tmp_path / "figures.json"
    for extra, expected in (([], (8, 16, 2, 2, False)), (["--rays", "32", "--bands", "3"], (8, 32, 3, 2, False))):
        assert main(["bench", "speed", str(session), "--warmup", "1", "--json", str(out), *extra]) == 0
        res = json.loads(out.read_text())
        assert (res["stride"], res["rays"], res["bands"], res["every"], res["sun"]) == expected
        assert res["frames_timed"] == 2 and res["device"] == "cpu"

