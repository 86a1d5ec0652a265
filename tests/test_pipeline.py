"""End-to-end runs of the per-frame pipeline on the demo and the shared real recordings."""
from __future__ import annotations

import dataclasses
import json
import multiprocessing
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

import photoreg.pipeline as pipeline_module
from photoreg.cli import main
from photoreg.config import LightingConfig, Session, load_session, validate
from photoreg.device import init_warp
from photoreg.io.images import linear_to_srgb, srgb_to_linear
from photoreg.lighting.sh import LUMINANCE
from photoreg.io.recording import iter_frames, open_recording
from photoreg.preprocess import prepare, strided_box
from photoreg.runner import run_session
from photoreg.types import Frame, Intrinsics
from scenes import write_recording

REPO = Path(__file__).resolve().parents[1]


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def finite_records(records: list[dict]) -> bool:
    return all(np.all(np.isfinite(np.array(r["sh"], dtype=float))) for r in records)


def test_demo_run_writes_every_output(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--frames", "0:4", "--rays", "16", "--quiet"]) == 0
    records = read_jsonl(out / "lighting.jsonl")
    assert [r["frame"] for r in records] == [0, 1, 2, 3]
    assert finite_records(records)
    r = records[0]
    bands = LightingConfig().bands
    assert r["bands"] == bands and np.array(r["sh"]).shape == (3, bands * bands)
    assert {"preprocess", "fuse", "raycast", "transfer", "solve", "total"} <= set(r["timings_ms"])
    assert r["diagnostics"]["n_samples"] > 100
    assert not (out / "lighting.jsonl.partial").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_processed"] == 4 and summary["device"] == "cpu"
    assert (out / "envmap" / "000000.png").is_file() and (out / "envmap" / "000000.exr").is_file()
    assert (out / "sphere" / "000000.png").is_file()


def test_session_overrides_and_bad_options(tmp_path, capsys):
    s = load_session(REPO / "data" / "demo" / "session.toml")
    assert Path(s.recording.path) == (REPO / "data" / "demo").resolve()
    assert main(["run", str(REPO / "data" / "demo"), "--bands", "0", "--out", str(tmp_path)]) == 2
    assert main(["run", str(tmp_path / "missing"), "--out", str(tmp_path)]) == 2
    bad = tmp_path / "bad.toml"
    where = REPO / "data" / "demo"                                    # its paths made absolute: bad.toml is elsewhere
    demo = (where / "session.toml").read_text().replace('path = "."', f'path = "{where}"').replace(
        'mesh = "object.obj"', f'mesh = "{where / "object.obj"}"')
    bad.write_text(demo.replace("[render]", '[render]\ngbuffer = "optix"'))
    with pytest.raises(ValueError, match=r"render\.gbuffer.*raycast"):
        load_session(bad)
    albedo = re.search(r"^albedo = .*$", demo, re.M).group(0)          # the object's: a colour, "texture" or an error
    bad.write_text(demo.replace(albedo, 'albedo = "texture"'))
    assert load_session(bad).objects[0].albedo == "texture"
    for value, message in (('"wood"', r"objects\[0\]\.albedo must be 3 finite numbers or 'texture'"),
                           ("3", r"objects\[0\]\.albedo' must be list or str"),
                           ("[true, 0.5, 0.5]", r"objects\[0\]\.albedo must be 3 finite numbers")):   # not 1.0
        bad.write_text(demo.replace(albedo, f"albedo = {value}"))
        with pytest.raises(ValueError, match=message):
            load_session(bad)
    with pytest.raises(ValueError, match=re.escape(f"{where}: a folder, not a session file (.toml)")):
        load_session(where)                                            # (photoreg train takes session files alone)
    bad.write_text(demo.replace(f'path = "{where}"', 'path = "${PHOTOREG_NO_SUCH_VARIABLE}/demo"'))
    with pytest.raises(ValueError, match=re.escape(f"{bad}: recording.path '${{PHOTOREG_NO_SUCH_VARIABLE}}/demo': "
                                                   "environment variable PHOTOREG_NO_SUCH_VARIABLE is not set")):
        load_session(bad)
    priced = tmp_path / "price$5"   # $$: a $ of the name itself (was 'environment variable 5 is not set')
    shutil.copytree(where, priced)
    bad.write_text(demo.replace(f'path = "{where}"', f'path = "{str(priced).replace("$", "$$")}"'))
    assert load_session(bad).recording.path == str(priced)
    bad.write_text('device = "gpu"\n' + demo)
    with pytest.raises(ValueError, match=f"{re.escape(str(bad))}: key 'device' must be one of"):   # not '.device'
        load_session(bad)
    if not init_warp().is_cuda_available():   # a session's device names the session, not the CLI flag alone
        bad.write_text('device = "cuda"\n' + demo)
        assert main(["run", str(bad), "--out", str(tmp_path / "o")]) == 2
        assert "device cuda asked for (--device, a session's device), but Warp finds no CUDA" in \
            capsys.readouterr().err
    upper = tmp_path / "demo.TOML"   # a session file whatever the suffix's case
    upper.write_text(demo)
    assert main(["run", str(upper), "--frames", "0:1", "--rays", "8", "--bands", "1", "--out", str(tmp_path / "o"),
                 "--quiet"]) == 0


def test_frame_selection_and_its_override(tmp_path):
    """--frames: N first N, A:B and A:B:S end exclusive and clipped, ':' every frame, also over a session file's own
    selection; bad specs are errors naming the option."""
    from photoreg.cli import build_parser
    from photoreg.config import parse_frames
    from photoreg.runner import session_from_args

    assert parse_frames("3", 10) == [0, 1, 2] and parse_frames("20", 4) == [0, 1, 2, 3]
    assert parse_frames("2:5", 10) == [2, 3, 4] and parse_frames("1:9:3", 6) == [1, 4]
    assert parse_frames(":", 4) == parse_frames("", 4) == [0, 1, 2, 3] and parse_frames("8:", 4) == []
    for bad in ("a", "1:2:0", "-1:3", "1:2:3:4"):
        with pytest.raises(ValueError, match="--frames"):
            parse_frames(bad, 10)
    session = tmp_path / "s.toml"
    demo = (REPO / "data" / "demo").as_posix()
    session.write_text(f'frames = "0:2"\n[recording]\npath = "{demo}"\n')
    for given, frames in ((None, "0:2"), (":", ":")):
        args = build_parser().parse_args(["run", str(session)] + (["--frames", given] if given else []))
        assert session_from_args(args).frames == frames


@pytest.mark.slow
@pytest.mark.parametrize("name", ["tum_fr1_rpy", "iclnuim_livingroom1"])
def test_real_recordings_give_finite_lighting_for_every_frame(data_dir, tmp_path, name):
    from photoreg.runner import session_from_args
    from photoreg.cli import build_parser

    args = build_parser().parse_args(["run", str(data_dir / "recordings" / name), "--out", str(tmp_path),
                                      "--stride", "8", "--rays", "16", "--quiet"])
    s = session_from_args(args)
    s.output.pictures_every = 0
    summary = run_session(s, quiet=True)
    records = read_jsonl(tmp_path / "lighting.jsonl")
    n = {"tum_fr1_rpy": 100, "iclnuim_livingroom1": 211}[name]
    assert summary["frames_processed"] == len(records) == n and not summary["frames_skipped"]
    assert finite_records(records)
    assert all(r["diagnostics"]["n_samples"] > 0 for r in records)


def test_lighting_every_holds_the_estimate_between_estimates(tmp_path, monkeypatch):
    """lighting.every = 3: frames 0 and 3 are solved, the frames between hold the latest estimate exactly (no
    transfer, no solve) with their own exposure gain: frame 4, exposed at half the linear radiance, gets 0.5 (the
    exposure its composite is made in)."""
    k = Intrinsics(64, 48, 56.0, 56.0, 31.5, 23.5, 5000.0)
    rec = open_recording(write_recording(tmp_path / "rec", k, 6, with_gt=False))
    solved, solve = [], pipeline_module.solve

    def counted(*args, **kwargs):
        solved.append(True)
        return solve(*args, **kwargs)

    monkeypatch.setattr(pipeline_module, "solve", counted)
    s = Session(device="cpu")
    s.lighting.rays, s.lighting.stride, s.lighting.sun, s.lighting.every = 16, 2, False, 3
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    results, calls = [], []
    for frame in iter_frames(rec, range(6)):
        if frame.index == 4:
            frame = dataclasses.replace(frame, color=linear_to_srgb(0.5 * srgb_to_linear(frame.color)))
        results.append(pipe.process(frame))
        calls.append(len(solved))
    assert calls == [1, 1, 1, 2, 2, 2], calls
    for r in results:
        held = r.index % 3 != 0
        source = results[r.index - r.index % 3]
        assert ("solve" in r.timings_ms, "transfer" in r.timings_ms) == (not held, not held)
        if held:
            assert np.array_equal(r.lighting.sh, source.lighting.sh)
            assert r.diagnostics.notes[0] == f"lighting of frame {source.index} held (lighting.every = 3)"
            assert r.diagnostics.bands == source.diagnostics.bands
    assert not np.array_equal(results[3].lighting.sh, results[0].lighting.sh)
    gains = [r.diagnostics.exposure_gain for r in results]
    assert abs(gains[4] - 0.5) < 0.1 and all(abs(g - 1) < 0.1 for i, g in enumerate(gains) if i != 4), gains
    # a first frame black: its estimate had no samples, so the next frame estimates again (was held, zero lighting,
    # over the good frames until the next due one)
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    black = pipe.process(dataclasses.replace(rec.frame(0), color=np.zeros_like(rec.frame(0).color)))
    after = pipe.process(rec.frame(1))
    assert black.diagnostics.n_samples == 0 and black.diagnostics.weak
    assert "solve" in after.timings_ms and after.diagnostics.n_samples > 0 and np.abs(after.lighting.sh).sum() > 0
    s.lighting.every = 0
    with pytest.raises(ValueError, match="lighting.every"):
        validate(s)


def test_a_lighting_record_is_strict_json(tmp_path):
    """lighting.jsonl's record (runner.result_record, a stream's lighting reply too) holds no NaN or Infinity token:
    a non-finite number becomes null (json.dumps wrote NaN, which strict readers refuse)."""
    from photoreg.runner import result_record

    k = Intrinsics(64, 48, 56.0, 56.0, 31.5, 23.5, 5000.0)
    rec = open_recording(write_recording(tmp_path / "rec", k, 1, with_gt=False))
    s = Session(device="cpu")
    s.lighting.rays, s.lighting.stride, s.lighting.bands = 16, 4, 2
    r = pipeline_module.Pipeline(s, rec.intrinsics).process(rec.frame(0))
    r.timings_ms["solve"], r.diagnostics.residual_rms = float("nan"), float("inf")
    record = json.loads(json.dumps(result_record(r), allow_nan=False))
    assert record["timings_ms"]["solve"] is None and record["diagnostics"]["residual_rms"] is None


def test_held_frames_ray_cast_coarser_only_where_the_gain_keeps_its_samples():
    """A held frame with no render stage ray casts only for its exposure gain: at 640x480 and stride 1 at stride 4
    (19200 pixels for 2000 samples), never finer than the lighting's stride, and on a 64x48 frame at its own."""
    for (w, h), stride, expected in (((640, 480), 1, 4), ((640, 480), 2, 4), ((640, 480), 8, 8), ((64, 48), 2, 2),
                                     ((64, 48), 1, 1)):
        s = Session(device="cpu")
        s.lighting.stride = stride
        k = Intrinsics(w, h, 0.9 * w, 0.9 * w, w / 2 - 0.5, h / 2 - 0.5, 5000.0)
        assert pipeline_module.Pipeline(s, k)._gain_stride() == expected, (w, stride)


def test_render_stride_is_the_shadows_own(tmp_path, monkeypatch):
    """render.stride, not lighting.stride, sets where the renderer samples the shadow ratio: the stage, given the
    frame's maps at another stride, ray casts its own, and its composite is the one made from maps cast at its
    stride; a frame that holds the lighting ray casts once, at the render stride, unless its exposure gain needs
    finer maps (no maps at the lighting's finer stride that nothing reads)."""
    import photoreg.render.stage as stage_module
    import trimesh

    from photoreg.config import ObjectConfig
    from photoreg.kernels.raycast import raycast_surface

    k = Intrinsics(64, 48, 56.0, 56.0, 31.5, 23.5, 5000.0)
    rec = open_recording(write_recording(tmp_path / "rec", k, 3, with_gt=False))
    trimesh.creation.box(extents=(1, 1, 1)).export(tmp_path / "cube.obj")
    s = Session(device="cpu")
    s.lighting.rays, s.lighting.stride, s.lighting.sun, s.lighting.every = 16, 1, False, 2
    s.objects = [ObjectConfig(mesh=str(tmp_path / "cube.obj"), position=[0.3, -0.2, 0.05], scale=0.1)]
    s.render.stride = 2
    casts = []

    def counted(grid, intr, pose, *args, stride=1, **kwargs):
        casts.append((intr.width, stride))
        return raycast_surface(grid, intr, pose, *args, stride=stride, **kwargs)

    monkeypatch.setattr(pipeline_module, "raycast_surface", counted)
    monkeypatch.setattr(stage_module, "raycast_surface", counted)
    frames = list(iter_frames(rec, range(3)))
    for exposure, held in ((False, [(64, 2)]), (True, [(64, 1), (64, 2)])):   # a 64 x 48 frame's gain needs stride 1
        s.lighting.exposure = exposure
        pipe = pipeline_module.Pipeline(s, rec.intrinsics)
        for f in frames:
            casts.clear()
            r = pipe.process(f)
            assert pipe.render.last_input.maps.stride == 2 and r.composite is not None
            full = [c for c in casts if c[0] == k.width]   # the stage's window casts are narrower
            assert full == ([(64, 1), (64, 2)] if f.index != 1 else held), (exposure, f.index, casts)   # 1 holds
    inp, rc = pipe.render.last_input, s.reconstruction
    prep, pose = prepare(frames[2], s.lighting, rc), frames[2].pose
    own = {st: raycast_surface(inp.grid, k, pose, rc.depth_min, rc.depth_max, stride=st) for st in (1, 2)}
    a = pipe.render(prep.linear, prep.depth, inp.grid, own[1], pose, inp.F, inp.gain, inp.sun)
    b = pipe.render(prep.linear, prep.depth, inp.grid, own[2], pose, inp.F, inp.gain, inp.sun)
    assert np.array_equal(a, b) and (pipe.render.last.ratio < 0.99).any()
    s.render.stride = 0
    with pytest.raises(ValueError, match="render.stride"):
        validate(s)


def test_the_renderer_s_notes_reach_the_frame_s_diagnostics():
    """One SH band and no traced light: no directional light for the shadow map, which draws no shadow and says why;
    the note reaches the frame's diagnostics (lighting.jsonl), not only the Python API."""
    s = load_session(REPO / "data" / "demo" / "session.toml")
    s.device, s.render.shadows, s.lighting.bands, s.lighting.rays, s.lighting.stride = "cpu", "shadowmap", 1, 8, 8
    s.lighting.sun = False
    rec = open_recording(s.recording.path)
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    r = pipe.process(rec.frame(0))
    assert "render: shadowmap: no directional light in F, no shadows" in r.diagnostics.notes, r.diagnostics.notes
    pipe.close()


def test_white_mode_stays_one_colour_through_the_filter():
    """lighting.mode = "white": one colour times a luminance SH in every frame, the temporal filter's too (it weighs
    the channels apart: before, the channels' ratios spread by up to 0.96 across the coefficients from frame 1 on)."""
    s = load_session(REPO / "data" / "demo" / "session.toml")
    s.objects, s.device, s.lighting.mode, s.lighting.rays, s.lighting.stride = [], "cpu", "white", 16, 8
    rec = open_recording(s.recording.path)
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    for frame in iter_frames(rec, range(4)):
        F = pipe.process(frame).lighting.sh
        lum = LUMINANCE @ F
        big = np.abs(lum) > 1e-3 * np.abs(lum).max()
        ratios = F[:, big] / lum[big]
        assert np.ptp(ratios, axis=1).max() < 1e-9, (frame.index, ratios)
    pipe.close()


def test_order_selection_says_it_turns_the_light_and_the_bounce_off(capsys):
    """lighting.select other than "fixed" compares SH models alone: the traced light and the bounce term are off, and
    the pipeline says so (before, silently)."""
    s = Session(device="cpu")
    s.lighting.select = "gcv"
    pipe = pipeline_module.Pipeline(s, Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5))
    assert pipe.sun is None and not pipe.bounce
    assert "lighting.select = 'gcv' compares SH models alone: the traced light" in capsys.readouterr().err
    pipe.close()


