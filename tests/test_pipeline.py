"""End-to-end runs of the per-frame pipeline on the demo and the shared real recordings."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from photoreg.cli import main
from photoreg.config import LightingConfig, load_session
from photoreg.recon.tracking import ate_rmse
from photoreg.runner import run_session

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


def test_session_overrides_and_bad_options(tmp_path):
    s = load_session(REPO / "data" / "demo" / "session.toml")
    assert Path(s.recording.path) == (REPO / "data" / "demo").resolve()
    assert main(["run", str(REPO / "data" / "demo"), "--bands", "0", "--out", str(tmp_path)]) == 2
    assert main(["run", str(tmp_path / "missing"), "--out", str(tmp_path)]) == 2


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


def test_tracking_without_poses_on_tum(data_dir, tmp_path):
    """Poses withheld: frame-to-model tracking follows the motion-capture trajectory."""
    out = tmp_path / "track"
    assert main(["run", str(data_dir / "recordings" / "tum_fr1_rpy"), "--no-poses", "--frames", "0:15",
                 "--rays", "8", "--stride", "8", "--out", str(out), "--quiet"]) == 0
    tracking = json.loads((out / "summary.json").read_text())["tracking"]
    assert tracking["failures"] == []
    assert tracking["ate_rmse_m"] < 0.03


def test_ate_is_zero_for_a_rigidly_moved_copy_and_measures_noise():
    rng = np.random.default_rng(0)
    gt = {}
    for i in range(20):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.2).as_matrix()
        T[:3, 3] = [0.1 * i, np.sin(i), 0.05 * i * i]
        gt[i] = T
    A = np.eye(4)
    A[:3, :3] = Rotation.from_euler("xyz", [10, -30, 70], degrees=True).as_matrix()
    A[:3, 3] = [1.0, -2.0, 0.5]
    moved = {i: A @ T for i, T in gt.items()}
    err, align = ate_rmse(moved, gt)
    assert err < 1e-9
    np.testing.assert_allclose(align @ A, np.eye(4), atol=1e-9)
    noisy = {i: T.copy() for i, T in gt.items()}
    for T in noisy.values():
        T[:3, 3] += rng.normal(scale=0.01, size=3)
    assert 0.005 < ate_rmse(noisy, gt)[0] < 0.02
    with pytest.raises(ValueError):
        ate_rmse({0: np.eye(4)}, gt)
