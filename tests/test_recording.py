"""Recording readers: the shared TUM and ICL-NUIM recordings, native and 7-Scenes folders written here,
and every kind of bad input giving an error that names the file (and line)."""
from __future__ import annotations

import dataclasses
import json
import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from photoreg.cli import main
from photoreg.config import load_session
from photoreg.io.poses import check_pose, format_tum_line, interpolate_poses, read_tum_trajectory
from photoreg.io.recording import iter_frames, open_recording
from photoreg.io.redwood import numbered
from photoreg.io.tum import associate, read_timestamped
from photoreg.types import Intrinsics

W, H = 8, 6
DEPTH_SCALE = 5000.0


@pytest.fixture(scope="module")
def tum_path(data_dir) -> Path:
    return data_dir / "recordings" / "tum_fr1_rpy"


@pytest.fixture(scope="module")
def icl_path(data_dir) -> Path:
    return data_dir / "recordings" / "iclnuim_livingroom1"


def gt_pose(t: float) -> np.ndarray:
    """A smooth made-up trajectory: constant-rate turn about a fixed axis, linear translation
    (what slerp plus linear interpolation reproduce exactly)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec((t - 100.0) * np.array([0.3, 0.5, 0.1])).as_matrix()
    T[:3, 3] = [t - 100.0, 0.5, 2.0 * (t - 100.0)]
    return T


def write_native(root: Path, n: int = 3) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A tiny native recording (TUM layout + intrinsics.json + groundtruth.txt); returns the images written."""
    rng = np.random.default_rng(0)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    colors, raws = [], []
    rgb_lines, depth_lines = ["# colour images", "# timestamp filename"], ["# depth maps", "# timestamp filename"]
    for i in range(n):
        t = 100.0 + i / 30
        color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        raw = rng.integers(1, 30000, (H, W)).astype(np.uint16)
        raw[0, 0] = 0
        cv2.imwrite(str(root / f"rgb/{i:06d}.png"), cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / f"depth/{i:06d}.png"), raw)
        rgb_lines.append(f"{t:.6f} rgb/{i:06d}.png")
        depth_lines.append(f"{t + 0.005:.6f} depth/{i:06d}.png")
        colors.append(color)
        raws.append(raw)
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    gt_times = np.arange(99.9, 100.0 + n / 30 + 0.1, 0.01)
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n"
                                          + "".join(format_tum_line(t, gt_pose(t)) + "\n" for t in gt_times))
    (root / "intrinsics.json").write_text(json.dumps(
        {"width": W, "height": H, "fx": 10.0, "fy": 11.0, "cx": 3.5, "cy": 2.5, "depth_scale": DEPTH_SCALE}))
    return colors, raws


def write_7scenes(root: Path, n: int = 2) -> None:
    """A tiny 7-Scenes sequence at the default 640x480 size, one invalid (65535) depth pixel per frame."""
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(root / f"frame-{i:06d}.color.png"), np.full((480, 640, 3), 40 * i, np.uint8))
        raw = np.full((480, 640), 1500, np.uint16)
        raw[0, 0] = 65535
        raw[0, 1] = 0
        cv2.imwrite(str(root / f"frame-{i:06d}.depth.png"), raw)
        T = gt_pose(100.0 + i)
        (root / f"frame-{i:06d}.pose.txt").write_text("".join("\t".join(f"{x:.7e}" for x in row) + "\t\n" for row in T))


def line_of(path: Path, text: str) -> int:
    """1-based number of the first line of `path` containing `text`."""
    return next(n for n, line in enumerate(path.read_text().splitlines(), 1) if text in line)


# --- the shared recordings ---------------------------------------------------------------------------

def test_tum_recording(tum_path):
    rec = open_recording(tum_path)
    assert rec.format == "tum" and len(rec) == 100
    k = rec.intrinsics
    assert (k.width, k.height, k.depth_scale) == (640, 480, 5000.0)
    assert (k.fx, k.fy, k.cx, k.cy) == pytest.approx((517.306408, 516.469215, 318.643040, 255.313989))
    np.testing.assert_allclose(rec.distortion, [0.262383, -0.953104, -0.005358, 0.002628, 1.163314])
    assert np.all(np.diff(rec.timestamps) > 0) and rec.timestamps[0] == pytest.approx(1305031244.261676)
    assert rec.frame_files(0)[0].name == "1305031244.261676.png"
    assert rec.frame_files(0)[1].name == "1305031244.247347.png"
    valid_fraction = []
    for frame in iter_frames(rec, [0, 33, 66, 99]):
        assert frame.color.shape == (480, 640, 3) and frame.color.dtype == np.uint8
        assert frame.depth.shape == (480, 640) and frame.depth.dtype == np.float32
        d = frame.depth[frame.depth > 0]
        assert 0.4 < d.min() and d.max() < 5.5
        valid_fraction.append(d.size / frame.depth.size)
    assert 0.66 < np.mean(valid_fraction) < 0.86


def test_tum_association_matches_associations_txt(tum_path):
    rgb_times, rgb_rows = read_timestamped(tum_path / "rgb.txt", 2)
    depth_times, depth_rows = read_timestamped(tum_path / "depth.txt", 2)
    _, rows = read_timestamped(tum_path / "associations.txt", 4)
    pairs = associate(rgb_times, depth_times)
    assert [(rgb_rows[i][1], depth_rows[j][1]) for i, j in pairs] == [(r[1], r[3]) for r in rows]
    big = np.array([1.7e18, 1.7e18 + 4096])    # where t +- 0.04 rounds to t, equal times still pair
    assert associate(big, big) == [(0, 0), (1, 1)]