@pytest.mark.parametrize("section, key, value, message", [
    ("lighting", "process_noise", float("inf"), "lighting.process_noise must be a finite number, got inf"),
    ("lighting", "regularization", float("nan"), "lighting.regularization must be a finite number"),
    ("reconstruction", "depth_max", float("inf"), "reconstruction.depth_max must be a finite number"),
    ("lighting", "reference_albedo", 1e-300, "lighting.reference_albedo must be in [0.01, 1]"),
    ("lighting", "ray_offset_voxels", -1.0, "lighting.ray_offset_voxels must be >= 0"),
    ("lighting", "saturation_level", 300, "lighting.black_level and saturation_level must be 8-bit levels"),
    ("lighting", "black_level", 250, "lighting.black_level and saturation_level must be 8-bit levels"),
    ("lighting", "sun_candidates", 0, "lighting.sun_candidates must be >= 8"),
    ("lighting", "stride", 100, "lighting.stride must be in 1..64"),
    ("lighting", "rays", 8, "lighting.rays must be >= 13 for 5 bands (25 coefficients; the transfer vectors span at "
                            "most 2 x rays directions)"),   # each frame was rank deficient, flagged weak
    ("reconstruction", "trunc_voxels", 0.0, "reconstruction.trunc_voxels must be > 0"),
    ("reconstruction", "block_count", -5, "reconstruction.block_count must be in 1..1048576"),
    ("reconstruction", "block_count", 2 ** 63 - 1, "reconstruction.block_count must be in 1..1048576"),   # malloc
    ("lighting", "rays", 100_000_000, "lighting.rays must be in 1..4096"),   # 37 GB at once: a MemoryError
    ("output", "pictures_every", -1, "output.pictures_every must be >= 0"),
    (None, "frames", "0:4:0", "frames (--frames): expected N, A:B or A:B:S with numbers >= 0 and S >= 1"),
])
def test_settings_out_of_range_are_named(section, key, value, message):
    """Every setting is checked before a frame runs (NaN and infinities included), the message naming it."""
    s = Session()
    setattr(s if section is None else getattr(s, section), key, value)
    s.source = "my.toml"
    with pytest.raises(ValueError, match=re.escape(f"my.toml: {message}")):
        validate(s)


