"""`photoreg score OUT --gt RECORDING`: official accuracy of a run against the recording's ground truth.

Lighting: every frame of OUT/lighting.jsonl against RECORDING/lighting_gt.json (metrics in
photoreg.bench.metrics; all are scale-invariant, so the GT "exposure" plays no part), plus the
sequence's flicker (metrics.flicker, no ground truth involved). Frames whose
SH is non-finite, and frames of the recording with no line at all, are counted in
`nonfinite_fraction` and left out of the other metrics.

Composites (--composite): for each insert render RECORDING/insert/NNNNNN.exr, the run's composite
(OUT/composite_linear/NNNNNN.exr, else OUT/composite/NNNNNN.png decoded from sRGB) and the 'no
shadow' baseline (camera frame with the perfect object pasted in) are compared with it over the
object mask RECORDING/insert_mask/NNNNNN.png dilated by 40 px. Composite flicker (any recording with
two or more composites, e.g. a static camera): metrics.image_flicker over the pixels the insertion
changed, beside the camera frames' own flicker there.
"""
from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..io.atomic import check_not_an_input, check_output_file, write_json
from ..io.images import read_exr, read_rgb, srgb_to_linear
from ..config import parse_frames
from ..io.recording import Recording, detect_format, open_recording
from ..lighting import sh
from . import metrics

LIGHTING_METRICS = ("direction_deg", "irradiance_si_rmse_upper", "irradiance_si_rmse_sphere", "colour_deg",
                    "light_direction_deg")
COMPOSITE_METRICS = ("rmse", "si_rmse", "baseline_rmse", "baseline_si_rmse", "flip", "baseline_flip")


def _sh_array(value, bands, where: str) -> np.ndarray:
    """A (3, B*B) float array from JSON (null entries become NaN); ValueError on a wrong shape."""
    try:
        arr = np.array([[np.nan if x is None else x for x in row] for row in value], dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: 'sh' is not a 3 x B*B list of numbers ({e})") from None
    if arr.ndim != 2 or arr.shape[0] != 3:
        raise ValueError(f"{where}: 'sh' must have 3 rows (RGB), got shape {arr.shape}")
    b = math.isqrt(arr.shape[1])
    if b * b != arr.shape[1] or b == 0:
        raise ValueError(f"{where}: 'sh' rows have {arr.shape[1]} coefficients, not a square number")
    if bands is not None and bands != b:
        raise ValueError(f"{where}: band mismatch: 'bands' is {bands} but 'sh' holds {b} bands")
    return arr


def load_gt(recording: str | Path) -> np.ndarray:
    """Ground-truth SH (3, B*B) from RECORDING/lighting_gt.json."""
    path = Path(recording) / "lighting_gt.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no ground-truth lighting (lighting_gt.json) in {recording}")
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: malformed JSON at line {e.lineno}: {e.msg}") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text (byte {e.start})") from None
    if not isinstance(obj, dict) or "sh" not in obj:
        raise ValueError(f"{path}: expected an object with 'bands' and 'sh'")
    if obj.get("frame", "world") != "world":
        raise ValueError(f"{path}: ground truth must be in the world frame, got {obj['frame']!r}")
    gt = _sh_array(obj["sh"], obj.get("bands"), str(path))
    if not np.isfinite(gt).all():
        raise ValueError(f"{path}: ground-truth SH has non-finite values")
    if not gt.any():
        raise ValueError(f"{path}: the ground-truth lighting is zero (no light to score against)")
    return gt


