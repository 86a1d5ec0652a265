"""Official accuracy metrics and `photoreg score` on tiny synthetic runs and recordings."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from photoreg.bench import metrics
from photoreg.bench.score import format_report, score, score_command, true_light
from photoreg.cli import main as cli_main
from photoreg.io.images import linear_to_srgb, write_exr, write_png_rgb
from photoreg.lighting import sh

QUAD = sh.fibonacci_sphere(4000)


def sun_sky_gt(sun=(0.4, 0.3, 0.866), bands=8):
    """Directional GT lighting: a sun lobe plus a dim sky, projected to `bands` bands."""
    s = np.asarray(sun, float) / np.linalg.norm(sun)
    f = np.exp(30 * (QUAD @ s - 1))[:, None] * [5.0, 4.5, 3.5] + np.clip(QUAD[:, 2:], 0, None) * [0.1, 0.15, 0.2] + 0.03
    return sh.project(QUAD, f, np.full(len(QUAD), 4 * math.pi / len(QUAD)), bands)


def l1_lobe(direction, ambient=1.0, strength=0.8):
    """Grey SH with band 0 and an l=1 band pointing along `direction` (2 bands)."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    c = np.array([ambient, strength * d[1], strength * d[2], strength * d[0]])
    return np.tile(c, (3, 1))


def write_run(tmp_path, gt, estimates, n_rgb=0):
    """RECORDING (lighting_gt.json, an index of n_rgb frames) and OUT (lighting.jsonl) under tmp_path."""
    rec, out = tmp_path / "rec", tmp_path / "out"
    rec.mkdir(exist_ok=True)
    out.mkdir(exist_ok=True)
    b = sh.bands_of(gt.shape[1])
    (rec / "lighting_gt.json").write_text(json.dumps({"bands": b, "sh": gt.tolist(), "frame": "world", "exposure": 1.0}))
    if n_rgb:  # a native recording index (images are only read where a test writes them)
        for kind in ("rgb", "depth"):
            (rec / f"{kind}.txt").write_text("".join(f"{i * 0.1:.6f} {kind}/{i:06d}.png\n" for i in range(n_rgb)))
        (rec / "intrinsics.json").write_text(json.dumps({"width": 160, "height": 120, "fx": 150.0, "fy": 150.0,
                                                         "cx": 79.5, "cy": 59.5, "depth_scale": 5000.0}))
    lines = []
    for i, e in enumerate(estimates):
        if isinstance(e, str):
            lines.append(e)
            continue
        e = np.atleast_2d(e)
        lines.append(json.dumps({"frame": i, "timestamp": 0.1 * i, "bands": sh.bands_of(e.shape[1]), "sh": e.tolist(),
                                 "dominant_direction": sh.dominant_direction(e).tolist(),
                                 "diagnostics": {"n_samples": 100}, "timings_ms": {"solve": 1.0}}))
    (out / "lighting.jsonl").write_text("\n".join(lines) + "\n")
    return out, rec


def test_gt_scores_zero(tmp_path):
    gt = sun_sky_gt()
    lt = score(*write_run(tmp_path, gt, [gt, gt]))["lighting"]
    assert lt["n_scored"] == 2 and lt["nonfinite_fraction"] == 0
    for name, s in lt["metrics"].items():
        assert s["median"] == pytest.approx(0, abs=1e-6) and s["p90"] == pytest.approx(0, abs=1e-6), name


def test_scale_invariance(tmp_path):
    gt = sun_sky_gt()
    lt = score(*write_run(tmp_path, gt, [3 * gt, 0.01 * gt]))["lighting"]
    for name, s in lt["metrics"].items():
        assert s["mean"] == pytest.approx(0, abs=1e-6), name