def test_a_frame_with_a_far_off_pose_is_left_out(tmp_path):
    """A recorded pose 1 km off (a tracking glitch) would stretch the volume past its limit: that frame is neither
    fused nor lit (weak, previous estimate, no pose), its note names it, and the frames after it go on as before.
    Where the wrong pose is the first one, the volume starts again at the third right frame in a row, named too."""
    k = Intrinsics(80, 60, 70.0, 70.0, 39.5, 29.5, 5000.0)
    rec = open_recording(write_recording(tmp_path / "rec", k, 5))
    s = Session()
    s.device, s.lighting.rays, s.lighting.bands, s.lighting.stride = "cpu", 16, 2, 2
    s.reconstruction.voxel_size = 0.02

    def run(far: int):
        pipe = pipeline_module.Pipeline(s, k)
        results = []
        for frame in iter_frames(rec):
            if frame.index == far:
                frame.pose = frame.pose.copy()
                frame.pose[:3, 3] += 1000.0
            results.append(pipe.process(frame))
        return pipe, results

    first_pipe, first = run(0)
    assert [r.pose is None for r in first] == [False, True, True, False, False]
    assert any(n.startswith("frame 3: the fused volume started again from this frame (3 frames in a row")
               for n in first[3].diagnostics.notes), first[3].diagnostics.notes
    assert first_pipe.volume.restarts == 1 and not first[4].diagnostics.weak
    pipe, results = run(2)
    bad = results[2]
    assert bad.pose is None and bad.diagnostics.weak and np.array_equal(bad.lighting.sh, results[1].lighting.sh)
    assert any(n.startswith("frame 2: dense SDF brick would need") and "was not fused" in n
               for n in bad.diagnostics.notes), bad.diagnostics.notes
    assert pipe.volume.frames_integrated == 4 and results[3].pose is not None and not results[3].diagnostics.weak
    assert all(np.all(np.isfinite(r.lighting.sh)) for r in results)