def true_light(recording: str | Path) -> tuple[np.ndarray, dict | None]:
    """The generator's light in the units of a RenderInput (gain 1): exposure times the environment's SH
    (lighting_gt.json, all its bands), and its brightest sun disc as SolveDiagnostics.sun has a traced light
    (world direction, radius in radians, irradiance per channel; None for an HDR map without suns). With it a
    renderer is scored without the lighting estimate's error (photoreg bench renderers)."""
    from ..synth.environment import Sun

    recording = Path(recording)
    sh_gt = load_gt(recording)
    path = recording / "lighting_gt.json"
    try:
        exposure = float(json.loads(path.read_text())["exposure"])
        path = recording / "scene.json"
        sky = json.loads(path.read_text())["lighting"]
        suns = [Sun(**{**s, "colour": tuple(s["colour"])}) for s in sky.get("suns", [])]
        yaw = float(sky.get("yaw_deg", 0.0))
    except (KeyError, TypeError, AttributeError, ValueError) as e:   # JSONDecodeError is a ValueError
        raise ValueError(f"{path}: not as `photoreg synth` writes it ({type(e).__name__}: {e})") from None
    F = exposure * sh_gt
    if not suns:
        return F, None
    sun = max(suns, key=lambda s: s.irradiance * float(np.mean(s.colour)))
    d = Rotation.from_euler("z", yaw, degrees=True).apply(sun.direction())  # -> world
    return F, {"direction": d.tolist(), "angle": math.radians(sun.diameter_deg) / 2.0,
               "irradiance": (exposure * sun.irradiance * np.asarray(sun.colour)).tolist(), "gain": 1.0}


@dataclass
class RunLighting:
    """A run's OUT/lighting.jsonl by frame index."""

    sh: dict[int, np.ndarray]             # SH (3, B*B); non-finite kept as is, 'sh': null -> NaN
    lights: dict[int, list | None]        # the traced light's direction (diagnostics.sun.direction), None: none held
    poses: dict[int, np.ndarray | None]   # the 4x4 pose the frame was lit from, None where it had none
    timestamps: dict[int, float | None]   # the frame's timestamp (s), None where the line gives none


def _numbers(value, shape: tuple[int, ...], where: str, field_name: str) -> np.ndarray | None:
    """`value` as float64 of `shape`, None for null; ValueError naming `where` and the field otherwise."""
    if value is None:
        return None
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != shape:
        size = " x ".join(map(str, shape)) + " numbers" if shape else "a number"
        raise ValueError(f"{where}: {field_name} must be {size} or null, got {value!r}")
    return arr


def load_lighting(out: str | Path) -> RunLighting:
    """OUT/lighting.jsonl read and checked line by line (errors name the file, line and field)."""
    path = Path(out) / "lighting.jsonl"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no per-frame lighting (lighting.jsonl) in {out}")
    run = RunLighting({}, {}, {}, {})
    lines: dict[int, int] = {}
    with path.open(encoding="utf-8", errors="replace") as f:   # a stray byte: the line's JSON error names it
        for lineno, line in enumerate(f, 1):
            if not line.strip():
                continue
            where = f"{path}:{lineno}"
            try:
                obj = json.loads(line)
            except json.JSONDecodeError as e:
                raise ValueError(f"{where}: malformed JSON: {e.msg} (column {e.colno})") from None
            if not isinstance(obj, dict) or "frame" not in obj or "sh" not in obj:
                raise ValueError(f"{where}: expected an object with 'frame' and 'sh'")
            frame = obj["frame"]
            if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
                raise ValueError(f"{where}: 'frame' must be a non-negative integer, got {frame!r}")
            if frame in run.sh:
                raise ValueError(f"{where}: frame {frame} already given on line {lines[frame]}")
            bands = obj.get("bands")
            if bands is not None and (isinstance(bands, bool) or not isinstance(bands, int) or not 1 <= bands <= 16):
                raise ValueError(f"{where}: 'bands' must be an integer in 1..16, got {bands!r}")
            if obj["sh"] is None:
                run.sh[frame] = np.full((3, (bands or 1) ** 2), np.nan)
            else:
                run.sh[frame] = _sh_array(obj["sh"], bands, where)
            diagnostics = obj.get("diagnostics") or {}
            if not isinstance(diagnostics, dict):
                raise ValueError(f"{where}: 'diagnostics' must be an object, got {type(diagnostics).__name__}")
            light = diagnostics.get("sun")
            if light is not None and not isinstance(light, dict):
                raise ValueError(f"{where}: 'diagnostics.sun' must be an object or null, got {type(light).__name__}")
            direction = _numbers(light.get("direction") if isinstance(light, dict) else None, (3,), where,
                                 "diagnostics.sun.direction")
            run.lights[frame] = None if direction is None else direction.tolist()
            run.poses[frame] = _numbers(obj.get("pose"), (4, 4), where, "pose")
            stamp = _numbers(obj.get("timestamp"), (), where, "timestamp")
            run.timestamps[frame] = None if stamp is None else float(stamp)
            lines[frame] = lineno
    if not run.sh:
        raise ValueError(f"{path}: no frames (an empty run's file?)")
    return run