def test_tum_poses_interpolated_near_groundtruth(tum_path):
    rec = open_recording(tum_path)
    gt_times, gt_poses = read_tum_trajectory(tum_path / "groundtruth.txt")
    missing = [i for i, T in enumerate(rec.poses) if T is None]
    # the motion-capture trajectory has a 0.13 s gap: bridged (limit 0.25 s), every frame gets a pose
    assert missing == []
    for t, T in zip(rec.timestamps, rec.poses):
        if T is None:
            continue
        check_pose(T, "interpolated")
        j = np.argmin(np.abs(gt_times - t))
        if abs(gt_times[j] - t) >= 0.03:  # inside the 0.13 s mocap gap: interpolated, no sample to compare
            continue
        assert np.linalg.norm(T[:3, 3] - gt_poses[j][:3, 3]) < 0.005
        angle = Rotation.from_matrix(T[:3, :3].T @ gt_poses[j][:3, :3]).magnitude()
        assert np.degrees(angle) < 1.5
    assert rec.frame(0).pose is not None and rec.frame(15).pose is not None


def test_interpolation_refuses_long_gaps():
    ts = np.array([0.0, 0.1, 0.5])
    poses = np.stack([np.eye(4)] * 3)
    out = interpolate_poses(ts, poses, np.array([0.05, 0.3, 0.6]))
    assert out[0] is not None and out[1] is None and out[2] is None


def test_tum_undistort_matches_cv2(tum_path):
    plain = open_recording(tum_path).frame(5)
    rec = open_recording(tum_path, undistort=True)
    frame = rec.frame(5)
    reference = cv2.undistort(plain.color, rec.intrinsics.K, rec.distortion)
    assert np.mean(np.abs(reference.astype(int) - frame.color) > 2) < 1e-3
    assert frame.depth.shape == plain.depth.shape
    # nearest-neighbour: every undistorted depth value is one of the measured ones
    assert np.isin(np.unique(frame.depth), np.unique(plain.depth)).all()
    assert frame.depth[0, 0] == 0  # the corner maps outside the distorted image


def test_icl_recording(icl_path):
    rec = open_recording(icl_path)
    assert rec.format == "redwood" and len(rec) == 211
    k = rec.intrinsics
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy, k.depth_scale) == (640, 480, 525, 525, 319.5, 239.5, 1000)
    np.testing.assert_allclose(rec.timestamps[:3], [0, 1 / 30, 2 / 30])
    assert [p.name for p in rec.frame_files(210)] == ["00210.jpg", "00210.png"]
    assert sum(T is not None for T in rec.poses) == 211
    for T in rec.poses:
        check_pose(T, "icl")
    np.testing.assert_allclose(rec.poses[0], np.eye(4), atol=1e-8)
    frame = rec.frame(100)
    assert frame.color.shape == (480, 640, 3) and frame.depth.dtype == np.float32
    d = frame.depth[frame.depth > 0]
    assert 0.3 < d.min() and d.max() < 6.0 and d.size > 0.9 * frame.depth.size
    np.testing.assert_allclose(frame.pose, rec.poses[100])


def test_info_command(tum_path, icl_path, capsys):
    assert main(["info", str(tum_path)]) == 0
    out = capsys.readouterr().out
    for text in ("format:      tum", "frames:      100", "image size:  640x480", "fx=517.306", "depth scale: 5000",
                 "poses:       yes (100/100 frames)", "time span:   3.736 s", "26.50 frames/s", "% valid"):
        assert text in out
    depth = re.search(r"min ([\d.]+) / median ([\d.]+) / max ([\d.]+) m, ([\d.]+)% valid", out)
    assert 0.4 < float(depth[1]) < float(depth[2]) < float(depth[3]) < 5.5 and 66 < float(depth[4]) < 86

    assert main(["info", str(icl_path)]) == 0
    out = capsys.readouterr().out
    for text in ("format:      redwood", "frames:      211", "fx=525 fy=525 cx=319.5 cy=239.5", "depth scale: 1000",
                 "poses:       yes (211/211 frames)", "30.00 frames/s"):
        assert text in out