def test_the_renderers_draw_the_traced_light_filtered():
    """The demo holds a traced light from frame 0: its irradiance in diagnostics.sun, which the renderers draw, is the
    filtered one (LightingFilter.irradiance), "irradiance_frame" the frame's own solve's; over 10 frames the first
    moves several times less from frame to frame (measured over the demo's 40: 0.5% against 2.3% a frame)."""
    s = load_session(REPO / "data" / "demo" / "session.toml")
    s.device, s.lighting.rays = "cpu", 64
    rec = open_recording(s.recording.path, fmt=s.recording.format)
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    drawn, own = [], []
    for frame in iter_frames(rec, range(10)):
        sun = pipe.process(frame).diagnostics.sun
        drawn.append(sun["irradiance"])
        own.append(sun["irradiance_frame"])
        assert pipe.render.last_input.sun["irradiance"] == sun["irradiance"]
    assert drawn[0] == own[0]
    step = lambda e: np.abs(np.diff(np.asarray(e), axis=0)).mean()   # noqa: E731
    assert step(drawn) < 0.4 * step(own), (step(drawn), step(own))


def _demo_lighting(frames: int, change=None, history: int | None = None) -> list:
    """The demo's first `frames` frames through its session's pipeline without its object, frame i changed by
    change(i, frame) where given, with lighting.history = `history` where given; their FrameResults."""
    s = load_session(REPO / "data" / "demo" / "session.toml")
    s.device, s.objects = "cpu", []
    if history is not None:
        s.lighting.history = history
    rec = open_recording(s.recording.path, fmt=s.recording.format)
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    try:
        return [pipe.process(change(f.index, f) if change else f) for f in iter_frames(rec, range(frames))]
    finally:
        pipe.close()


def test_a_pipeline_in_a_user_s_code_checks_its_inputs_and_keeps_its_state_its_own():
    """photoreg as a library: the session is checked as a file's is and copied (changed afterwards, nothing changes);
    a result's arrays are the caller's (editing them in place scaled later frames' lighting 100 times); frames whose
    intrinsics, shutter or depth cannot be right are refused by name (before: used silently, or a Warp or numpy
    traceback); a closed pipeline processes nothing."""
    def session(**lighting) -> Session:
        s = load_session(REPO / "data" / "demo" / "session.toml")
        s.device, s.objects = "cpu", []
        s.lighting.stride, s.lighting.rays, s.lighting.bands = 8, 16, 3
        for key, value in lighting.items():
            setattr(s.lighting, key, value)
        return s

    rec = open_recording(REPO / "data" / "demo")
    f0, f1 = rec.frame(0), rec.frame(1)
    expected = pipeline_module.Pipeline(session(), rec.intrinsics)
    expected.process(f0)
    want = expected.process(f1).lighting.sh
    s = session()
    s.recording.path, s.output.dir = REPO / "data" / "demo", REPO / "out"   # paths as a user's code has them
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    s.lighting.bands = 5                                   # the pipeline's copy is not this
    r0 = pipe.process(f0)
    r0.lighting.sh *= 100.0
    r0.pose[:3, 3] += 1.0
    np.testing.assert_array_equal(pipe.process(f1).lighting.sh, want)
    assert pipe.session.lighting.bands == 3 and not np.array_equal(f0.pose, r0.pose)
    for bad, says in (({"stride": 8.0}, "key 'lighting.stride' must be int, got 8.0"),
                      ({"denoise": "guide"}, "key 'lighting.denoise' must be one of")):
        with pytest.raises(ValueError, match=re.escape(says)):
            pipeline_module.Pipeline(session(**bad), rec.intrinsics)
    painted = load_session(REPO / "data" / "demo" / "session.toml")
    painted.device, painted.objects[0].albedo = "cpu", [200, 200, 200]   # 8-bit, not a reflectance
    with pytest.raises(ValueError, match=re.escape("objects[0].albedo must be reflectances in 0..1")):
        pipeline_module.Pipeline(painted, rec.intrinsics)
    zoomed = dataclasses.replace(f1.intrinsics, fx=2 * f1.intrinsics.fx)
    for bad, says in ((dataclasses.replace(f1, intrinsics=zoomed), "are not the pipeline's"),
                      (dataclasses.replace(f1, shutter=16.0), "frame 1: shutter must be seconds in 0..1"),
                      (dataclasses.replace(f1, depth=(f1.depth * 1000).astype(np.uint16)),
                       "depth is uint16 of shape (240, 320), expected HxW float metres"),
                      (dataclasses.replace(f1, depth=f1.depth[..., None]), "expected HxW float metres")):
        with pytest.raises(ValueError, match=re.escape(says)):
            pipe.process(bad)
    pipe.close()
    with pytest.raises(RuntimeError, match="this Pipeline was closed"):
        pipe.process(f1)


def test_a_first_frame_with_a_patch_of_depth_does_not_set_the_lighting_s_scale():
    """Frame 0 with depth on a 12 x 12 patch alone (one usable sample): its estimate is its own, flagged weak, and does
    not start the temporal filter, whose first estimate is every later solve's reference (its colour balance fixes
    their albedo scale): frames 3-5 as bright as without it (before: 29% darker to the end, albedos over 1)."""
    def patch(i, f):
        if i:
            return f
        depth = np.zeros_like(f.depth)
        depth[114:126, 154:166] = f.depth[114:126, 154:166]
        return dataclasses.replace(f, depth=depth)

    clean, patched = _demo_lighting(6), _demo_lighting(6, patch)
    assert patched[0].diagnostics.weak and any("start the temporal filter" in n for n in patched[0].diagnostics.notes)
    for a, b in zip(clean[3:], patched[3:]):
        assert b.lighting.sh[:, 0] == pytest.approx(a.lighting.sh[:, 0], rel=0.1), b.index