def read_summary(out: str | Path) -> dict:
    """OUT/summary.json ({} where the run wrote none); ValueError naming it where it is not a JSON object."""
    path = Path(out) / "summary.json"
    if not path.is_file():
        return {}
    try:
        obj = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"{path}: not readable as JSON ({e})") from None
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: expected a JSON object (a run's summary), got {type(obj).__name__}")
    return obj


def same_recording(out: str | Path, recording: str | Path, rec: Recording | None, summary: dict,
                   timestamps: dict[int, float | None]) -> str | None:
    """ValueError where the run's frames carry other timestamps than `rec`'s (--gt is not the recording it ran on); a
    note where summary.json names another folder whose frames have the same timestamps (a moved or copied recording),
    ValueError where that folder still holds another ground truth or scene (lighting_gt.json, scene.json: another
    generated recording, whose timestamps all start at 0 s alike), else None."""
    if rec is not None:
        off = [i for i, t in sorted(timestamps.items()) if t is not None and abs(t - rec.timestamps[i]) > 1e-3]
        if off:
            i, ran = off[0], summary.get("recording")
            raise ValueError(f"{out}: frame {i} has timestamp {timestamps[i]:.6f} s, {recording} "
                             f"{rec.timestamps[i]:.6f} s ({len(off)} of the run's {len(timestamps)} frames differ): is "
                             "--gt the recording it ran on" + (f" ({ran})?" if isinstance(ran, str) else "?"))
    ran = summary.get("recording")
    if isinstance(ran, str) and Path(ran).is_absolute() and Path(ran).resolve() != Path(recording).resolve():
        for name in ("lighting_gt.json", "scene.json"):   # timestamps alone: the generator's all start at 0 s
            theirs, ours = Path(ran) / name, Path(recording) / name
            if theirs.is_file() and ours.is_file() and theirs.read_bytes() != ours.read_bytes():
                raise ValueError(f"{out}: the run read {ran}, whose {name} differs from {ours}: is --gt the recording "
                                 "it ran on?")
        return f"the run read {ran}, scored against {recording} (their frames' timestamps agree)"
    return None


def recording_of(recording: str | Path, pose_time_offset: float = 0.0) -> Recording | None:
    """The recording (photoreg.io.recording), its poses looked up as a run with that recording.pose_time_offset did;
    None for a folder that holds ground truth but no recognised recording index."""
    path = Path(recording)
    try:
        detect_format(path)
    except ValueError:
        return None
    return open_recording(path, pose_time_offset=pose_time_offset)


def color_files(recording: str | Path) -> list[Path]:
    """Colour image of each frame in the recording's frame order; [] where recording_of finds no recording."""
    rec = recording_of(recording)
    return [] if rec is None else rec.color_files


def score_lighting(estimates: dict[int, np.ndarray], gt: np.ndarray, expected: Iterable[int] = (),
                   lights: dict[int, list | None] | None = None, sun: dict | None = None) -> dict:
    """Per-frame lighting metrics and their summaries; `expected` frames missing count as non-finite. With the
    run's traced lights (load_lighting) and the true sun (true_light), light_direction_deg too."""
    frames = sorted(set(estimates) | set(expected))
    per_frame, notes = [], []
    n_missing = n_nonfinite = n_no_dir = n_no_light = 0
    for i in frames:
        est = estimates.get(i)
        if est is None:
            n_missing += 1
            per_frame.append({"frame": i, "finite": False, "missing": True})
            continue
        if not np.isfinite(est).all():
            n_nonfinite += 1
            per_frame.append({"frame": i, "finite": False})
            continue
        m = metrics.lighting_metrics(est, gt)
        if not metrics.has_direction(est):
            n_no_dir += 1
        if sun is not None:
            traced = (lights or {}).get(i)
            m["light_direction_deg"] = metrics.light_direction_error_deg(traced, sun["direction"])
            n_no_light += traced is None
        per_frame.append({"frame": i, "finite": True, **m})
    gt_has_dir = metrics.has_direction(gt)
    if not gt_has_dir:
        notes.append("ground truth has no l=1 band: direction error not defined, left out")
        for r in per_frame:
            r.pop("direction_deg", None)
    if n_no_dir:
        notes.append(f"{n_no_dir} frame(s) without an l=1 band: direction error counted as "
                     f"{metrics.NO_DIRECTION_DEG:g} deg (no information)")
    if n_no_light:
        notes.append(f"{n_no_light} frame(s) without a traced light: its direction error counted as "
                     f"{metrics.NO_DIRECTION_DEG:g} deg")
    if n_missing:
        notes.append(f"{n_missing} frame(s) the run selected have no line in lighting.jsonl")
    n_bad = n_missing + n_nonfinite
    est_bands = sorted({sh.bands_of(e.shape[1]) for e in estimates.values()})
    return {"n_frames": len(frames), "n_scored": len(frames) - n_bad, "n_nonfinite": n_nonfinite,
            "n_missing": n_missing, "nonfinite_fraction": n_bad / len(frames) if frames else 0.0,
            "gt_bands": sh.bands_of(gt.shape[1]), "estimate_bands": est_bands,
            "flicker": metrics.flicker([estimates[i] for i in sorted(estimates)]),
            "metrics": {k: metrics.summarize(r.get(k) for r in per_frame) for k in LIGHTING_METRICS
                        if (k != "direction_deg" or gt_has_dir) and (k != "light_direction_deg" or sun is not None)},
            "notes": notes, "per_frame": per_frame}


def _read_mask(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(f"{path}: object mask missing or unreadable")
    return (img.max(axis=2) if img.ndim == 3 else img) > 0


@dataclass
class InsertTruth:
    """One insert frame's ground truth: the path-traced composite, the object mask and its ROI, and the
    camera frame (linear) it was inserted into."""

    frame: int
    gt: np.ndarray
    mask: np.ndarray
    roi: np.ndarray
    camera: np.ndarray

    def baseline(self, with_flip: bool = False) -> dict[str, float]:
        """Errors of the 'no shadow' baseline: the path-traced object pasted, surroundings untouched."""
        return metrics.composite_metrics(metrics.no_shadow_baseline(self.camera, self.gt, self.mask), self.gt,
                                         self.roi, with_flip)


def insert_truth(recording: str | Path) -> list[InsertTruth]:
    """Every insert frame of a generated recording (insert/NNNNNN.exr, insert_mask/NNNNNN.png)."""
    recording = Path(recording)
    inserts = sorted(p for p in (recording / "insert").glob("*.exr") if p.stem.isdigit())
    if not inserts:
        raise FileNotFoundError(f"{recording / 'insert'}: no insert renders (NNNNNN.exr) to score composites against")
    rgb = color_files(recording)
    out = []
    for p in inserts:
        i = int(p.stem)
        if i >= len(rgb):
            raise FileNotFoundError(f"{p}: frame {i} is not a frame of the recording {recording} "
                                    f"({len(rgb)} frames)")
        mask_file = recording / "insert_mask" / f"{p.stem}.png"
        mask, gt, camera = _read_mask(mask_file), read_exr(p), srgb_to_linear(read_rgb(rgb[i]))
        for what, shape in ((mask_file, mask.shape), (rgb[i], camera.shape[:2])):
            if shape != gt.shape[:2]:
                raise ValueError(f"{what}: {shape[1]}x{shape[0]}, but the insert render {p} is "
                                 f"{gt.shape[1]}x{gt.shape[0]}")
        out.append(InsertTruth(i, gt, mask, metrics.roi_mask(mask), camera))
    return out


def score_composites(out: str | Path, recording: str | Path) -> dict:
    """Composite and no-shadow-baseline errors over each insert frame's ROI."""
    out = Path(out)
    truths = insert_truth(recording)
    with_flip = metrics.flip_available()
    notes = [] if with_flip else ["FLIP skipped: flip_evaluator is not installed"]
    per_frame, missing, empty, broken = [], [], [], []
    for t in truths:
        if not t.mask.any():   # no object in view: nothing to score, not a perfect score
            empty.append(t.frame)
            continue
        row = {"frame": t.frame, **{f"baseline_{k}": v for k, v in t.baseline(with_flip).items()}}
        lin, png = out / "composite_linear" / f"{t.frame:06d}.exr", out / "composite" / f"{t.frame:06d}.png"
        source = lin if lin.is_file() else png if png.is_file() else None
        est = None if source is None else read_exr(source) if source == lin else srgb_to_linear(read_rgb(source))
        if est is None:
            missing.append(t.frame)
        elif est.shape != t.gt.shape:
            raise ValueError(f"{source}: {est.shape[1]}x{est.shape[0]}, but the ground truth's frame {t.frame} is "
                             f"{t.gt.shape[1]}x{t.gt.shape[0]}: is --gt the recording the run read?")
        elif not np.isfinite(est[t.roi]).all():
            broken.append(t.frame)
        else:
            row.update(metrics.composite_metrics(est, t.gt, t.roi, with_flip))
        per_frame.append(row)
    if empty:
        notes.append(f"insert frame(s) {empty} show no object (empty insert_mask): left out")
    if missing:
        notes.append(f"no composite for insert frame(s) {missing}: only the baseline is scored there")
    if broken:
        notes.append(f"the composite of insert frame(s) {broken} holds non-finite pixels near the object: only the "
                     "baseline is scored there")
    return {"n_inserts": len(truths), "n_scored": len(per_frame) - len(missing) - len(broken),
            "roi_dilation_px": metrics.ROI_DILATION_PX,
            "flip": with_flip,
            "metrics": {k: metrics.summarize(r.get(k) for r in per_frame)
                        for k in COMPOSITE_METRICS if with_flip or "flip" not in k},
            "notes": notes, "per_frame": per_frame}


def composite_flicker(out: str | Path, recording: str | Path) -> dict | None:
    """Flicker E (metrics.image_flicker) of the run's consecutive composites (composite_linear/; of the recording's
    frames) over the pixels the insertion changed in any of them, beside the camera frames' own flicker on the same
    pixels (sensor or render noise sets that floor); `nonfinite_frames`: composites whose non-finite pixels counted as
    black; None with fewer than two composites."""
    rgb = color_files(recording)
    files = sorted(p for p in (Path(out) / "composite_linear").glob("*.exr")
                   if p.stem.isdigit() and int(p.stem) < len(rgb))
    if len(files) < 2:   # (no camera frames: a folder of ground truth alone)
        return None
    comps = [read_exr(p) for p in files]
    cams = [srgb_to_linear(read_rgb(rgb[int(p.stem)])) for p in files]
    broken = []
    for p, c, cam in zip(files, comps, cams):
        if c.shape != cam.shape:
            raise ValueError(f"{p}: {c.shape[1]}x{c.shape[0]}, but its camera frame {rgb[int(p.stem)]} is "
                             f"{cam.shape[1]}x{cam.shape[0]}: is --gt the recording the run read?")
        if not np.isfinite(c).all():   # counted as black there: flicker, not NaN
            broken.append(int(p.stem))
            np.nan_to_num(c, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    region = metrics.changed_region(comps, cams)
    return {"frames": [int(p.stem) for p in files], "nonfinite_frames": broken, "pixels": int(region.sum()),
            "composite": metrics.image_flicker(comps, region), "camera": metrics.image_flicker(cams, region)}


def selected_frames(summary: dict, n: int) -> list[int]:
    """The frames of an n-frame recording the run was asked for (its summary's settings.frames, as --frames gives
    them; every frame where it does not say)."""
    settings = summary.get("settings")
    try:
        return parse_frames(settings["frames"], n)
    except (ValueError, KeyError, TypeError, AttributeError):
        return list(range(n))


def tracked_to_world(summary: dict, out: str | Path, recording: str | Path, rec: Recording | None,
                     poses: dict[int, np.ndarray | None]) -> tuple[np.ndarray, int] | None:
    """For a run that tracked the camera, whose world is its first tracked camera's frame: (the rotation into the
    recording's world, the frame whose recorded and tracked poses relate the two); None for a run lit from the
    recorded poses. Its summary says which (settings.use_poses); without one (a library run's lighting.jsonl) the
    poses do: a run's that are not the recording's are tracked ones (before: scored in the wrong frame, 113 against
    12.5 degrees on the demo). ValueError where a tracked run has no frame with both. `rec`: recording_of(recording)."""
    settings = summary.get("settings")
    told = settings.get("use_poses", True) if isinstance(settings, dict) else None
    if told is True:
        return None
    recorded = None if rec is None else rec.poses
    for i in sorted(poses):   # the first frame with both (a broken pose of the run's, not a rotation, passed over)
        rigid = poses[i] is not None and np.isfinite(poses[i]).all() and abs(np.linalg.det(poses[i][:3, :3]) - 1) < 1e-3
        if rigid and recorded is not None and i < len(recorded) and recorded[i] is not None:
            turn = recorded[i] @ np.linalg.inv(poses[i])
            if told is None and np.allclose(turn, np.eye(4), atol=1e-4):
                return None
            return turn[:3, :3], i
    if told is None:
        return None
    raise ValueError(f"{out}: a tracked run (--no-poses), its lighting in its first camera's frame, and no frame of "
                     f"{recording} has a recorded pose to turn it into the ground truth's world")


def score(out: str | Path, recording: str | Path, composite: bool = False) -> dict:
    """All scores of run folder `out` against `recording` as a JSON-ready dict. A tracked run's lighting is turned
    into the recording's world first (tracked_to_world); a run whose frames' timestamps are not the recording's is
    refused (same_recording)."""
    gt = load_gt(recording)
    sun = true_light(recording)[1] if (Path(recording) / "scene.json").is_file() else None   # a generated one's
    run = load_lighting(out)
    summary = read_summary(out)
    settings = summary.get("settings")
    offset = settings.get("pose_time_offset", 0.0) if isinstance(settings, dict) else 0.0
    # opened once: its frame count and timestamps and, for a tracked run, its poses (looked up as the run did)
    rec = recording_of(recording, offset if isinstance(offset, float) and math.isfinite(offset) else 0.0)
    n = 0 if rec is None else len(rec)
    foreign = sorted(i for i in run.sh if i >= n) if n else []
    if foreign:
        listed = ", ".join(map(str, foreign[:5])) + (", ..." if len(foreign) > 5 else "")
        raise ValueError(f"{out} holds frame(s) {listed} that {recording} ({n} frames) does not have: is --gt the "
                         "recording it ran on?")
    moved = same_recording(out, recording, rec, summary, run.timestamps)
    estimates, lights = run.sh, run.lights
    turn = tracked_to_world(summary, out, recording, rec, run.poses)
    if turn is not None:
        R, anchor = turn
        estimates = {i: sh.rotate(e, R) for i, e in estimates.items()}
        lights = {i: None if d is None else (R @ np.asarray(d, np.float64)).tolist() for i, d in lights.items()}
    elif rec is not None and rec.poses is not None:   # lit from the recorded poses: they are the recording's
        off = [i for i, P in sorted(run.poses.items()) if P is not None and i < n and rec.poses[i] is not None
               and not np.allclose(P, rec.poses[i], atol=1e-4)]
        if off:
            raise ValueError(f"{out}: frame {off[0]}'s pose is not {recording}'s ({len(off)} of the run's frames "
                             "differ): is --gt the recording it ran on?")
    result = {"out": str(out), "recording": str(recording),
              "lighting": score_lighting(estimates, gt, selected_frames(summary, n), lights, sun)}
    if moved is not None:
        result["lighting"]["notes"].append(moved)
    if turn is not None:
        result["lighting"]["notes"].append(f"a tracked run (--no-poses): its lighting turned into the recording's "
                                           f"world by frame {anchor}'s recorded and tracked poses")
    if composite:
        inserts = any((Path(recording) / "insert").glob("*.exr"))
        result["composite"] = score_composites(out, recording) if inserts else {"notes": ["no insert renders"]}
        result["composite"]["flicker"] = composite_flicker(out, recording)
    return result


def _table(summaries: dict[str, dict]) -> list[str]:
    rows = [f"  {'metric':28s}{'median':>10s}{'mean':>10s}{'p90':>10s}"]
    for name, s in summaries.items():
        cells = "".join(f"{'-':>10s}" if s[k] is None else f"{s[k]:10.4g}" for k in ("median", "mean", "p90"))
        rows.append(f"  {name:28s}{cells}")
    return rows


def format_report(result: dict) -> str:
    """The readable table printed by `photoreg score`."""
    lt = result["lighting"]
    lines = [f"photoreg score: {result['out']} against {result['recording']}",
             f"lighting (GT {lt['gt_bands']} bands, estimate {', '.join(map(str, lt['estimate_bands'])) or '-'} bands): "
             f"{lt['n_frames']} frames, {lt['n_scored']} scored, non-finite or missing "
             f"{lt['n_nonfinite'] + lt['n_missing']} ({100 * lt['nonfinite_fraction']:.1f}%)"]
    lines += _table(lt["metrics"])
    lines.append(f"  {'flicker (sequence)':28s}{'-' if lt['flicker'] is None else format(lt['flicker'], '10.4g'):>10s}")
    lines += [f"  note: {n}" for n in lt["notes"]]
    if "composite" in result:
        c = result["composite"]
        if "metrics" in c:
            lines.append(f"composite (ROI = object mask dilated by {c['roi_dilation_px']} px, linear RGB): "
                         f"{c['n_inserts']} insert frames, {c['n_scored']} composites scored")
            lines += _table(c["metrics"])
        lines += [f"  note: {n}" for n in c["notes"]]
        fl = c["flicker"]
        if fl is not None:
            lines.append(f"composite flicker over {len(fl['frames'])} frames, {fl['pixels']} changed pixels: "
                         f"{fl['composite']:.4g} (camera frames alone {fl['camera']:.4g})")
    return "\n".join(lines)


def _scores(file: Path) -> bool:
    """Whether `file` holds scores `photoreg score --json` wrote."""
    try:
        earlier = json.loads(file.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(earlier, dict) and {"out", "recording", "lighting"} <= earlier.keys()


def score_command(args) -> int:
    """CLI entry: print the report, write --json atomically when given."""
    if getattr(args, "json_out", None):
        check_output_file(args.json_out, "--json")
        check_not_an_input(args.json_out, "--json", {"the run's": args.out, "the recording's": args.gt}, _scores)
    result = score(args.out, args.gt, composite=bool(getattr(args, "composite", False)))
    if getattr(args, "json_out", None):
        write_json(args.json_out, result)
    print(format_report(result))
    return 0