def test_truncated_gt_is_close_but_not_zero(tmp_path):
    gt = sun_sky_gt()
    lt = score(*write_run(tmp_path, gt, [sh.truncate(gt, 3)]))["lighting"]["metrics"]
    assert lt["direction_deg"]["median"] == pytest.approx(0, abs=1e-6)
    assert 1e-4 < lt["irradiance_si_rmse_sphere"]["median"] < 0.1


def test_constant_estimate_scores_badly(tmp_path):
    gt = sun_sky_gt()
    ambient = np.zeros((3, 9))
    ambient[:, 0] = 1.0
    lt = score(*write_run(tmp_path, gt, [ambient]))["lighting"]
    m = lt["metrics"]
    assert m["direction_deg"]["median"] == 90.0
    assert m["irradiance_si_rmse_upper"]["median"] > 0.1 and m["irradiance_si_rmse_sphere"]["median"] > 0.1
    assert any("90 deg" in n for n in lt["notes"])


@pytest.mark.parametrize("angle", [0.0, 17.0, 90.0, 150.0])
def test_rotated_lobe_direction_error(tmp_path, angle):
    d = np.array([0.3, -0.2, 0.9])
    axis = np.cross(d, [1.0, 0.0, 0.0])
    rotated = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).apply(d)
    lt = score(*write_run(tmp_path, l1_lobe(d), [l1_lobe(rotated)]))["lighting"]
    assert lt["metrics"]["direction_deg"]["median"] == pytest.approx(angle, abs=1e-6)
    assert lt["metrics"]["colour_deg"]["median"] == pytest.approx(0, abs=1e-6)


def test_colour_error():
    gt = l1_lobe([0, 0, 1])
    tinted = gt * np.array([[1.0], [1.0], [0.5]])
    expected = math.degrees(math.acos(2.5 / math.sqrt(3 * 2.25)))
    assert metrics.colour_error_deg(tinted, gt) == pytest.approx(expected, abs=1e-6)


def test_non_finite_and_missing_frames_counted(tmp_path):
    gt = sun_sky_gt()
    bad = gt.copy()
    bad[1, 4] = np.nan
    null_line = json.dumps({"frame": 2, "bands": 8, "sh": None})
    # Frames 0..5 in the recording; 0 good, 1 NaN, 2 null, 3 good, 4 and 5 missing.
    lt = score(*write_run(tmp_path, gt, [gt, bad, null_line, gt], n_rgb=6))["lighting"]
    assert (lt["n_frames"], lt["n_scored"], lt["n_nonfinite"], lt["n_missing"]) == (6, 2, 2, 2)
    assert lt["nonfinite_fraction"] == pytest.approx(4 / 6)
    assert lt["metrics"]["direction_deg"]["n"] == 2
    assert [r["finite"] for r in lt["per_frame"]] == [True, False, False, True, False, False]