def test_info_warns_of_depth_in_other_units(tmp_path, capsys):
    """Depth stored in metres as float images under a depth scale of 5000 reads 0.2 mm away: `photoreg info` says the
    scale looks wrong (a run would find no depth in range and say only that)."""
    write_native(tmp_path)
    for path in (tmp_path / "depth").glob("*.png"):
        cv2.imwrite(str(path.with_suffix(".tiff")), np.full((H, W), 1.5, np.float32))
        path.unlink()
    (tmp_path / "depth.txt").write_text((tmp_path / "depth.txt").read_text().replace(".png", ".tiff"))
    assert main(["info", str(tmp_path)]) == 0
    warning = ("a median depth of 0.0003 m is no depth camera's: is the depth scale (5000 units per metre; float "
               "images in metres need 1) right?")
    assert f"warning:     {warning}" in capsys.readouterr().out
    out = tmp_path / "out"   # a run says so too (it said only that every frame had no usable samples)
    assert main(["run", str(tmp_path), "--out", str(out), "--frames", "1", "--rays", "8", "--bands", "2",
                 "--device", "cpu", "--quiet"]) == 0
    assert f"{tmp_path / 'depth/000000.tiff'}: {warning}" in capsys.readouterr().err
    assert json.loads((out / "summary.json").read_text())["recording_warnings"] == [f"frame 0: {warning}"]
    js = tmp_path / "intrinsics.json"
    js.write_text(js.read_text().replace(f'"depth_scale": {DEPTH_SCALE}', '"depth_scale": 1'))
    assert main(["info", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "median 1.500" in out and "warning" not in out
    js.write_text(js.read_text().replace('"depth_scale": 1', '"depth_scale": 0.001'))   # metres per unit
    with pytest.raises(ValueError, match="depth_scale = 0.001 is no depth image's: it counts the depth image's "
                                         "units per metre"):
        open_recording(tmp_path)


def test_a_principal_point_outside_the_image_is_warned_of(tmp_path):
    """A calibration of a larger image given the size of this one (cy past the image's last row) is warned of."""
    write_native(tmp_path)
    assert not open_recording(tmp_path).warnings
    _replace(tmp_path / "intrinsics.json", '"cy": 2.5', '"cy": 7.5')
    assert open_recording(tmp_path).warnings == [f"the principal point (3.5, 7.5) lies outside the {W}x{H} image: a "
                                                 "calibration of another image size?"]


def test_intrinsics_json_gives_the_distortion(tmp_path):
    """intrinsics.json's "dist" undistorts a native recording (before: refused as an unknown key, and the
    intrinsics.txt beside it, which could hold them, was ignored without a word)."""
    write_native(tmp_path)
    js = tmp_path / "intrinsics.json"
    (tmp_path / "intrinsics.txt").write_text("fx 1\nfy 1\ncx 1\ncy 1\n")
    with pytest.raises(ValueError, match="no distortion coefficients"):
        open_recording(tmp_path, undistort=True)
    assert "intrinsics from intrinsics.json (intrinsics.txt beside it ignored)" in open_recording(tmp_path).notes
    js.write_text(json.dumps({**json.loads(js.read_text()), "dist": [0.2, -0.5, 0.001, 0.002, 0.3]}))
    rec = open_recording(tmp_path, undistort=True)
    np.testing.assert_array_equal(rec.distortion, [0.2, -0.5, 0.001, 0.002, 0.3])
    assert not np.array_equal(rec.frame(0).color, open_recording(tmp_path).frame(0).color)


def test_info_command_error(tmp_path, capsys):
    assert main(["info", str(tmp_path)]) == 2
    assert "not a recognised recording" in capsys.readouterr().err


def test_info_counts_every_missing_file(tmp_path, capsys):
    """Files listed but gone, in frames the depth summary does not read (it samples 5 of 12): all counted."""
    write_native(tmp_path, 12)
    for name in ("rgb/000001.png", "depth/000001.png", "depth/000004.png", "depth/000007.png"):
        (tmp_path / name).unlink()
    assert main(["info", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"missing:     4 listed file(s) of 3 frame(s): frame 1 {tmp_path / 'rgb/000001.png'}, frame 1" in out


def test_output_into_a_closed_pipe_ends_quietly():
    """`photoreg info X | head -1`: the reader gone, the command ends with SIGPIPE's status and no error message
    (before: 'error: [Errno 32] Broken pipe', status 2)."""
    import subprocess
    import sys

    demo = Path(__file__).resolve().parents[1] / "data" / "demo"
    proc = subprocess.Popen([sys.executable, "-m", "photoreg", "info", str(demo)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.close()   # before it writes: its first line meets a closed pipe
    err = proc.stderr.read().decode()
    assert proc.wait(60) == 141 and "Broken pipe" not in err and "Traceback" not in err, err


# --- folders written here ------------------------------------------------------------------------------

def test_native_round_trip(tmp_path):
    colors, raws = write_native(tmp_path)
    rec = open_recording(tmp_path)
    assert rec.format == "native" and len(rec) == 3 and rec.has_poses and rec.distortion is None
    assert rec.intrinsics.to_json() == {"width": W, "height": H, "fx": 10.0, "fy": 11.0, "cx": 3.5, "cy": 2.5,
                                        "depth_scale": DEPTH_SCALE}
    frames = list(rec)
    for i, frame in enumerate(frames):
        assert frame.index == i and frame.timestamp == pytest.approx(100.0 + i / 30)
        np.testing.assert_array_equal(frame.color, colors[i])
        np.testing.assert_allclose(frame.depth, raws[i] / DEPTH_SCALE, rtol=1e-6)
        assert frame.depth[0, 0] == 0
        np.testing.assert_allclose(frame.pose, gt_pose(frame.timestamp), atol=1e-6)
        assert frame.source == str(tmp_path / f"rgb/{i:06d}.png")


def test_pose_time_offset_looks_the_poses_up_later_or_earlier(tmp_path):
    """recording.pose_time_offset: the poses of groundtruth.txt at the frames' times + the offset (a motion-capture
    clock's offset, benchmarks/pose_offset.py); the frames' own times stay; refused where each
    frame has its own pose (7-Scenes) and out of range in a session."""
    write_native(tmp_path / "rec")
    rec = open_recording(tmp_path / "rec", pose_time_offset=-0.028)
    assert any("-28 ms (recording.pose_time_offset)" in n for n in rec.notes)
    for frame in rec:
        assert frame.timestamp == pytest.approx(100.0 + frame.index / 30)
        np.testing.assert_allclose(frame.pose, gt_pose(frame.timestamp - 0.028), atol=1e-6)
        assert not np.allclose(frame.pose, gt_pose(frame.timestamp), atol=1e-3)
    write_7scenes(tmp_path / "7s")
    with pytest.raises(ValueError, match="pose_time_offset applies to poses given by time"):
        open_recording(tmp_path / "7s", pose_time_offset=0.01)
    session = tmp_path / "s.toml"
    session.write_text(f'[recording]\npath = "{tmp_path / "rec"}"\npose_time_offset = -1.5\n')
    with pytest.raises(ValueError, match=r"s.toml: recording.pose_time_offset must be seconds in -1..1, got -1.5"):
        load_session(session)


def test_native_association_without_match(tmp_path, capsys):
    """A colour frame without depth within 0.02 s is left out of the frame order, and a run says so before its frames
    and in summary.json (before: only `photoreg info` did; the later frames' indices shifted without a word)."""
    rec_dir = tmp_path / "rec"
    write_native(rec_dir, n=4)
    lines = (rec_dir / "depth.txt").read_text().splitlines()
    (rec_dir / "depth.txt").write_text("\n".join(lines[:3] + lines[4:]) + "\n")  # frame 1 loses its depth
    rec = open_recording(rec_dir)
    assert [p.name for p in rec.color_files] == ["000000.png", "000002.png", "000003.png"]
    assert [p.name for p in rec.depth_files] == ["000000.png", "000002.png", "000003.png"]
    assert rec.warnings == ["1 of 4 colour frames in rgb.txt have no depth within 0.02 s and are left out (the first: "
                            "rgb/000001.png); frame indices count the frames kept"]
    out = tmp_path / "out"
    assert main(["run", str(rec_dir), "--out", str(out), "--rays", "8", "--bands", "1", "--stride", "4", "--quiet"]) == 0
    assert f"photoreg: {rec_dir}: {rec.warnings[0]}" in capsys.readouterr().err
    assert json.loads((out / "summary.json").read_text())["recording_warnings"] == rec.warnings


def test_text_files_with_a_bom_read_and_other_encodings_named(tmp_path):
    """Files saved by a Windows editor (a UTF-8 byte-order mark) read as without it: a comment on line 1 stays a
    comment (before: rgb.txt:1 'expected 2 fields', intrinsics.txt "unknown key '\\ufeff#'", TOML 'Invalid
    statement'); bytes that are not UTF-8 give an error naming the file (before: the codec's message alone)."""
    from photoreg.config import load_session

    write_native(tmp_path / "rec", n=3)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        path = tmp_path / "rec" / name
        path.write_bytes(b"\xef\xbb\xbf# saved by Notepad\n" + path.read_bytes())
    (tmp_path / "rec" / "intrinsics.json").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "rec" / "intrinsics.json")
                                                        .read_bytes())
    rec = open_recording(tmp_path / "rec")
    assert len(rec) == 3 and rec.has_poses
    session = tmp_path / "s.toml"
    session.write_bytes(b'\xef\xbb\xbf[recording]\npath = "rec"\n')
    assert load_session(session).recording.path == str(tmp_path / "rec")
    session.write_bytes('[recording]\npath = "rec"  # caf\xe9\n'.encode("latin-1"))
    with pytest.raises(ValueError, match=re.escape(f"{session}: not UTF-8 text")):
        load_session(session)
    gt = tmp_path / "rec" / "groundtruth.txt"
    gt.write_bytes(gt.read_bytes() + b"\xff")
    with pytest.raises(ValueError, match=re.escape(f"{gt}: not UTF-8 text")):
        open_recording(tmp_path / "rec")


def test_7scenes(tmp_path):
    write_7scenes(tmp_path, n=3)
    (tmp_path / "README.txt").write_text("not a frame")
    rec = open_recording(tmp_path)
    assert rec.format == "7scenes" and len(rec) == 3
    k = rec.intrinsics
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy, k.depth_scale) == (640, 480, 585, 585, 320, 240, 1000)
    frame = rec.frame(2)
    assert frame.color[0, 0].tolist() == [80, 80, 80]
    assert frame.depth[0, 0] == 0 and frame.depth[0, 1] == 0 and frame.depth[1, 1] == pytest.approx(1.5)
    np.testing.assert_allclose(frame.pose, gt_pose(102.0), atol=1e-6)
    assert frame.timestamp == pytest.approx(2 / 30)


def test_tum_defaults_from_folder_name(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg2_desk"
    write_native(root)
    (root / "intrinsics.json").unlink()
    rec = open_recording(root)
    assert rec.format == "tum"
    assert (rec.intrinsics.fx, rec.intrinsics.cy, rec.intrinsics.depth_scale) == (520.9, 249.7, 5000.0)
    assert rec.distortion[0] == pytest.approx(0.2312)


# --- bad input ------------------------------------------------------------------------------------------

def test_depth_in_openexr_files(tmp_path):
    """Float depth in OpenEXR files (one channel, or Z among several) is read through OpenEXR (OpenCV's EXR reader is
    off in its wheels: every frame was a raw cv2.error)."""
    import OpenEXR

    write_native(tmp_path)
    metres = np.random.default_rng(1).uniform(0.5, 3.0, (H, W)).astype(np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"Z": metres}).write(str(tmp_path / "depth/000001.exr"))
    OpenEXR.File(header, {"Z": metres, "A": metres * 0}).write(str(tmp_path / "depth/000002.exr"))
    _replace(tmp_path / "depth.txt", "depth/000001.png", "depth/000001.exr")
    _replace(tmp_path / "depth.txt", "depth/000002.png", "depth/000002.exr")
    _replace(tmp_path / "intrinsics.json", f'"depth_scale": {DEPTH_SCALE}', '"depth_scale": 1.0')
    rec = open_recording(tmp_path)
    for i in (1, 2):
        np.testing.assert_array_equal(rec.frame(i).depth, metres)
    OpenEXR.File(header, {"P": metres, "Q": metres}).write(str(tmp_path / "depth/000002.exr"))
    with pytest.raises(ValueError, match="000002.exr: depth EXR with channels P, Q"):
        rec.frame(2)


def test_colour_is_read_as_stored_whatever_its_exif_orientation(tmp_path):
    """A JPEG tagged upside down (EXIF orientation 3, as phones write) is read as its pixels are stored, as its depth
    is (OpenCV's IMREAD_COLOR turned it: colour and depth misregistered without a word); the server alike."""
    from PIL import Image

    from photoreg.io.images import read_rgb
    from photoreg.service.protocol import _decode_color

    rng = np.random.default_rng(2)
    pixels = np.kron(rng.integers(0, 256, (6, 8, 3)), np.ones((8, 8, 1))).astype(np.uint8)
    exif = Image.Exif()
    exif[0x0112] = 3
    path = tmp_path / "turned.jpg"
    Image.fromarray(pixels).save(path, quality=95, exif=exif)
    plain = tmp_path / "plain.jpg"
    Image.fromarray(pixels).save(plain, quality=95)
    assert np.array_equal(read_rgb(path), read_rgb(plain))
    got = read_rgb(path).astype(int)
    assert np.abs(got - pixels).mean() < 0.2 * np.abs(got - pixels[::-1, ::-1]).mean()   # not turned
    intr = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    assert np.array_equal(_decode_color("jpeg", path.read_bytes(), intr), read_rgb(plain))


def test_iter_frames_reports_corrupt_frame(tmp_path):
    write_native(tmp_path)
    bad = tmp_path / "rgb/000001.png"
    bad.write_bytes(b"not a png")
    rec = open_recording(tmp_path)
    errors = []
    frames = list(iter_frames(rec, on_error=lambda i, msg: errors.append((i, msg))))
    assert [f.index for f in frames] == [0, 2]
    assert len(errors) == 1 and errors[0][0] == 1 and str(bad) in errors[0][1]
    with pytest.raises(ValueError, match=re.escape(str(bad))):
        list(iter_frames(rec))


def _drop_line(path: Path, text: str) -> None:
    path.write_text("".join(line for line in path.read_text().splitlines(True) if text not in line))


def _replace(path: Path, old: str, new: str) -> None:
    assert old in path.read_text()
    path.write_text(path.read_text().replace(old, new, 1))


def _open_error(root: Path) -> Exception:
    with pytest.raises((ValueError, FileNotFoundError)) as e:
        open_recording(root)
    return e.value


def _frame_error(root: Path, i: int = 1) -> Exception:
    rec = open_recording(root)
    with pytest.raises((ValueError, FileNotFoundError)) as e:
        rec.frame(i)
    return e.value


@pytest.mark.parametrize("case", [
    "missing depth.txt", "unsorted rgb.txt", "malformed rgb.txt", "bad timestamp", "non-finite pose",
    "non-unit quaternion", "broken intrinsics.json", "intrinsics.json missing key", "intrinsics.txt unknown key",
    "intrinsics.json bad shutter", "intrinsics.txt bad shutter", "intrinsics.json unknown key",
    "intrinsics.json bad dist", "normalised focal length", "principal point outside",
    "intrinsics.txt of a larger camera without its size", "pose beyond reach", "intrinsics.txt key twice",
    "colour and depth never pair",
])
def test_index_errors_name_file_and_line(tmp_path, case):
    write_native(tmp_path)
    rgb, gt, js = tmp_path / "rgb.txt", tmp_path / "groundtruth.txt", tmp_path / "intrinsics.json"
    txt = tmp_path / "intrinsics.txt"

    def intrinsics_txt(text: str) -> None:
        """The calibration as intrinsics.txt alone."""
        js.unlink()
        txt.write_text(text)
    if case == "missing depth.txt":
        (tmp_path / "depth.txt").unlink()
        where = str(tmp_path / "depth.txt")
    elif case == "unsorted rgb.txt":
        _replace(rgb, "100.033333", "99.000000")
        where = f"{rgb}:{line_of(rgb, '99.000000')}"
    elif case == "malformed rgb.txt":
        _replace(rgb, "rgb/000001.png", "rgb/000001.png extra")
        where = f"{rgb}:{line_of(rgb, 'extra')}"
    elif case == "bad timestamp":
        _replace(rgb, "100.033333", "1OO.033333")
        where = f"{rgb}:{line_of(rgb, '1OO')}"
    elif case == "non-finite pose":
        first = gt.read_text().splitlines()[5]
        _replace(gt, first, first.split()[0] + " nan 0 0 0 0 0 1")
        where = f"{gt}:6: invalid pose (non-finite translation [nan, 0.0, 0.0])"
    elif case == "non-unit quaternion":
        first = gt.read_text().splitlines()[3]
        _replace(gt, first, first.split()[0] + " 0 0 0 0.5 0 0 0.5")
        where = f"{gt}:4"
    elif case == "broken intrinsics.json":
        js.write_text('{"width": 8,\n "height": 6,\n "fx": }')
        where = f"{js}:3"
    elif case == "normalised focal length":
        js.write_text(json.dumps({**json.loads(js.read_text()), "fx": 0.8, "fy": 0.8}))
        where = f"{js}: fx = 0.8 is under a pixel"
    elif case == "principal point outside":
        js.write_text(json.dumps({**json.loads(js.read_text()), "cy": 1e7}))
        where = f"{js}: cy = 10000000.0 lies far outside the 8x6 image"
    elif case == "intrinsics.txt of a larger camera without its size":
        intrinsics_txt("fx 3000\nfy 3000\ncx 72016\ncy 1512\n")
        where = f"{txt} (size 640x480 assumed: give width and height): cx = 72016.0 lies far outside the 640x480 image"
    elif case == "pose beyond reach":
        first = gt.read_text().splitlines()[3]
        _replace(gt, first, first.split()[0] + " 1e12 0 0 0 0 0 1")
        where = f"{gt}:4: invalid pose (translation [1000000000000.0, 0.0, 0.0] beyond 1e+09 m)"
    elif case == "colour and depth never pair":   # depth stamped in other units
        dep = tmp_path / "depth.txt"
        dep.write_text("".join(f"{float(t) * 1000:.3f} {f}\n" for t, f in (ln.split() for ln in
                                                                           dep.read_text().splitlines()
                                                                           if not ln.startswith("#"))))
        where = f"{tmp_path}: no colour frame of rgb.txt"
    elif case == "intrinsics.txt key twice":
        intrinsics_txt("fx 10\nfy 11\ncx 3.5\ncy 2.5\nfx 12\n")
        where = f"{txt}:5: fx given again (first on line 1)"
    elif case == "intrinsics.json missing key":
        js.write_text('{"width": 8, "height": 6, "fx": 10, "fy": 10, "cx": 3.5}')
        where = f"{js}: missing cy"
    elif case == "intrinsics.json bad shutter":
        js.write_text(json.dumps({**json.loads(js.read_text()), "shutter": 16}))
        where = f"{js}: shutter must be seconds in 0..1, found 16"
    elif case == "intrinsics.json bad dist":
        js.write_text(json.dumps({**json.loads(js.read_text()), "dist": [0.1, 0.0, True, 0.0, 0.0]}))
        where = f"{js}: dist must be 5 finite numbers (k1 k2 p1 p2 k3)"
    elif case == "intrinsics.json unknown key":   # a misspelt depth_scale would take the default
        js.write_text(json.dumps({**json.loads(js.read_text()), "depthscale": 1000}))
        where = f"{js}: unknown key(s) 'depthscale'"
    elif case == "intrinsics.txt bad shutter":
        intrinsics_txt("fx 10\nfy 11\ncx 3.5\ncy 2.5\nshutter -0.01\n")
        where = f"{txt}:5: shutter must be seconds in 0..1"
    else:
        intrinsics_txt("# calibration\nfx 10\nfy 11\ncx 3.5\ncy 2.5\nfocal 3\n")
        where = f"{txt}:6"
    assert where in str(_open_error(tmp_path))


def test_what_the_reader_assumed_is_said(tmp_path):
    """Notes and warnings where the files leave something to a default or give nothing: a depth scale not given (the
    format's), one pose in groundtruth.txt (taken by the frames near it), poses stamped in other units (none
    reaches a frame)."""
    write_native(tmp_path)
    js, gt = tmp_path / "intrinsics.json", tmp_path / "groundtruth.txt"
    assert "intrinsics from intrinsics.json" in open_recording(tmp_path).notes
    js.write_text(json.dumps({k: v for k, v in json.loads(js.read_text()).items() if k != "depth_scale"}))
    assert "intrinsics from intrinsics.json (no depth_scale: 5000 units per metre, the format's)" in \
        open_recording(tmp_path).notes
    lines = [ln for ln in gt.read_text().splitlines() if not ln.startswith("#")]
    gt.write_text(lines[0] + "\n")
    rec = open_recording(tmp_path)
    assert any("holds one pose" in n for n in rec.notes) and rec.poses[0] is not None
    gt.write_text("".join(f"{float(ln.split()[0]) * 1000:.3f} {' '.join(ln.split()[1:])}\n" for ln in lines))
    rec = open_recording(tmp_path)
    assert not rec.has_poses and any("groundtruth.txt gives no frame a pose" in w for w in rec.warnings)


def test_a_jpeg_cut_short_is_an_error_naming_it(tmp_path):
    """A JPEG cut short (a copy interrupted) is refused, naming the file, where OpenCV would decode it with its
    missing rows grey; whole ones are read whatever they hold or have after them (progressive scans, restart markers,
    an EXIF thumbnail, appended binary data with marker-like bytes, as a phone's motion photo); over the socket the
    same."""
    from photoreg.io.images import jpeg_cut_short, read_rgb
    from photoreg.service.protocol import ProtocolError, _decode_color

    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (48, 64, 3), np.uint8)
    data = cv2.imencode(".jpg", img)[1].tobytes()
    thumb = cv2.imencode(".jpg", img[::4, ::4])[1].tobytes()
    exif = b"\xff\xe1" + (len(thumb) + 8).to_bytes(2, "big") + b"Exif\x00\x00" + thumb
    whole = {"plain": data, "progressive": cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes(),
             "restarts": cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_RST_INTERVAL, 2])[1].tobytes(),
             "thumbnail": data[:2] + exif + data[2:], "appended": data + b"\x00\xff\xda\x00" + rng.bytes(4096)}
    for name, jpeg in whole.items():
        assert not jpeg_cut_short(jpeg), name
        image = jpeg if name != "appended" else data
        assert all(jpeg_cut_short(image[:n]) for n in (len(image) // 10, len(image) // 2, len(image) - 2)), name
    cut, extra = tmp_path / "cut.jpg", tmp_path / "extra.jpg"
    (tmp_path / "whole.jpg").write_bytes(data)
    cut.write_bytes(data[:len(data) // 2])
    extra.write_bytes(whole["appended"])
    assert cv2.imread(str(cut)) is not None                # what OpenCV alone would take
    assert np.array_equal(read_rgb(tmp_path / "whole.jpg"), read_rgb(extra))
    with pytest.raises(ValueError, match=re.escape(f"{cut}: JPEG data cut short")):
        read_rgb(cut)
    intr = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    assert _decode_color("jpeg", data, intr).shape == (48, 64, 3)
    with pytest.raises(ProtocolError, match="corrupt jpeg"):
        _decode_color("jpeg", data[:len(data) // 2], intr)


@pytest.mark.parametrize("case", ["missing image", "empty depth", "a header past OpenCV's limits", "corrupt depth",
                                  "8-bit depth", "size mismatch", "size differs from intrinsics"])
def test_frame_errors_name_file(tmp_path, case):
    """A frame's bad image is a ValueError or FileNotFoundError naming it (an empty file and a size past OpenCV's
    limits were raw cv2.error, which ended a run instead of skipping the frame)."""
    write_native(tmp_path)
    color, depth = tmp_path / "rgb/000001.png", tmp_path / "depth/000001.png"
    if case == "missing image":
        color.unlink()
        where = color
    elif case == "empty depth":
        depth.write_bytes(b"")
        where = depth
    elif case == "a header past OpenCV's limits":   # a 70000 x 70000 PNG's header, its checksum right
        data = bytearray(depth.read_bytes())
        data[16:24] = struct.pack(">II", 70000, 70000)
        data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
        depth.write_bytes(bytes(data))
        where = depth
    elif case == "corrupt depth":
        depth.write_bytes(b"\x89PNG garbage")
        where = depth
    elif case == "8-bit depth":
        cv2.imwrite(str(depth), np.zeros((H, W), np.uint8))
        where = depth
    elif case == "size mismatch":
        cv2.imwrite(str(depth), np.zeros((H + 1, W), np.uint16))
        where = depth
    else:
        cv2.imwrite(str(color), np.zeros((H + 1, W, 3), np.uint8))
        cv2.imwrite(str(depth), np.zeros((H + 1, W), np.uint16))
        where = color
    assert str(where) in str(_frame_error(tmp_path))


def test_depth_registered_at_another_resolution_is_scaled_to_the_colour(tmp_path, capsys):
    """A depth map of half the colour's size in x and y (a phone's LiDAR under its camera) is read at the colour's
    size, each depth pixel over the 2 x 2 colour pixels it covers, its values and holes as they are (`photoreg info`
    says so); a depth map of another shape stays an error naming the file."""
    _, raws = write_native(tmp_path)
    depth = tmp_path / "depth/000001.png"
    half = raws[1][::2, ::2].copy()
    half[1, 2] = 0
    cv2.imwrite(str(depth), half)
    frame = open_recording(tmp_path).frame(1)
    got = frame.depth
    assert got.shape == (H, W)
    # kept at its own size for `photoreg stream` (not where undistortion remaps it at the colour's)
    np.testing.assert_array_equal(frame.depth_native, half.astype(np.float32) / np.float32(DEPTH_SCALE))
    undistorted = dataclasses.replace(open_recording(tmp_path), distortion=np.zeros(5), undistort=True)
    assert undistorted.frame(1).depth_native is None and open_recording(tmp_path).frame(0).depth_native is None
    cv2.imwrite(str(tmp_path / "depth/000000.png"), raws[0][::2, ::2].copy())
    assert main(["info", str(tmp_path)]) == 0
    assert f"depth size:  {W // 2}x{H // 2} (first frame), scaled to the colour's" in capsys.readouterr().out
    np.testing.assert_array_equal(got, np.kron(half, np.ones((2, 2))).astype(np.float32) / np.float32(DEPTH_SCALE))
    cv2.imwrite(str(depth), raws[1][:, : W // 2 + 1].copy())
    assert str(depth) in str(_frame_error(tmp_path)) and "another shape" in str(_frame_error(tmp_path))


def test_a_calibration_s_shutter_time_reaches_every_frame(tmp_path, capsys):
    """`shutter` (seconds) in intrinsics.json or intrinsics.txt: the recording's and each frame's (Frame.shutter, what
    the objects' motion blur takes), shown by `photoreg info`; without it None."""
    write_native(tmp_path)
    rec = open_recording(tmp_path)
    assert rec.shutter is None and rec.frame(0).shutter is None
    js = tmp_path / "intrinsics.json"
    js.write_text(json.dumps({**json.loads(js.read_text()), "shutter": 0.012}))
    rec = open_recording(tmp_path)
    assert rec.shutter == 0.012 and {rec.frame(i).shutter for i in range(len(rec))} == {0.012}
    assert main(["info", str(tmp_path)]) == 0 and "shutter:     12 ms" in capsys.readouterr().out
    k = rec.intrinsics
    js.unlink()
    (tmp_path / "intrinsics.txt").write_text(f"fx {k.fx}\nfy {k.fy}\ncx {k.cx}\ncy {k.cy}\nwidth {k.width}\n"
                                             f"height {k.height}\ndepth_scale {k.depth_scale}\nshutter 0.02\n")
    assert open_recording(tmp_path).frame(1).shutter == 0.02


def test_unknown_tum_sensor_asks_for_intrinsics(tmp_path):
    root = tmp_path / "my_recording"
    write_native(root)
    (root / "intrinsics.json").unlink()
    assert "intrinsics.json" in str(_open_error(root))


def _write_redwood(root: Path, icl_path: Path, n: int, ext: str) -> Path:
    """A Redwood folder of n 64 x 48 frames (frame i: colour 10 i, depth 1000 + i units) and ICL-NUIM's first n poses
    as trajectory.log; returns the log."""
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    for i in range(n):
        cv2.imwrite(str(root / f"color/{i:05d}.{ext}"), np.full((48, 64, 3), 10 * i, np.uint8))
        cv2.imwrite(str(root / f"depth/{i:05d}.png"), np.full((48, 64), 1000 + i, np.uint16))
    log = root / "trajectory.log"
    log.write_text("".join(open(icl_path / "trajectory_open3d_estimated.log").readlines()[:5 * n]))
    return log


def test_the_first_frames_of_a_redwood_sequence_with_its_whole_log(tmp_path, icl_path):
    """Three frames kept with the sequence's whole .log (was refused: 'frame 3 out of range'): each has its pose, the
    other records are unused and noted; a log of none of the frames is warned of."""
    root = tmp_path / "icl"
    log = _write_redwood(root, icl_path, 3, "png")
    whole = open(icl_path / "trajectory_open3d_estimated.log").readlines()
    log.write_text("".join(whole[:5 * 10]))
    rec = open_recording(root)
    assert rec.has_poses and all(p is not None for p in rec.poses) and not rec.warnings
    assert "trajectory.log: 7 record(s) of frames past the recording's last unused" in rec.notes
    one_based = "".join(line if k % 5 else "{0} {0} {1}\n".format(k // 5 + 1, k // 5 + 2)
                        for k, line in enumerate(whole[:5 * 3]))
    log.write_text(one_based)   # ids 1, 2, 3: each pose a frame late, warned of
    rec = open_recording(root)
    assert rec.poses[0] is None and "are its ids counted from 1?" in rec.warnings[0]
    log.write_text("".join(whole[5 * 5:5 * 10]))   # frames 5-9 only
    rec = open_recording(root)
    assert not rec.has_poses and rec.warnings == ["trajectory.log gives none of the 3 frames a pose: the camera is "
                                                  "tracked"]


def test_redwood_errors(tmp_path, icl_path):
    root = tmp_path / "icl"
    log = _write_redwood(root, icl_path, 3, "jpg")
    rec = open_recording(root)
    assert rec.format == "redwood" and len(rec) == 3 and rec.has_poses

    _replace(log, "1 1 2\n0.99999139", "1 1 2\n1.99999139")  # not a rotation any more
    assert f"{log}:7" in str(_open_error(root))
    _replace(log, "1 1 2\n1.99999139", "x 1 2\n0.99999139")
    assert f"{log}:6" in str(_open_error(root))
    _replace(log, "x 1 2\n", "7 7 8\n")   # a record past the last frame: unused, and said
    rec = open_recording(root)
    assert rec.poses[1] is None and rec.poses[0] is not None and rec.poses[2] is not None
    assert "trajectory.log: 1 record(s) of frames past the recording's last unused" in rec.notes
    _replace(log, "7 7 8\n", "1 1 2\n")

    with pytest.raises(ValueError, match="no distortion coefficients"):
        open_recording(root, undistort=True)
    (root / "depth/00002.png").unlink()   # paired by number, frame 2 without depth: the test below
    for i in range(2):   # timestamps for names: the first numbers repeat and pair nothing
        (root / f"depth/{i:05d}.png").rename(root / f"depth/1305031102.{i}.png")
    assert "holds 3 images but" in str(_open_error(root))


def test_redwood_pairs_frames_by_number(tmp_path, icl_path):
    """A frame missing from either folder neither shifts the pairs nor the .log's poses onto other frames."""
    root = tmp_path / "icl"
    _write_redwood(root, icl_path, 4, "png")
    (root / "intrinsics.txt").write_text("fx 50\nfy 50\ncx 31.5\ncy 23.5\nwidth 64\nheight 48\ndepth_scale 1000\n")
    full = open_recording(root)
    (root / "color/00001.png").unlink()
    (root / "depth/00002.png").unlink()
    rec = open_recording(root)
    assert len(rec) == 3 and [p.name for p in rec.color_files] == ["00000.png", "00002.png", "00003.png"]
    assert np.allclose(rec.timestamps, [0, 2 / 30, 3 / 30])
    assert any("1 colour image(s) without a depth image" in n for n in rec.notes)
    assert any("1 depth image(s) without a colour image" in n and "00001.png" in n for n in rec.notes)
    assert np.array_equal(rec.poses[1], full.poses[2]) and np.array_equal(rec.poses[2], full.poses[3])
    f = rec.frame(2)
    assert f.color[0, 0, 0] == 30 and abs(f.depth[0, 0] - 1.003) < 1e-6
    assert f"{root / 'depth' / '00002.png'}: no such file" in str(_frame_error(root, 1))


def test_numbered_images_order(tmp_path):
    for name in ["000010-000000333.jpg", "000002-000000066.jpg", "000001-000000033.jpg", "notes.txt"]:
        (tmp_path / name).write_bytes(b"")
    assert [p.name[:6] for p in numbered(tmp_path).values()] == ["000001", "000002", "000010"]
    (tmp_path / "000002-000000066.png").write_bytes(b"")
    with pytest.raises(ValueError, match="same frame number"):
        numbered(tmp_path)


def test_7scenes_errors(tmp_path):
    write_7scenes(tmp_path)
    pose = tmp_path / "frame-000001.pose.txt"
    pose.write_text(pose.read_text().replace("1.0000000e+00", "inf", 1))
    assert str(pose) in str(_open_error(tmp_path))
    write_7scenes(tmp_path)
    (tmp_path / "frame-000001.depth.png").unlink()
    assert "frame-000001.depth.png" in str(_frame_error(tmp_path))


def test_unknown_layout_and_format(tmp_path):
    assert "not a recognised recording" in str(_open_error(tmp_path))
    assert isinstance(_open_error(tmp_path / "absent"), FileNotFoundError)
    write_native(tmp_path)
    with pytest.raises(ValueError, match="unknown recording format"):
        open_recording(tmp_path, fmt="kinect")
    with pytest.raises(IndexError):
        open_recording(tmp_path).frame(3)


def test_atomic_writes_use_the_umask_not_0600(tmp_path):
    import os

    from photoreg.io.atomic import write_text

    old = os.umask(0o022)
    try:
        write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o644


def test_check_pose_rejects_what_is_not_rigid_even_after_a_rigid_pose():
    """check_pose passes the pose its thread checked last at once (a frame's stages check one pose several times):
    anything else is still checked, in this thread and in another."""
    import threading

    good = np.eye(4)
    good[:3, :3] = Rotation.from_euler("xyz", [10.0, 20.0, 30.0], degrees=True).as_matrix()
    good[:3, 3] = [0.1, 0.2, 0.3]
    scaled, nan = good.copy(), good.copy()
    scaled[:3, :3] *= 1.1
    nan[0, 3] = np.nan
    for _ in range(2):
        np.testing.assert_array_equal(check_pose(good, "here"), good)
        with pytest.raises(ValueError, match="there: pose is not a rigid transform"):
            check_pose(scaled, "there")
        with pytest.raises(ValueError, match="not a finite 4x4"):
            check_pose(nan, "there")
    errors = []
    worker = threading.Thread(target=lambda: errors.append(pytest.raises(ValueError, check_pose, scaled, "other")))
    worker.start()
    worker.join()
    assert len(errors) == 1