@pytest.mark.parametrize("history", [None, 0])
def test_a_black_frame_keeps_the_held_light(history):
    """Frame 2 black (nothing to search the light in): it keeps the light held since frame 0, whose irradiance goes
    on being filtered (before: frame 2 had none, which dropped its shadow, and frame 3's filter started again). With
    the history of samples the joint solve still fits it on the earlier views' samples; without (history 0) the solve
    has no sample and returns the previous lighting, and frame 1's light is held with it."""
    results = _demo_lighting(5, lambda i, f: dataclasses.replace(f, color=np.zeros_like(f.color)) if i == 2 else f,
                             history)
    suns = [r.diagnostics.sun for r in results]
    assert results[2].diagnostics.weak and all(sun is not None for sun in suns)
    assert np.degrees(np.arccos(np.clip(np.dot(suns[1]["direction"], suns[2]["direction"]), -1, 1))) < 5
    assert suns[3]["irradiance"] != suns[3]["irradiance_frame"]
    if history == 0:
        assert suns[2] == suns[1] and "no samples: the traced light of frame 1 held" in results[2].diagnostics.notes
        assert np.array_equal(results[2].lighting.sh, results[1].lighting.sh)


def test_a_uniform_frame_is_weak_and_leaves_the_lighting_after_it_alone():
    """Frame 3 one grey level everywhere (a camera's glitch, its depth intact): weak, said, no samples taken (an
    all-255 frame alike: no lower bounds with lighting.censored); the frames after it are lit as without it. Before,
    it was lit as it was: it restarted the temporal filter, and the traced light's irradiance fell to a third (2.86
    -> 0.88) and was still a quarter low ten frames later."""
    grey = (lambda i, f: dataclasses.replace(f, color=np.full_like(f.color, 128)) if i == 3 else f)
    clean, glitch = _demo_lighting(6), _demo_lighting(6, grey)
    diag = glitch[3].diagnostics
    assert diag.weak and any("one level everywhere" in n for n in diag.notes)
    assert not any(r.diagnostics.change_detected for r in glitch)
    for a, b in zip(clean[4:], glitch[4:]):
        assert np.asarray(b.diagnostics.sun["irradiance"]) == pytest.approx(a.diagnostics.sun["irradiance"], rel=0.05)
        assert np.linalg.norm(b.lighting.sh - a.lighting.sh) < 0.15 * np.linalg.norm(a.lighting.sh), b.index
    k = Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, 1000.0)
    white = prepare(Frame(0, 0.0, np.full((48, 64, 3), 255, np.uint8), np.ones((48, 64), np.float32), k, np.eye(4)),
                    Session().lighting, Session().reconstruction)
    assert white.uniform and not white.usable.any() and not white.clipped.any()


def test_a_frame_without_a_pose_repeats_the_previous_estimate_and_its_light():
    """Frame 2 without a pose repeats frame 1's lighting, says it is frame 1's and keeps its traced light (before: no
    estimated_frame and no light, which photoreg score counted as 90 degrees off)."""
    results = _demo_lighting(3, lambda i, f: dataclasses.replace(f, pose=None) if i in (0, 2) else f)
    held, before = results[2].diagnostics, results[1].diagnostics
    assert held.weak and "no pose: previous estimate repeated" in held.notes
    assert held.estimated_frame == 1 and held.sun == before.sun is not None
    assert np.array_equal(results[2].lighting.sh, results[1].lighting.sh)
    # before any estimate there is none to repeat: zero lighting, said so, and lighting.jsonl's estimated_frame null
    # (before: "previous estimate repeated", and the key missing)
    first = results[0].diagnostics
    assert first.weak and first.notes[-1] == "no pose and no earlier estimate: zero lighting"
    assert first.notes[0].startswith("frame 0: no pose given (to track the camera instead: photoreg run --no-poses")
    assert not results[0].lighting.sh.any() and first.to_json()["estimated_frame"] is None


def test_asynchronous_lighting_is_the_in_line_estimate_one_frame_later(tmp_path):
    """lighting.asynchronous with a worker that always finishes before the next frame (waited for here, as a slow
    camera would): frame 0 is estimated in line, every later frame hands its estimate to the worker and holds the
    one before, so frame k + 1 shows the in-line pipeline's lighting of frame k (same history, filter and fused
    luminance), to rounding with the solves in the child process (lighting.solve_process: arrays unpickled at other
    addresses sum in another order; 1e-13 on the demo) and exactly in the worker thread; the solve's stages run in
    the worker ('worker solve' in the collecting frame's ms), and a frame exposed at half the radiance still gets
    its own gain 0.5."""
    k = Intrinsics(64, 48, 56.0, 56.0, 31.5, 23.5, 5000.0)
    rec = open_recording(write_recording(tmp_path / "rec", k, 6, with_gt=False))
    frames = [dataclasses.replace(f, color=linear_to_srgb(0.5 * srgb_to_linear(f.color))) if f.index == 4 else f
              for f in iter_frames(rec, range(6))]
    s = Session(device="cpu")
    s.lighting.rays, s.lighting.stride = 16, 2
    inline = pipeline_module.Pipeline(s, rec.intrinsics)
    expected = [inline.process(f) for f in frames]
    s.lighting.asynchronous = True
    for process in (True, False):
        s.lighting.solve_process = process
        pipe = pipeline_module.Pipeline(s, rec.intrinsics)
        results = []
        for f in frames:
            results.append(pipe.process(f))
            pipe.wait_for_estimate()
        pipe.close()
        assert [r.diagnostics.estimated_frame for r in results] == [0, 0, 1, 2, 3, 4]
        for r in results:
            got, want = r.lighting.sh, expected[max(r.index - 1, 0)].lighting.sh
            assert np.allclose(got, want, rtol=1e-9, atol=1e-12) if process else np.array_equal(got, want), r.index
        for r in results[1:]:
            assert "solve" not in r.timings_ms
            assert r.diagnostics.notes[0].startswith(f"lighting of frame {r.index - 1}, estimated beside")
        assert all("worker solve" in r.timings_ms for r in results[2:])
        gains = [r.diagnostics.exposure_gain for r in results]
        assert abs(gains[4] - 0.5) < 0.1 and all(abs(g - 1) < 0.1 for i, g in enumerate(gains) if i != 4), gains