def test_errors_are_clear(tmp_path):
    gt = sun_sky_gt(bands=3)
    out, rec = write_run(tmp_path, gt, [gt, "{not json", gt])
    with pytest.raises(ValueError, match=r"lighting\.jsonl:2: malformed JSON"):
        score(out, rec)
    out, rec = write_run(tmp_path, gt, [json.dumps({"frame": 0, "bands": 2, "sh": gt.tolist()})])
    with pytest.raises(ValueError, match="band mismatch"):
        score(out, rec)
    out, rec = write_run(tmp_path, gt, [json.dumps({"frame": 0, "sh": gt[:2].tolist()})])
    with pytest.raises(ValueError, match="3 rows"):
        score(out, rec)
    out, rec = write_run(tmp_path, gt, [gt, json.dumps({"frame": 0, "sh": gt.tolist()})])
    with pytest.raises(ValueError, match="frame 0 already given on line 1"):
        score(out, rec)
    out, rec = write_run(tmp_path, gt, [json.dumps({"frame": True, "sh": gt.tolist()})])
    with pytest.raises(ValueError, match=r"lighting\.jsonl:1: 'frame' must be a non-negative integer, got True"):
        score(out, rec)
    sun = {"frame": 0, "sh": gt.tolist(), "diagnostics": {"sun": {"direction": [0, 0]}}}
    out, rec = write_run(tmp_path, gt, [json.dumps(sun)])
    with pytest.raises(ValueError, match=r"lighting\.jsonl:1: diagnostics\.sun\.direction must be 3 numbers"):
        score(out, rec)
    out, rec = write_run(tmp_path, gt, [])
    with pytest.raises(ValueError, match=r"lighting\.jsonl: no frames"):
        score(out, rec)
    with pytest.raises(FileNotFoundError, match="lighting_gt.json"):
        score(out, tmp_path / "nowhere")
    (out / "lighting.jsonl").unlink()
    with pytest.raises(FileNotFoundError, match="lighting.jsonl"):
        score(out, rec)
    (rec / "lighting_gt.json").write_text(json.dumps({"bands": 4, "sh": gt.tolist()}))
    with pytest.raises(ValueError, match="band mismatch"):
        score(out, rec)
    out, rec = write_run(tmp_path, gt, [gt, gt, gt], n_rgb=2)   # a run of another recording than --gt
    with pytest.raises(ValueError, match=r"holds frame\(s\) 2 that .*rec \(2 frames\) does not have"):
        score(out, rec)
    bad = {"frame": 0, "sh": gt.tolist(), "diagnostics": {"sun": {"direction": ["a", "b", "c"]}}}
    out, rec = write_run(tmp_path, gt, [json.dumps(bad)])
    with pytest.raises(ValueError, match=r"lighting\.jsonl:1: diagnostics\.sun\.direction must be 3 numbers or null"):
        score(out, rec)
    out, rec = write_run(tmp_path, gt, [json.dumps({"frame": 0, "sh": gt.tolist(), "pose": [[1, 0], [0, 1]]})])
    with pytest.raises(ValueError, match=r"lighting\.jsonl:1: pose must be 4 x 4 numbers or null"):
        score(out, rec)
    out, rec = write_run(tmp_path, gt, [json.dumps({"frame": 0, "sh": gt.tolist(), "timestamp": "noon"})])
    with pytest.raises(ValueError, match=r"lighting\.jsonl:1: timestamp must be a number or null, got 'noon'"):
        score(out, rec)
    out, rec = write_run(tmp_path, gt, [gt])
    for text in ("[]", "{not json"):   # a hand-edited summary: named, not an AttributeError
        (out / "summary.json").write_text(text)
        with pytest.raises(ValueError, match=r"summary\.json: (expected a JSON object|not readable as JSON)"):
            score(out, rec)
    (out / "summary.json").unlink()
    for text in ("{}", "{not json"):   # a scene.json, but not the generator's: named, not a KeyError
        (rec / "scene.json").write_text(text)
        with pytest.raises(ValueError, match=r"scene\.json: not as `photoreg synth` writes it"):
            score(out, rec)