def test_asynchronous_lighting_runs_free_and_raises_the_workers_error(tmp_path, monkeypatch):
    """Not waited for: every frame is processed with a finite, earlier frame's lighting (never a later one, never
    going back), `photoreg run --async` writes every record; a solve that fails in the worker thread, or a solve
    process that dies (lighting.solve_process), fails the frame that collects it instead of passing silently."""
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--frames", "0:6", "--rays", "16", "--async", "--quiet"]) == 0
    records = read_jsonl(out / "lighting.jsonl")
    assert len(records) == 6 and finite_records(records)
    est = [r["diagnostics"]["estimated_frame"] for r in records]
    assert est[0] == 0 and all(e <= r["frame"] for e, r in zip(est, records)) and est == sorted(est), est

    k = Intrinsics(64, 48, 56.0, 56.0, 31.5, 23.5, 5000.0)
    rec = open_recording(write_recording(tmp_path / "rec", k, 4, with_gt=False))
    solve = pipeline_module.solve

    def failing(*args, **kwargs):
        if failing.calls:
            raise FloatingPointError("solver broke")
        failing.calls += 1
        return solve(*args, **kwargs)

    s = Session(device="cpu")
    s.lighting.rays, s.lighting.stride, s.lighting.sun, s.lighting.asynchronous = 16, 2, False, True
    frames = list(iter_frames(rec, range(4)))
    before = set(multiprocessing.active_children())
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    pipe.process(frames[0])   # in line, solved in the child process
    for child in set(multiprocessing.active_children()) - before:
        child.kill()
        child.join()
    pipe.process(frames[1])
    pipe.wait_for_estimate()
    with pytest.raises(RuntimeError, match="solve process stopped"):
        pipe.process(frames[2])
    pipe.close()

    failing.calls = 0
    monkeypatch.setattr(pipeline_module, "solve", failing)
    s.lighting.solve_process = False   # the worker thread solves
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    pipe.process(frames[0])
    pipe.process(frames[1])
    pipe.wait_for_estimate()
    with pytest.raises(FloatingPointError, match="solver broke"):
        pipe.process(frames[2])
    pipe.close()


def test_composites_on_frames_that_hold_the_lighting(tmp_path):
    """The demo with its object and --every 2: every frame is composited, the held frame 1 from its own view."""
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--frames", "0:3", "--rays", "16", "--every", "2", "--quiet"]) == 0
    records = read_jsonl(out / "lighting.jsonl")
    assert ["solve" in r["timings_ms"] for r in records] == [True, False, True]
    for r in records:   # the render stage and its parts (G-buffer, the renderer, the composite) within it
        parts = [r["timings_ms"]["render " + p] for p in ("gbuffer", "shadows", "composite")]
        assert min(parts) > 0 and sum(parts) <= r["timings_ms"]["render"]
    shots = [cv2.imread(str(out / "composite" / f"{i:06d}.png")) for i in range(3)]
    assert all(x is not None for x in shots) and np.abs(shots[1].astype(int) - shots[0]).mean() > 1


def test_depth_filter_averages_noise_and_keeps_edges_and_holes():
    """reconstruction.depth_filter_px: a noisy plane at 1 m (sigma 2 mm) with a 10 cm step and a hole; the filter
    cuts the noise, does not blur the step and leaves the hole empty; bad windows are refused."""
    rng = np.random.default_rng(0)
    truth = np.full((60, 80), 1.0, np.float32)
    truth[:, 40:] = 1.1
    depth = truth + rng.normal(0, 0.002, truth.shape).astype(np.float32)
    depth[20:30, 10:20] = 0.0
    k = Intrinsics(80, 60, 70.0, 70.0, 39.5, 29.5, 1000.0)
    frame = Frame(0, 0.0, np.full((60, 80, 3), 128, np.uint8), depth, k, np.eye(4))
    s = Session()
    raw = prepare(frame, s.lighting, s.reconstruction).depth
    s.reconstruction.depth_filter_px = 9
    out = prepare(frame, s.lighting, s.reconstruction).depth
    flat = np.zeros_like(truth, bool)
    flat[35:55, 5:35] = True
    assert np.std(out[flat] - truth[flat]) < 0.4 * np.std(raw[flat] - truth[flat])
    assert np.abs(out[:, 38] - truth[:, 38]).max() < 0.006 and np.abs(out[:, 41] - truth[:, 41]).max() < 0.006
    assert np.all(out[20:30, 10:20] == 0) and np.all(out[raw > 0] > 0)
    for bad in (8, 1, 17):
        s.reconstruction.depth_filter_px = bad
        with pytest.raises(ValueError, match="depth_filter_px"):
            validate(s)


def test_prepare_masks_and_shares_match_their_definitions():
    """prepare (cv2 fast paths): depth kept only within [depth_min, depth_max] (NaN, +-inf, negative and far depth
    become 0), saturated = brightest channel >= saturation_level, black = brightest <= black_level, usable = valid
    and neither; the shares are of the whole frame. A colour that is not 8-bit RGB is refused naming the frame."""
    rng = np.random.default_rng(3)
    color = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    color[:5] = 255
    color[5:12, :, :] = rng.integers(0, 4, (7, 64, 3), dtype=np.uint8)
    depth = rng.uniform(-1.0, 6.0, (48, 64)).astype(np.float32)
    depth[::7, ::5], depth[1::9, ::4], depth[2::11, 1::3] = np.nan, np.inf, -np.inf
    k = Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, 1000.0)
    s = Session()
    lc, rc = s.lighting, s.reconstruction
    p = prepare(Frame(4, 0.0, color, depth, k, np.eye(4), source="made up"), lc, rc)
    valid = np.isfinite(depth) & (depth >= rc.depth_min) & (depth <= rc.depth_max)
    assert 0.2 < valid.mean() < 0.8
    assert p.depth.dtype == np.float32 and np.array_equal(p.depth, np.where(valid, depth, 0.0).astype(np.float32))
    peak = color.max(axis=2)
    saturated, black = peak >= lc.saturation_level, peak <= lc.black_level
    assert saturated.any() and black.any()
    assert np.array_equal(p.usable, valid & ~saturated & ~black)
    assert (p.saturated_fraction, p.black_fraction, p.valid_depth_fraction) == pytest.approx(
        (saturated.mean(), black.mean(), valid.mean()))
    assert np.array_equal(p.linear, srgb_to_linear(color))
    with pytest.raises(ValueError, match=r"frame 4 \(made up\): colour is float32"):
        prepare(Frame(4, 0.0, color.astype(np.float32) / 255, depth, k, np.eye(4), source="made up"), lc, rc)


@pytest.mark.skipif(__import__("platform").libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_keep_frame_memory_spares_each_frame_its_page_faults():
    """photoreg.device.keep_frame_memory: glibc accepts every mallopt setting, and a process that made it allocates
    and frees frame-sized arrays with next to no page faults (50 frames of two 640x480x3 float32 arrays touch 90000
    pages; glibc's defaults fault in about as many: 88400 on the 2-core CPU)."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        import resource
        import numpy as np
        from photoreg.device import keep_frame_memory
        assert keep_frame_memory() is True
        def frame():
            a = np.empty((480, 640, 3), np.float32)
            a[:] = 0.5
            return float((a * 2.0)[0, 0, 0])
        for _ in range(3):
            frame()
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(50):
            frame()
        print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
        """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert int(run.stdout.split()[-1]) < 900


def test_solve_process_without_main_guard_is_a_clear_error(tmp_path):
    """lighting.solve_process spawns a child that imports the main script again: a script that builds an asynchronous
    Pipeline at import gets an error saying so (not a bare BrokenProcessPool); the same script under a main guard
    runs."""
    import subprocess
    import sys
    import textwrap

    body = textwrap.dedent("""
        from photoreg.config import Session, validate
        from photoreg.pipeline import Pipeline
        from photoreg.types import Intrinsics
        def build():
            s = Session()
            s.device = "cpu"
            s.lighting.asynchronous = True
            validate(s)
            Pipeline(s, Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)).close()
            print("pipeline ready")
        """)
    runs = {}
    for name, tail in (("bare", "build()\n"), ("guarded", 'if __name__ == "__main__":\n    build()\n')):
        script = tmp_path / f"{name}.py"
        script.write_text(body + tail)
        runs[name] = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                                    cwd=tmp_path)
    assert runs["bare"].returncode != 0 and "pipeline ready" not in runs["bare"].stdout
    assert 'if __name__ == "__main__":' in runs["bare"].stderr and "solve_process = false" in runs["bare"].stderr
    assert runs["guarded"].returncode == 0 and "pipeline ready" in runs["guarded"].stdout, runs["guarded"].stderr


def test_strided_box_is_the_centred_box_mean():
    """strided_box(prep, st): at pixel (r*st, c*st) the mean linear radiance of the (st|1)^2 box centred there (image
    edges reflected) and whether the whole box is usable; stride 1 is the frame itself."""
    rng = np.random.default_rng(5)
    color = rng.integers(10, 240, (30, 41, 3), dtype=np.uint8)
    color[7, 9] = 255   # saturated: every box holding it is unusable
    depth = np.full((30, 41), 1.5, np.float32)
    k = Intrinsics(41, 30, 40.0, 40.0, 20.0, 14.5, 1000.0)
    s = Session()
    prep = prepare(Frame(0, 0.0, color, depth, k, np.eye(4)), s.lighting, s.reconstruction)
    radiance, usable, clipped = strided_box(prep, 4)
    assert radiance.shape == (8, 11, 3) and usable.shape == (8, 11) and not clipped.any()
    padded = np.pad(prep.linear, ((2, 2), (2, 2), (0, 0)), mode="symmetric")   # numpy's symmetric = cv2's REFLECT
    for r, c in [(0, 0), (1, 2), (3, 5), (7, 10)]:
        box = padded[4 * r:4 * r + 5, 4 * c:4 * c + 5]
        np.testing.assert_allclose(radiance[r, c], box.reshape(-1, 3).mean(axis=0), rtol=1e-5)
    bad = np.pad(~prep.usable, 2, mode="symmetric")
    expected = np.array([[not bad[4 * r:4 * r + 5, 4 * c:4 * c + 5].any() for c in range(11)] for r in range(8)])
    np.testing.assert_array_equal(usable, expected)
    assert not usable[2, 2] and usable.sum() > 80
    # lighting.censored: a box holding a saturated pixel is measured as it is; one holding nothing else is clipped
    # (its mean a lower bound)
    _, fit, clipped = strided_box(prep, 4, censored=True)
    near = np.zeros((8, 11), bool)
    near[2, 2] = True       # the one box holding pixel (7, 9): rows 6-10, columns 6-10
    np.testing.assert_array_equal(fit, usable | near)
    assert not clipped.any()
    color[17:30, 25:41] = 255
    sat = prepare(Frame(0, 0.0, color, depth, k, np.eye(4)), s.lighting, s.reconstruction)
    _, fit, clipped = strided_box(sat, 4, censored=True)
    inside = np.zeros((8, 11), bool)
    inside[5:, 7:] = True   # boxes of rows 18-29 and columns 26-40 (reflected at the border): all saturated
    np.testing.assert_array_equal(clipped, inside)
    assert fit[inside].all() and not strided_box(sat, 4)[1][inside].any()
    full_radiance, full_usable, _ = strided_box(prep, 1)
    assert full_radiance is prep.linear and full_usable is prep.usable
    for bad in (2, -1, 17):
        s.lighting.sample_box = bad
        with pytest.raises(ValueError, match="sample_box"):
            validate(s)
    small, small_usable, _ = strided_box(prep, 4, 3)   # lighting.sample_box: a 3 x 3 box at stride 4
    for r, c in [(0, 0), (3, 5), (7, 10)]:
        np.testing.assert_allclose(small[r, c], padded[4 * r + 1:4 * r + 4, 4 * c + 1:4 * c + 4].reshape(-1, 3).mean(0),
                                   rtol=1e-5)
    bad = np.pad(~prep.usable, 1, mode="symmetric")
    expected = np.array([[not bad[4 * r:4 * r + 3, 4 * c:4 * c + 3].any() for c in range(11)] for r in range(8)])
    np.testing.assert_array_equal(small_usable, expected)
    assert not small_usable[2, 2]
    own, own_usable, _ = strided_box(prep, 4, 1)
    np.testing.assert_array_equal(own, prep.linear[::4, ::4])
    np.testing.assert_array_equal(own_usable, prep.usable[::4, ::4])


def _demo_observed(frames: int):
    """(pipeline, recording, prepared frame, pose) after the demo's first `frames` frames were fused on the CPU."""
    s = load_session(REPO / "data" / "demo" / "session.toml")
    s.device, s.lighting.rays = "cpu", 16
    rec = open_recording(s.recording.path)
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    for frame in iter_frames(rec, range(frames)):
        prep, pose, _ = pipe.observe(frame, {})
    return pipe, rec, prep, pose