def test_a_run_of_another_recording_is_refused_by_its_timestamps(tmp_path):
    """--gt must be the recording the run processed: frames whose timestamps are not the recording's are refused
    (before: scored against the wrong ground truth, a believable table); a summary naming another folder whose frames
    agree (a moved or copied recording) gives a note."""
    gt = sun_sky_gt(bands=3)
    other = {"frame": 1, "timestamp": 5.0, "bands": 3, "sh": gt.tolist()}
    out, rec = write_run(tmp_path, gt, [gt, json.dumps(other)], n_rgb=3)
    (out / "summary.json").write_text(json.dumps({"recording": "/data/elsewhere"}))
    with pytest.raises(ValueError, match=r"frame 1 has timestamp 5\.000000 s, .*rec 0\.100000 s \(1 of the run's 2 "
                                         r"frames differ\): is --gt the recording it ran on \(/data/elsewhere\)\?"):
        score(out, rec)
    (out / "summary.json").unlink()
    out, rec = write_run(tmp_path, gt, [gt, gt], n_rgb=3)
    notes = score(out, rec)["lighting"]["notes"]
    assert not any("the run read" in n for n in notes)
    (out / "summary.json").write_text(json.dumps({"recording": "/data/elsewhere"}))
    notes = score(out, rec)["lighting"]["notes"]
    assert f"the run read /data/elsewhere, scored against {rec} (their frames' timestamps agree)" in notes
    # that folder still there with another ground truth: another recording made alike (a tracked run, lit from no
    # recorded pose, passed before), refused; a copy of the same ground truth keeps the note
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "lighting_gt.json").write_text((rec / "lighting_gt.json").read_text())
    (out / "summary.json").write_text(json.dumps({"recording": str(elsewhere)}))
    assert any(n.startswith(f"the run read {elsewhere}") for n in score(out, rec)["lighting"]["notes"])
    (elsewhere / "lighting_gt.json").write_text((rec / "lighting_gt.json").read_text().replace("0", "1", 1))
    with pytest.raises(ValueError, match=f"the run read {elsewhere}, whose lighting_gt.json differs from"):
        score(out, rec)
    (out / "summary.json").write_text(json.dumps({"recording": str(rec)}))
    assert not any("the run read" in n for n in score(out, rec)["lighting"]["notes"])
    # the generator's recordings share their timestamps: a run lit from recorded poses other than the recording's
    # is refused by them (before: scored, the summary's note alone telling)
    gt_poses = "".join(f"{0.1 * i:.6f} 0 0 {1.0 + i} 0 0 0 1\n" for i in range(3))
    (rec / "groundtruth.txt").write_text(gt_poses)
    lines = [json.loads(x) for x in (out / "lighting.jsonl").read_text().splitlines()]
    for i, line in enumerate(lines):
        line["pose"] = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 1.0 + i], [0, 0, 0, 1.0]]
    (out / "lighting.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    (out / "summary.json").write_text(json.dumps({"recording": "/data/elsewhere", "settings": {"use_poses": True}}))
    assert score(out, rec)["lighting"]["n_scored"] == 2
    lines[1]["pose"][0][3] = 0.5
    (out / "lighting.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    with pytest.raises(ValueError, match=r"frame 1's pose is not .*rec's \(1 of the run's frames differ\)"):
        score(out, rec)


def test_score_command_prints_and_writes_json(tmp_path, capsys):
    gt = sun_sky_gt()
    out, rec = write_run(tmp_path, gt, [gt, 2 * gt])
    json_path = tmp_path / "res" / "score.json"
    assert cli_main(["score", str(out), "--gt", str(rec), "--json", str(json_path)]) == 0
    text = capsys.readouterr().out
    assert "direction_deg" in text and "irradiance_si_rmse_upper" in text and "p90" in text
    saved = json.loads(json_path.read_text())
    assert saved["lighting"]["n_scored"] == 2
    assert cli_main(["score", str(tmp_path / "missing"), "--gt", str(rec)]) == 2
    assert "lighting.jsonl" in capsys.readouterr().err
    assert cli_main(["score", str(out), "--gt", str(rec), "--json", str(tmp_path / "res")]) == 2   # a folder
    assert f"{tmp_path / 'res'} (--json) is a folder" in capsys.readouterr().err
    # a file of the run's is not overwritten; scores written there before are
    run_file = out / "lighting.jsonl"
    kept = run_file.read_bytes()
    assert cli_main(["score", str(out), "--gt", str(rec), "--json", str(run_file)]) == 2
    assert "is the run's file" in capsys.readouterr().err and run_file.read_bytes() == kept
    assert cli_main(["score", str(out), "--gt", str(rec), "--json", str(out / "scores.json")]) == 0
    assert cli_main(["score", str(out), "--gt", str(rec), "--json", str(out / "scores.json")]) == 0


# --- composites --------------------------------------------------------------------------------------

def synthetic_insert(h=120, w=160):
    """Camera frame (linear), GT insert render with an object and its shadow, and the object mask."""
    yy, xx = np.mgrid[0:h, 0:w]
    camera = np.dstack([0.2 + 0.3 * xx / w, 0.3 + 0.2 * yy / h, np.full((h, w), 0.25)]).astype(np.float32)
    mask = (abs(yy - 60) < 15) & (abs(xx - 80) < 15)
    shadow = (abs(yy - 75) < 12) & (xx - 80 > -10) & (xx - 80 < 35) & ~mask
    gt = camera.copy()
    gt[shadow] *= 0.4
    gt[mask] = [0.7, 0.1, 0.1]
    return camera, gt, mask


def test_roi_mask_dilation():
    mask = np.zeros((200, 200), bool)
    mask[100, 100] = True
    roi = metrics.roi_mask(mask)
    assert roi[100, 140] and roi[60, 100] and not roi[100, 141] and not roi[71, 71]


def test_composite_metrics_identical_and_baseline():
    camera, gt, mask = synthetic_insert()
    roi = metrics.roi_mask(mask)
    assert metrics.composite_metrics(gt, gt, roi) == {"rmse": 0.0, "si_rmse": 0.0}
    base = metrics.composite_metrics(metrics.no_shadow_baseline(camera, gt, mask), gt, roi)
    assert base["rmse"] > 0.02 and base["si_rmse"] > 0.05
    assert metrics.composite_metrics(2 * gt, gt, roi)["si_rmse"] == pytest.approx(0, abs=1e-7)
    with pytest.raises(ValueError, match="shapes differ"):
        metrics.composite_metrics(gt[:10], gt, roi)


def test_score_composite_end_to_end(tmp_path, capsys):
    camera, gt, mask = synthetic_insert()
    lighting = sun_sky_gt()
    out, rec = write_run(tmp_path, lighting, [lighting] * 3, n_rgb=3)
    for i in range(3):
        write_png_rgb(rec / "rgb" / f"{i:06d}.png", linear_to_srgb(camera))
    for i in (1, 2):
        write_exr(rec / "insert" / f"{i:06d}.exr", gt)
        write_png_rgb(rec / "insert_mask" / f"{i:06d}.png", np.repeat(mask[..., None] * 255, 3, axis=2).astype(np.uint8))
    write_exr(out / "composite_linear" / "000001.exr", gt)          # perfect, linear
    write_png_rgb(out / "composite" / "000002.png", linear_to_srgb(gt))  # perfect up to 8-bit sRGB quantisation
    res = score(out, rec, composite=True)["composite"]
    assert res["n_inserts"] == 2 and res["n_scored"] == 2
    rows = {r["frame"]: r for r in res["per_frame"]}
    assert rows[1]["rmse"] == 0.0 and rows[2]["rmse"] < 3e-3
    assert rows[1]["baseline_rmse"] > 10 * rows[2]["rmse"]
    if not metrics.flip_available():
        assert any("FLIP skipped" in n for n in res["notes"]) and "flip" not in res["metrics"]
    text = format_report(score(out, rec, composite=True))
    assert "baseline_si_rmse" in text
    (out / "composite_linear" / "000001.exr").unlink()
    res = score(out, rec, composite=True)["composite"]
    assert res["n_scored"] == 1 and any("[1]" in n for n in res["notes"])


def test_score_composite_without_inserts(tmp_path):
    lighting = sun_sky_gt()
    out, rec = write_run(tmp_path, lighting, [lighting])
    result = score(out, rec, composite=True)
    c = result["composite"]           # nothing to compare with: said, not a crash
    assert c["notes"] == ["no insert renders"] and c["flicker"] is None and "metrics" not in c
    # one frame: no pair to take a flicker of (was 0, a perfectly stable sequence)
    assert result["lighting"]["flicker"] is None
    flicker_lines = [ln.split() for ln in format_report(result).splitlines() if "flicker" in ln]
    assert flicker_lines == [["flicker", "(sequence)", "-"]]


def test_flip_when_installed():
    pytest.importorskip("flip_evaluator", reason="flip_evaluator not installed: FLIP is optional")
    camera, gt, mask = synthetic_insert()
    roi = metrics.roi_mask(mask)
    assert metrics.composite_metrics(gt, gt, roi, with_flip=True)["flip"] == 0.0
    assert metrics.composite_metrics(metrics.no_shadow_baseline(camera, gt, mask), gt, roi, with_flip=True)["flip"] > 0.01


def test_composite_flicker_over_changed_pixels(tmp_path):
    """Composite flicker counts only the pixels the insertion changed: a 10x10 patch brightened by 0.1 in
    the middle one of three composites gives exp(0.3) - 1 on both pairs; the demo frames' own flicker on
    that patch is reported beside it."""
    from pathlib import Path

    from photoreg.bench.score import composite_flicker
    from photoreg.io.images import read_rgb, srgb_to_linear

    demo = Path(__file__).resolve().parents[1] / "data" / "demo"
    out = tmp_path / "run"
    (out / "composite_linear").mkdir(parents=True)
    for i in range(3):
        cam = srgb_to_linear(read_rgb(demo / "rgb" / f"{i:06d}.png"))
        if i == 1:
            cam[50:60, 70:80] += 0.1
        write_exr(out / "composite_linear" / f"{i:06d}.exr", cam)
    fl = composite_flicker(out, demo)
    assert fl["pixels"] == 100 and fl["frames"] == [0, 1, 2]
    assert fl["composite"] == pytest.approx(math.exp(0.3) - 1.0, rel=1e-2)      # EXR stores half floats
    assert np.isfinite(fl["camera"]) and fl["camera"] < fl["composite"]
    assert composite_flicker(tmp_path / "empty", demo) is None
    gt_only = tmp_path / "gt_only"   # ground truth without the camera frames: no flicker to compare with
    gt_only.mkdir()
    assert composite_flicker(out, gt_only) is None
    # one image has no pair to compare: no flicker figure (bench renderers --frames 1 wrote 0.0000, "perfectly
    # stable"); nothing changed: zero
    region = np.ones((4, 4), bool)
    assert metrics.image_flicker([np.zeros((4, 4, 3))], region) is None
    assert metrics.image_flicker([np.zeros((4, 4, 3))] * 2, ~region) == 0.0


def test_true_light_of_a_generated_recording(tmp_path):
    """The demo's light for a renderer: exposure x the environment's SH, and its sun (elevation 45, azimuth 30
    degrees, 4 degrees wide, irradiance 4) with the exposure; a yaw turns the sun about +z; no suns, no disc."""
    import shutil

    demo = Path(__file__).resolve().parents[1] / "data" / "demo"
    gt = json.loads((demo / "lighting_gt.json").read_text())
    F, sun = true_light(demo)
    assert np.allclose(F, gt["exposure"] * np.asarray(gt["sh"]))
    el, az = math.radians(45.0), math.radians(30.0)
    assert np.allclose(sun["direction"], [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    assert math.degrees(math.acos(np.dot(sun["direction"], sh.dominant_direction(F)))) < 30.0   # the SH agrees
    assert np.isclose(sun["angle"], math.radians(2.0))
    assert np.allclose(sun["irradiance"], gt["exposure"] * 4.0 * np.array([1.0, 0.92, 0.8]))
    for name in ("lighting_gt.json", "scene.json"):
        shutil.copy(demo / name, tmp_path / name)
    scene = json.loads((tmp_path / "scene.json").read_text())
    scene["lighting"]["yaw_deg"] = 90.0
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    _, turned = true_light(tmp_path)
    assert np.allclose(turned["direction"], Rotation.from_euler("z", 90, degrees=True).apply(sun["direction"]))
    scene["lighting"]["suns"] = []
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    assert true_light(tmp_path)[1] is None


def test_light_direction_error_of_the_traced_light(tmp_path):
    """With a generated recording's sun (scene.json), `photoreg score` also scores the traced light's direction
    (diagnostics.sun.direction) against it: the angle itself, 90 degrees for a frame that held no light (noted);
    without scene.json (a recording that only has lighting_gt.json) the metric is left out."""
    demo = Path(__file__).resolve().parents[1] / "data" / "demo"
    _, sun = true_light(demo)
    true = np.asarray(sun["direction"])
    axis = np.cross(true, [0, 0, 1])
    tilted = Rotation.from_rotvec(np.radians(7.0) * axis / np.linalg.norm(axis))
    gt = json.loads((demo / "lighting_gt.json").read_text())
    F = np.asarray(gt["sh"])
    lines = [json.dumps({"frame": i, "bands": sh.bands_of(F.shape[1]), "sh": F.tolist(),
                         "diagnostics": {"sun": None if d is None else {"direction": list(d)}}})
             for i, d in enumerate([true, tilted.apply(true), None])]
    out, rec = write_run(tmp_path, F, lines)
    result = score(out, rec)["lighting"]
    assert "light_direction_deg" not in result["metrics"]            # no scene.json: no true sun
    (rec / "scene.json").write_text((demo / "scene.json").read_text())
    result = score(out, rec)["lighting"]
    errors = [r["light_direction_deg"] for r in result["per_frame"]]
    assert errors[0] == pytest.approx(0.0, abs=1e-6) and errors[1] == pytest.approx(7.0, abs=1e-6)
    assert errors[2] == metrics.NO_DIRECTION_DEG
    assert result["metrics"]["light_direction_deg"]["median"] == pytest.approx(7.0, abs=1e-6)
    assert any("1 frame(s) without a traced light" in n for n in result["notes"])
    assert "light_direction_deg" in format_report(score(out, rec))


def test_a_tracked_run_is_scored_in_the_recording_s_world(tmp_path):
    """A `--no-poses` run's lighting lies in its first camera's frame: score turns it into the recording's world by
    a frame's recorded and tracked poses, so the demo tracked scores as the demo lit from its recorded poses (before:
    113 against 13 degrees, si-RMSE 0.74 against 0.07 over 10 frames)."""
    demo = Path(__file__).resolve().parents[1] / "data" / "demo"
    scores = {}
    for name, extra in (("recorded", []), ("tracked", ["--no-poses"])):
        out = tmp_path / name
        assert cli_main(["run", str(demo), "--out", str(out), "--frames", "0:4", "--rays", "16", "--stride", "8",
                         "--device", "cpu", "--quiet", *extra]) == 0
        scores[name] = score(out, demo)["lighting"]
    med = {k: {m: v["metrics"][m]["median"] for m in ("direction_deg", "irradiance_si_rmse_upper")}
           for k, v in scores.items()}
    assert abs(med["tracked"]["direction_deg"] - med["recorded"]["direction_deg"]) < 5, med
    assert abs(med["tracked"]["irradiance_si_rmse_upper"] - med["recorded"]["irradiance_si_rmse_upper"]) < 0.03, med
    assert any("a tracked run (--no-poses): its lighting turned into the recording's world by frame 0" in n
               for n in scores["tracked"]["notes"])
    # a library run writes no summary.json: its poses tell a tracked run from one lit from the recorded poses
    for name in scores:
        (tmp_path / name / "summary.json").unlink()
        again = score(tmp_path / name, demo)["lighting"]
        assert again["metrics"]["direction_deg"]["median"] == pytest.approx(scores[name]["metrics"]["direction_deg"][
            "median"]), name
    # the frames the runs were asked for (summary.json), not the recording's 40, are what may be missing
    assert all(v["n_frames"] == 4 and v["n_missing"] == 0 and v["nonfinite_fraction"] == 0 for v in scores.values())
    # a broken first pose (singular) is passed over: the next frame relates the worlds (before: 'Singular matrix')
    path = tmp_path / "tracked" / "lighting.jsonl"
    lines = [json.loads(x) for x in path.read_text().splitlines()]
    lines[0]["pose"] = [[0.0] * 4] * 4
    path.write_text("".join(json.dumps(x) + "\n" for x in lines))
    again = score(tmp_path / "tracked", demo)["lighting"]
    assert any("by frame 1" in n for n in again["notes"]), again["notes"]


def test_scores_stay_finite_and_honest_on_broken_input(tmp_path):
    """A negated estimate scores as no signal (si-RMSE 1; before, as well as the truth), a tiny or huge scale of the
    truth scores 0 (before: 37.9 degrees, and 1.0 with an overflow at 1e160); composites: an insert frame showing no
    object is left out, not a perfect score, one with a NaN pixel near the object is named, not NaN in strict JSON,
    one of another size is an error naming its file; malformed lighting.jsonl fields are named."""
    gt = sun_sky_gt()
    normals = metrics.UPPER_NORMALS
    assert metrics.irradiance_si_rmse(-gt, gt, normals) == pytest.approx(1.0)
    for scale in (1e-13, 1e160):
        assert metrics.irradiance_si_rmse(scale * gt, gt, normals) == pytest.approx(0.0, abs=1e-9)
        assert metrics.direction_error_deg(scale * gt, gt) == pytest.approx(0.0, abs=1e-6)

    camera, truth, mask = synthetic_insert()
    out, rec = write_run(tmp_path, gt, [gt] * 4, n_rgb=4)
    for i in range(4):
        write_png_rgb(rec / "rgb" / f"{i:06d}.png", linear_to_srgb(camera))
    for i, m in ((1, mask), (2, mask), (3, np.zeros_like(mask))):
        write_exr(rec / "insert" / f"{i:06d}.exr", truth)
        write_png_rgb(rec / "insert_mask" / f"{i:06d}.png", np.repeat(m[..., None] * 255, 3, axis=2).astype(np.uint8))
    broken = truth.copy()
    broken[mask] = np.nan
    for i, img in ((1, truth), (2, broken), (3, truth)):
        write_exr(out / "composite_linear" / f"{i:06d}.exr", img)
    res = score(out, rec, composite=True)["composite"]
    assert res["n_inserts"] == 3 and res["n_scored"] == 1 and [r["frame"] for r in res["per_frame"]] == [1, 2]
    assert any("[3] show no object" in n for n in res["notes"])
    assert any("[2] holds non-finite" in n for n in res["notes"])
    assert res["flicker"]["nonfinite_frames"] == [2] and np.isfinite(res["flicker"]["composite"])
    assert cli_main(["score", str(out), "--gt", str(rec), "--composite", "--json", str(tmp_path / "s.json")]) == 0
    json.loads((tmp_path / "s.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in strict JSON"))
    write_exr(out / "composite_linear" / "000001.exr", truth[:60, :80])
    with pytest.raises(ValueError, match=r"000001.exr: 80x60, but the ground truth's frame 1 is 160x120"):
        score(out, rec, composite=True)

    for bad, message in (('"bands": "5"', "'bands' must be an integer in 1..16, got '5'"),
                         ('"diagnostics": [1]', "'diagnostics' must be an object, got list"),
                         ('"diagnostics": {"sun": [0, 0, 1]}', "'diagnostics.sun' must be an object or null")):
        (out / "lighting.jsonl").write_text('{"frame": 0, "sh": null, ' + bad + "}\n")
        with pytest.raises(ValueError, match=re.escape(f"lighting.jsonl:1: {message}")):
            score(out, rec)
    (out / "lighting.jsonl").write_bytes(b'{"frame": 0, "sh": null}\n\xff\n')
    with pytest.raises(ValueError, match=r"lighting.jsonl:2: malformed JSON"):
        score(out, rec)