def test_sample_kernel_draws_the_host_paths_samples():
    """The GPU's sample path (kernels.samples: box radiance and depth checks by one kernel over the maps, run here
    on Warp's CPU) gives the flags of strided_box and lighting.samples.agreement at every map pixel, and the
    pipeline's samples are the same either way, at the lighting's stride and a held frame's, with the stride's box
    and other boxes (lighting.sample_box), with the brightest fifth of the frame saturated (lighting.censored)."""
    from photoreg.kernels.raycast import raycast_surface
    from photoreg.kernels.samples import AGREES, CANDIDATE, CLIPPED, sample_maps
    from photoreg.lighting.samples import agreement

    pipe, rec, prep, pose = _demo_observed(3)
    bright = prep.usable & (prep.linear.max(axis=-1) > np.percentile(prep.linear.max(axis=-1)[prep.usable], 80))
    prep = dataclasses.replace(prep, usable=prep.usable & ~bright, clipped=prep.clipped | bright)
    s = pipe.session
    lc, rc = s.lighting, s.reconstruction
    gap = lc.max_depth_gap_voxels * rc.voxel_size
    checked = 0
    for st, box, censored in ((1, 0, True), (2, 0, True), (4, 0, True), (8, 0, True), (4, 3, True), (4, 1, True),
                              (2, 5, True), (4, 0, False)):
        lc.sample_box, lc.censored = box, censored
        maps = raycast_surface(pipe.volume.dense_grid(), rec.intrinsics, pose, rc.depth_min, rc.depth_max, stride=st)
        found = sample_maps(prep.colour, prep.usable, prep.depth, rec.intrinsics, pose, maps, lc.max_normal_angle,
                            gap, "cpu", box, prep.clipped if censored else None)
        radiance, usable, clipped = strided_box(prep, st, box, censored)
        np.testing.assert_array_equal((found.flags & CANDIDATE) > 0, usable & maps.valid)
        np.testing.assert_array_equal((found.flags & CLIPPED) > 0, clipped & usable & maps.valid)
        assert (clipped & usable & maps.valid).any() == censored
        r, c = np.nonzero(usable & maps.valid)
        agrees = agreement(prep.depth, rec.intrinsics, pose, r * st, c * st, maps.depth[r, c], maps.normal[r, c],
                           max(2, st), lc.max_normal_angle, gap)
        assert 0 < agrees.sum() < agrees.size   # both kinds of candidate are there
        np.testing.assert_array_equal((found.flags[r, c] & AGREES) > 0, agrees)
        np.testing.assert_allclose(found.radiance[r, c], radiance[r, c], rtol=1e-5, atol=1e-7)
        for cap in (None, 500):
            host = pipe._samples(prep, maps, pose, cap)
            pipe.sample_kernel = True
            try:
                kernel = pipe._samples(prep, maps, pose, cap)
            finally:
                pipe.sample_kernel = False
            np.testing.assert_allclose(kernel[0], host[0], rtol=1e-5, atol=1e-7)
            for a, b in zip(kernel[1:], host[1:]):
                np.testing.assert_array_equal(a, b)
            checked += len(host[0])
    assert checked > 7000


def test_kernel_samples_read_the_8bit_colour():
    """On the samples' kernel path (a GPU's; here Warp's CPU) a frame with no object inserted never makes its float
    linear colour on the host (Prepared.linear, made when first read): the kernel linearises the 8-bit colour, a
    quarter of the bytes to upload, and draws the same samples as the host's path from the float colour."""
    from photoreg.kernels.raycast import raycast_surface

    s = load_session(REPO / "data" / "demo" / "session.toml")
    s.device, s.lighting.rays, s.objects = "cpu", 16, []
    rec = open_recording(s.recording.path)
    pipe = pipeline_module.Pipeline(s, rec.intrinsics)
    pipe.sample_kernel = True
    for frame in iter_frames(rec, range(3)):
        prep, pose, notes = pipe.observe(frame, {})
        result = pipe.estimate(frame, prep, pose, notes, {})
    assert np.isfinite(result.lighting.sh).all() and result.diagnostics.exposure_gain > 0
    assert "linear" not in vars(prep)   # the cached_property was never read
    rc = pipe.session.reconstruction
    maps = raycast_surface(pipe.volume.dense_grid(), rec.intrinsics, pose, rc.depth_min, rc.depth_max, stride=4)
    kernel = pipe._samples(prep, maps, pose)
    pipe.sample_kernel, pipe._checked = False, None
    host = pipe._samples(prep, maps, pose)
    np.testing.assert_allclose(kernel[0], host[0], rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(kernel[1], host[1])


def test_samples_of_one_frame_check_its_pixels_once(monkeypatch):
    """A frame that hands its estimate to the worker (lighting.asynchronous) takes its gain's samples from the maps
    the worker's estimate reads next: the per-pixel checks (strided_box, kernels.samples on a GPU) run once for both,
    and the samples are those of a fresh check."""
    from photoreg.kernels.raycast import raycast_surface

    pipe, rec, prep, pose = _demo_observed(2)
    rc = pipe.session.reconstruction
    maps = raycast_surface(pipe.volume.dense_grid(), rec.intrinsics, pose, rc.depth_min, rc.depth_max, stride=4)
    calls = []
    monkeypatch.setattr(pipeline_module, "strided_box", lambda *a: calls.append(a) or strided_box(*a))
    gain = pipe._samples(prep, maps, pose, pipeline_module.GAIN_SAMPLES)
    estimate = pipe._samples(prep, maps, pose)
    assert len(calls) == 1 and len(gain[0]) < len(estimate[0])
    pipe._checked = None
    for fresh, kept in zip(pipe._samples(prep, maps, pose), estimate):
        np.testing.assert_array_equal(fresh, kept)
    assert len(calls) == 2


def test_fusion_takes_the_sessions_depth_range():
    """reconstruction.depth_min reaches the fusion volume: a wall 8 cm from the camera, inside a depth_min of 5 cm
    (below the fusion's own default of 10 cm), is fused and ray cast (before, the fusion dropped it: nothing fused)."""
    k = Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, 1000.0)
    s = Session()
    s.device = "cpu"
    s.reconstruction.depth_min = 0.05
    validate(s)
    pipe = pipeline_module.Pipeline(s, k)
    frame = Frame(0, 0.0, np.full((48, 64, 3), 128, np.uint8), np.full((48, 64), 0.08, np.float32), k, np.eye(4))
    prep, pose, _ = pipe.observe(frame, {})
    assert pipe.volume.cfg.depth_min == 0.05 and pipe.volume.frames_integrated == 1
    maps = pipeline_module.raycast_surface(pipe.volume.dense_grid(), k, pose, 0.05, 4.0)
    assert maps.valid.mean() > 0.5
