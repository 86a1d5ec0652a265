"""The WebSocket service (photoreg.service): protocol unit tests, then the real server on loopback with real
pipelines on a small analytic recording (tests/scenes.py, 80x60, few rays): replay equals the direct pipeline,
concurrent and misbehaving clients, malformed messages (hypothesis), limits, shutdown, a load figure."""
from __future__ import annotations

import contextlib
import dataclasses
import gc
import json
import logging
import multiprocessing
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as ws_connect

from photoreg.cli import main
from photoreg.config import Session, load_session
from photoreg.io.images import linear_to_srgb
from photoreg.io.poses import read_tum_trajectory
from photoreg.io.recording import open_recording
from photoreg.pipeline import Pipeline
from photoreg.recon.tracking import ate_rmse
from photoreg.service import client as client_module
from photoreg.service.client import Client, ServiceClosed, connect, encoded_ahead, replay, session_options
from photoreg.service.protocol import (CLIENT_TYPES, ERROR_CODES, Limits, ProtocolError, composite_message, decode,
                                       decode_composite, decode_frame, encode, encode_composite, encode_frame,
                                       hello_message, lighting_message, parse_hello, ready_message,
                                       record_from_lighting, token_option)
from photoreg.service.server import ServerConfig, ServerThread
from photoreg.types import Frame, Intrinsics
from scenes import write_recording

REPO = Path(__file__).resolve().parents[1]
K = Intrinsics(80, 60, 70.0, 70.0, 39.5, 29.5, 5000.0)
OPTIONS = {"lighting": {"bands": 2, "rays": 16, "stride": 4}, "reconstruction": {"voxel_size": 0.02}}
STREAM_ARGS = ["--bands", "2", "--rays", "16", "--stride", "4", "--voxel-size", "0.02", "--quiet"]
N_FRAMES = 6
N_FLOOD = 800   # frames the slow client sends


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return write_recording(tmp_path_factory.mktemp("rec") / "scene", K, N_FRAMES)


def first_frame(recording: Path) -> Frame:
    return open_recording(recording).frame(0)


# ------------------------------------------------------------------------------------------ protocol

def test_frame_encodings_round_trip(recording):
    """Every colour/depth encoding decodes to the frame sent (lossless ones exactly)."""
    frame = first_frame(recording)
    for color in ("png", "rgb8", "jpeg"):
        for depth in ("png16", "u16", "f32"):
            header, payload = decode(encode_frame(frame, 7, color, depth))
            got = decode_frame(header, payload, K, default_index=0)
            assert (got.index, got.timestamp) == (7, frame.timestamp)
            np.testing.assert_array_equal(got.pose, frame.pose)
            np.testing.assert_array_equal(got.depth, frame.depth)
            if color == "jpeg":
                assert np.abs(got.color.astype(int) - frame.color).mean() < 3
            else:
                np.testing.assert_array_equal(got.color, frame.color)


def test_a_frame_s_shutter_time_travels_with_it(recording):
    """frame.shutter (seconds, optional): a frame's own shutter time (render.motion_blur) is sent and decoded with it;
    absent it is None (the session's render.shutter); out of 0..1 or not a number it is a bad_field naming it."""
    frame = first_frame(recording)
    header, payload = decode(encode_frame(dataclasses.replace(frame, shutter=0.012)))
    assert header["shutter"] == 0.012 and decode_frame(header, payload, K, default_index=0).shutter == 0.012
    header, payload = decode(encode_frame(frame))
    assert "shutter" not in header and decode_frame(header, payload, K, default_index=0).shutter is None
    for bad in (-0.01, 1.5, "fast", float("nan")):
        with pytest.raises(ProtocolError, match="frame.shutter") as e:
            decode_frame({**header, "shutter": bad}, payload, K, default_index=0)
        assert e.value.code == "bad_field"


def test_depth_at_a_lower_resolution_is_scaled_to_the_colour(recording):
    """frame.depth with its own width and height (a phone's LiDAR under its camera): decoded at that size and scaled
    to the colour's like a recording's (io.images.registered_depth), in every depth encoding; another shape or a
    size beyond the colour's is a bad_field."""
    frame = first_frame(recording)
    small = np.round(frame.depth[::2, ::2] * K.depth_scale).astype(np.uint16)       # 40 x 30 under 80 x 60
    want = np.kron(small, np.ones((2, 2))).astype(np.float32) / np.float32(K.depth_scale)
    cbytes = cv2.imencode(".png", cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR))[1].tobytes()
    encoded = {"u16": small.astype("<u2").tobytes(), "png16": cv2.imencode(".png", small)[1].tobytes(),
               "f32": (small.astype(np.float32) / np.float32(K.depth_scale)).astype("<f4").tobytes()}

    def message(enc: str, data: bytes, **size) -> bytes:
        return encode({"type": "frame", "timestamp": 0.0,
                       "color": {"encoding": "png", "offset": 0, "length": len(cbytes)},
                       "depth": {"encoding": enc, "offset": len(cbytes), "length": len(data), **size}}, cbytes + data)

    for enc, data in encoded.items():
        got = decode_frame(*decode(message(enc, data, width=40, height=30)), K, default_index=0)
        np.testing.assert_array_equal(got.depth, want, err_msg=enc)
        np.testing.assert_array_equal(got.color, frame.color)
    for w, h, text in ((40, 20, "another shape"), (160, 120, "at most")):
        with pytest.raises(ProtocolError, match=text) as e:
            decode_frame(*decode(message("u16", np.zeros((h, w), "<u2").tobytes(), width=w, height=h)), K,
                         default_index=0)
        assert e.value.code == "bad_field"


def test_text_messages_round_trip():
    hello = parse_hello(decode(encode(hello_message(K, OPTIONS, "tok")))[0], "cpu", Limits())
    assert hello.intrinsics == K and hello.token == "tok" and hello.version == "1.2" and hello.composite == "jpeg"
    assert (hello.session.lighting.bands, hello.session.lighting.rays, hello.session.lighting.stride) == (2, 16, 4)
    assert hello.session.reconstruction.voxel_size == 0.02 and hello.session.device == "cpu"
    record = {"frame": 3, "timestamp": 1.5, "bands": 1, "sh": [[1.0]] * 3, "dominant_direction": [0, 0, 1],
              "diagnostics": {"weak": False}, "timings_ms": {"total": 2.0}}
    msg = decode(encode(lighting_message(record, 4, 12.3456, 1.0)))[0]
    assert msg["type"] == "lighting" and msg["dropped"] == 4 and msg["latency_ms"] == 12.346
    assert record_from_lighting(msg) == record


def test_an_empty_token_is_refused_and_the_environment_s_is_the_default(monkeypatch):
    """An empty --token (or PHOTOREG_TOKEN) is refused, not read as 'no token' or as 'take the environment's'."""
    monkeypatch.setenv("PHOTOREG_TOKEN", "from-env")
    assert token_option(None) == "from-env" and token_option("given") == "given"
    with pytest.raises(ValueError, match="--token is empty"):
        token_option("")
    monkeypatch.setenv("PHOTOREG_TOKEN", " ")
    with pytest.raises(ValueError, match="PHOTOREG_TOKEN is empty"):
        token_option(None)
    monkeypatch.delenv("PHOTOREG_TOKEN")
    assert token_option(None) is None
    assert main(["serve", "--port", "0", "--token", ""]) == 2


def test_objects_name_meshes_in_the_server_s_folder(tmp_path):
    """An object's mesh is a file name in the server's mesh folder, never a path; no folder, no objects."""
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "bunny.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "secret.obj").write_text("v 0 0 0\n")
    (tmp_path / "meshes" / "README.md").write_text("not a mesh: left out of the list of meshes")
    obj = {"mesh": "bunny.obj", "position": [0, 0, 0], "rotation": [0, 0, 90], "scale": 0.1, "albedo": [0.8, 0.8, 0.8]}

    def hello(mesh, meshes=tmp_path / "meshes", **extra):
        options = {"objects": [{**obj, "mesh": mesh}], "render": {"shadows": "shadowmap", "stride": 2,
                                                                  "gbuffer": "raycast", "shutter": 0.01}}
        msg = {**hello_message(K, options), **extra}
        return parse_hello(msg, "cpu", Limits(), meshes)

    h = hello("bunny.obj", composite="png")
    assert h.session.objects[0].mesh == str(tmp_path / "meshes" / "bunny.obj") and h.composite == "png"
    ready = ready_message(h, "cpu", 2, Limits())
    assert ready["compositing"] is True and ready["settings"]["composite"] == "png"
    assert ready["settings"]["render"] == {"shadows": "shadowmap", "light_rays": 16, "stride": 2, "gbuffer": "raycast",
                                           "shutter": 0.01}
    assert ready_message(parse_hello(hello_message(K, OPTIONS), "cpu", Limits()), "cpu", 2, Limits())[
        "compositing"] is False
    for mesh, says in (("../secret.obj", "file name"), (str(tmp_path / "secret.obj"), "file name"),
                       (".hidden", "file name"), ("rabbit.obj", "it has: bunny.obj)")):
        with pytest.raises(ProtocolError, match=re.escape(says)) as e:
            hello(mesh)
        assert e.value.code == "bad_field" and "objects[0].mesh" in e.value.message
    textured = parse_hello(hello_message(K, {"objects": [{**obj, "albedo": "texture", "smooth": True}]}), "cpu",
                           Limits(), tmp_path / "meshes").session.objects[0]   # the mesh's own colour, smooth normals
    assert (textured.albedo, textured.smooth) == ("texture", True)
    session = tmp_path / "textured.toml"                               # what a client asks for from its session file
    session.write_text(f'[recording]\npath = "{REPO / "data" / "demo"}"\n\n[[objects]]\n'
                       f'mesh = "{tmp_path / "meshes" / "bunny.obj"}"\nalbedo = "texture"\nsmooth = true\n')
    sent = session_options(session)["objects"][0]
    assert (sent["mesh"], sent["albedo"], sent["smooth"]) == ("bunny.obj", "texture", True)
    elsewhere = tmp_path / "elsewhere.toml"   # written on the server's machine: its paths are not the client's
    elsewhere.write_text('[recording]\npath = "$SERVER_DATA/rec"\n\n[[objects]]\nmesh = "/srv/meshes/teapot.obj"\n')
    assert session_options(elsewhere)["objects"][0]["mesh"] == "teapot.obj"
    with pytest.raises(ValueError, match="SERVER_DATA"):
        load_session(elsewhere)
    with pytest.raises(ProtocolError, match="albedo") as e:
        parse_hello(hello_message(K, {"objects": [{**obj, "albedo": "wood"}]}), "cpu", Limits(), tmp_path / "meshes")
    assert e.value.code == "bad_field"
    # which object is wrong, named; a boolean is not a number; more objects than the server takes is its limit
    for bad, says in (({"scale": -1.0}, "objects[1].scale must be a positive finite number"),
                      ({"position": [True, 0, 0]}, "objects[1].position must be 3 finite numbers"),
                      ({"colour": "red"}, "unknown key 'objects[1].colour'")):
        with pytest.raises(ProtocolError, match=re.escape(says)) as e:
            parse_hello(hello_message(K, {"objects": [obj, {**obj, **bad}]}), "cpu", Limits(), tmp_path / "meshes")
        assert e.value.code == "bad_field"
    with pytest.raises(ProtocolError, match=r"3 objects, this server takes at most 2") as e:
        parse_hello(hello_message(K, {"objects": [obj] * 3}), "cpu", Limits(max_objects=2), tmp_path / "meshes")
    assert e.value.code == "too_large"
    with pytest.raises(ProtocolError, match="no mesh folder"):
        hello("bunny.obj", meshes=None)
    with pytest.raises(ProtocolError, match="hello.composite"):
        hello("bunny.obj", composite="gif")
    with pytest.raises(ValueError, match="not a folder"):
        ServerConfig(meshes=str(tmp_path / "missing"))


def test_a_mesh_that_does_not_load_is_named_without_the_server_s_folder(tmp_path):
    """A mesh in the server's folder that its pipeline cannot load: the client's error names the mesh, not where
    the server keeps it."""
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\n")   # no faces
    obj = {"mesh": "flat.obj", "position": [0, 0, 1], "rotation": [0, 0, 0], "scale": 0.1, "albedo": [0.8, 0.8, 0.8]}
    with ServerThread(ServerConfig(port=0, device="cpu", meshes=str(tmp_path), processes=False)) as running:
        with ws_connect(running.server.url, compression=None) as ws:
            ws.send(encode(hello_message(K, {**OPTIONS, "objects": [obj]})))
            reply = json.loads(ws.recv(60))
    assert reply["type"] == "error" and reply["code"] == "pipeline", reply
    assert "flat.obj" in reply["message"] and str(tmp_path) not in reply["message"], reply


def test_composite_messages_round_trip():
    linear = np.random.default_rng(0).random((6, 8, 3)).astype(np.float32)
    for encoding in ("png", "jpeg"):
        header, payload = decode(composite_message(4, encode_composite(linear_to_srgb(linear), encoding), encoding))
        index, enc, image = decode_composite(header, payload)
        got = cv2.cvtColor(cv2.imdecode(np.frombuffer(image, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        assert (index, enc, header["type"]) == (4, encoding, "composite") and got.shape == (6, 8, 3)
        if encoding == "png":
            np.testing.assert_array_equal(got, linear_to_srgb(linear))
    with pytest.raises(ProtocolError, match="composite.image.encoding"):
        decode_composite({"type": "composite", "frame": 1, "image": {"encoding": "gif", "offset": 0, "length": 0}},
                         memoryview(b""))


def raw_message(header: dict, payload: bytes) -> bytes:
    """The binary framing as docs/protocol.md gives it, written independently of protocol.encode
    (and letting NaN through, as a careless client's JSON library might)."""
    head = json.dumps(header).encode()
    return struct.pack(">I", len(head)) + head + payload


def _frame_msg(recording, **changes) -> bytes:
    """A frame message with header fields replaced (None deletes a field)."""
    header, payload = decode(encode_frame(first_frame(recording)))
    for key, value in changes.items():
        if value is None:
            del header[key]
        else:
            header[key] = value
    return raw_message(header, bytes(payload))


def _png(img: np.ndarray) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def _frame_with(recording, color=None, depth=None) -> bytes:
    """A frame message whose colour or depth payload is replaced by (encoding, bytes)."""
    frame = first_frame(recording)
    cbytes = color[1] if color else _png(cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR))
    dbytes = depth[1] if depth else _png((frame.depth * K.depth_scale).astype(np.uint16))
    header = {"type": "frame", "timestamp": 1.0, "color": {"encoding": color[0] if color else "png", "offset": 0,
                                                           "length": len(cbytes)},
              "depth": {"encoding": depth[0] if depth else "png16", "offset": len(cbytes), "length": len(dbytes)}}
    return encode(header, cbytes + dbytes)


BAD_HELLOS = [
    ({"version": "2.0"}, "version"),
    ({"version": 1}, "bad_field"),
    ({"intrinsics": None}, "missing_field"),
    ({"intrinsics": {**K.to_json(), "width": 100000, "height": 100000}}, "too_large"),
    ({"intrinsics": {**K.to_json(), "fx": float("nan")}}, "bad_field"),
    ({"intrinsics": {**K.to_json(), "width": 80.5}}, "bad_field"),
    ({"options": {"lighting": {"rays": 2000}}}, "too_large"),
    ({"options": {"lighting": {"bands": 0}}}, "bad_field"),
    ({"options": {"lighting": {"colour": 1}}}, "bad_field"),
    ({"options": {"reconstruction": {"block_count": 10**9}}}, "bad_field"),
    ({"options": {"reconstruction": {"voxel_size": 0.001}}}, "too_large"),
    ({"options": {"reconstruction": {"trunc_voxels": 1e6}}}, "too_large"),
    ({"options": {"objects": [{"mesh": "x", "scale": -1.0}]}}, "bad_field"),
    ({"options": {"track": "yes"}}, "bad_field"),
    ({"options": []}, "bad_field"),
    ({"version": "\u00b2.0"}, "bad_field"),          # a digit to isdigit(), not to int()
    ({"version": "1" * 5000}, "bad_field"),            # past Python's integer-string limit
    ({"intrinsics": {**K.to_json(), "fx": 10 ** 400}}, "bad_field"),   # too large for a float
    ({"options": {"objects": [{"mesh": "x", "albedo": [-5.0, 1e6, 0.0]}]}}, "bad_field"),
    ({"options": {"lighting": {"process_noise": float("inf")}}}, "bad_field"),
    # the light search's and the solves' sizes capped as rays are (before: 3e7 candidates took 19.5 GB in a frame)
    ({"options": {"lighting": {"sun_candidates": 30_000_000}}}, "too_large"),
    ({"options": {"lighting": {"sun_rays": 100_000}}}, "too_large"),
    ({"options": {"render": {"light_rays": 100_000}}}, "too_large"),
    ({"options": {"lighting": {"history": 10**9}}}, "too_large"),
    ({"options": {"lighting": {"max_samples": 10**9}}}, "too_large"),
    ({"options": {"lighting": {"sun_samples": 10**9}}}, "too_large"),
]


@pytest.mark.parametrize("change,code", BAD_HELLOS)
def test_bad_hello_names_the_problem(change, code):
    msg = hello_message(K, {})
    for key, value in change.items():
        if value is None:
            del msg[key]
        else:
            msg[key] = value
    with pytest.raises(ProtocolError) as e:
        parse_hello(msg, "cpu", Limits())
    assert e.value.code == code and e.value.message and not e.value.message.startswith(code)


def _bad_frames(recording) -> list[tuple[bytes | str, str]]:
    frame = first_frame(recording)
    pose = frame.pose.tolist()
    png = _png(cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR))
    big_jpeg = cv2.imencode(".jpg", np.zeros((16, 16, 3), np.uint8))[1].tobytes()
    big_jpeg = big_jpeg.replace(b"\xff\xc0\x00\x11\x08\x00\x10\x00\x10", b"\xff\xc0\x00\x11\x08\xff\xff\xff\xff")
    return [
        (b"\x00\x00", "bad_message"),
        (b"\x00\x00\xff\xff{}", "bad_message"),
        ("not json", "bad_message"),
        ("[1, 2]", "bad_message"),
        ('{"index": 1}', "missing_field"),
        (_frame_msg(recording, timestamp=None), "missing_field"),
        (_frame_msg(recording, timestamp="noon"), "bad_field"),
        (_frame_msg(recording, index=-1), "bad_field"),
        (_frame_msg(recording, index=2 ** 70), "bad_field"),    # past the integers JSON clients hold exactly
        (_frame_msg(recording, timestamp=10 ** 400), "bad_field"),
        (_frame_msg(recording, pose=[[1, 0, 0, 1.7e308], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "bad_field"),
        (_frame_msg(recording, pose=[[float("nan")] * 4] * 4), "bad_field"),   # NaN survives JSON as NaN
        (_frame_msg(recording, pose=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "bad_field"),
        (_frame_msg(recording, pose=pose[:3]), "bad_field"),
        (_frame_msg(recording, color={"encoding": "bmp", "offset": 0, "length": 1}), "bad_field"),
        (_frame_msg(recording, color={"encoding": "png", "offset": 0, "length": 10**9}), "bad_field"),
        (_frame_msg(recording, depth={"encoding": "f32", "offset": 0, "length": 4}), "bad_field"),
        (_frame_with(recording, color=("rgb8", b"\x00" * 10)), "bad_field"),
        (_frame_with(recording, color=("png", png[:40])), "bad_image"),
        (_frame_with(recording, color=("png", b"\x89PNG garbage" * 10)), "bad_image"),
        (_frame_with(recording, color=("png", _png(np.zeros((10, 10, 3), np.uint8)))), "bad_image"),
        (_frame_with(recording, color=("jpeg", big_jpeg)), "bad_image"),
        (_frame_with(recording, depth=("png16", _png(np.zeros((60, 80), np.uint8)))), "bad_image"),
        (_frame_with(recording, depth=("png16", png)), "bad_image"),
    ]


def test_bad_frames_name_the_problem(recording):
    for data, code in _bad_frames(recording):
        with pytest.raises(ProtocolError) as e:
            header, payload = decode(data)
            decode_frame(header, payload, K, default_index=0)
        assert e.value.code == code, (data[:80], e.value)


# ------------------------------------------------------------------------------------------ live server

@pytest.fixture(scope="module")
def server():
    """The real server on a free loopback port, in a background thread, CPU pipelines on threads of its own
    (quicker to start than a process per connection; that mode: test_a_process_per_connection)."""
    with ServerThread(ServerConfig(port=0, device="cpu", max_clients=8, queue=2, idle_timeout=60,
                                   processes=False)) as running:
        yield running


def stream(recording: Path, url: str, out: Path, *extra: str) -> tuple[list[dict], dict]:
    """`photoreg stream` into `out`; returns its lighting.jsonl records and summary."""
    assert main(["stream", str(recording), "--url", url, "--out", str(out), *STREAM_ARGS, *extra]) == 0
    records = [json.loads(line) for line in (out / "lighting.jsonl").read_text().splitlines()]
    return records, json.loads((out / "summary.json").read_text())


def direct_lighting(recording: Path) -> list[np.ndarray]:
    """SH of every frame from photoreg.pipeline.Pipeline run in-process on the same settings."""

    s = Session(device="cpu")
    s.lighting.bands, s.lighting.rays, s.lighting.stride = 2, 16, 4
    s.reconstruction.voxel_size, s.reconstruction.block_count = 0.02, ServerConfig().block_count
    rec = open_recording(recording)
    pipe = Pipeline(s, rec.intrinsics)
    return [pipe.process(frame).lighting.sh for frame in rec]


def test_replay_matches_direct_pipeline(server, recording, tmp_path):
    records, summary = stream(recording, server.server.url, tmp_path / "out")
    assert [r["frame"] for r in records] == list(range(N_FRAMES))
    assert summary["frames_dropped"] == 0 and not summary["errors"] and summary["stopped"] is None
    assert summary["latency_ms"]["p95"] > 0 and summary["device"] == "cpu" and summary["hello_ms"] > 0
    poses = open_recording(recording).poses
    for r, sh in zip(records, direct_lighting(recording)):
        assert set(r) == {"frame", "timestamp", "bands", "sh", "dominant_direction", "diagnostics", "timings_ms",
                          "pose"}
        np.testing.assert_allclose(r["sh"], sh, atol=2e-7)
        np.testing.assert_allclose(r["pose"], poses[r["frame"]], atol=1e-6)   # the frame's own pose, sent back


def test_a_stream_without_poses_is_tracked_and_gets_its_poses_back(server, data_dir, tmp_path):
    """A client that sends no poses (`track`), every 16th frame of TUM fr1_rpy (as a server that drops frames hands
    them over, 20-60 degrees apart): every reply carries the tracked pose, the first frame's camera the world, and
    the trajectory follows the motion capture's."""
    rec_path = data_dir / "recordings" / "tum_fr1_rpy"
    out = tmp_path / "out"
    assert main(["stream", str(rec_path), "--url", server.server.url, "--out", str(out), "--no-poses", "--frames",
                 "0:100:16", "--rays", "8", "--bands", "3", "--stride", "8", "--quiet"]) == 0
    records = [json.loads(line) for line in (out / "lighting.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in records] == list(range(0, 100, 16))
    np.testing.assert_allclose(records[0]["pose"], np.eye(4), atol=1e-12)
    gt = open_recording(rec_path).poses
    tracked = {r["frame"]: np.array(r["pose"]) for r in records}
    assert ate_rmse(tracked, {i: gt[i] for i in tracked})[0] < 0.03
    summary = json.loads((out / "summary.json").read_text())   # scored and written as `photoreg run` does
    assert summary["tracking"]["frames"] == len(records)
    assert summary["tracking"]["ate_rmse_m"] == pytest.approx(ate_rmse(tracked, {i: gt[i] for i in tracked})[0],
                                                             abs=1e-5)
    times, poses = read_tum_trajectory(out / "trajectory.txt")
    np.testing.assert_allclose(poses, [tracked[i] for i in sorted(tracked)], atol=1e-6)
    np.testing.assert_allclose(times, [r["timestamp"] for r in records], atol=1e-6)


def test_a_tracked_stream_reports_its_failures_as_run_does(server, tmp_path):
    """A tracked stream's summary lists the frames whose tracking failed, with the reasons, as `photoreg run
    --no-poses` does (before: its "frames" counted the tracked ones alone, and no failure was listed)."""
    rec = write_recording(tmp_path / "rec", K, N_FRAMES, with_gt=False)
    for depth in sorted((rec / "depth").glob("*.png"))[:2]:   # no depth in the first two: tracking not started
        cv2.imwrite(str(depth), np.zeros((K.height, K.width), np.uint16))
    _, streamed = stream(rec, server.server.url, tmp_path / "streamed", "--no-poses")
    assert main(["run", str(rec), "--no-poses", "--out", str(tmp_path / "ran"), "--device", "cpu", *STREAM_ARGS]) == 0
    ran = json.loads((tmp_path / "ran" / "summary.json").read_text())["tracking"]
    tracking = streamed["tracking"]
    assert tracking["frames"] == ran["frames"] == N_FRAMES and tracking["failures"] == ran["failures"]
    assert [f["frame"] for f in ran["failures"][:2]] == [0, 1]
    assert all(f["reason"].startswith("tracking not started: 0.0% of the pixels") for f in ran["failures"][:2])
    assert (tracking["unconfirmed"], tracking["unconfirmed_frames"]) == (ran["unconfirmed"], ran["unconfirmed_frames"])


def test_depth_registered_at_a_lower_resolution_streams_at_its_own(server, recording, tmp_path):
    """A recording whose depth is half the colour's size (a phone's LiDAR): each frame message carries the depth at
    that size (frame.depth's width and height, a quarter of the bytes in every encoding), which decodes to the depth
    the recording reads at the colour's size; `photoreg stream` of it gives the lighting the pipeline gives
    in-process."""
    import shutil

    half = tmp_path / "half"
    shutil.copytree(recording, half)
    for f in sorted((half / "depth").iterdir()):
        cv2.imwrite(str(f), cv2.imread(str(f), cv2.IMREAD_UNCHANGED)[::2, ::2].copy())
    frame = first_frame(half)
    assert frame.depth.shape == (K.height, K.width) and frame.depth_native.shape == (K.height // 2, K.width // 2)
    full = dataclasses.replace(frame, depth_native=None)
    for enc in ("png16", "u16", "f32"):
        header, payload = decode(encode_frame(frame, None, "png", enc))
        assert (header["depth"]["width"], header["depth"]["height"]) == (K.width // 2, K.height // 2)
        if enc != "png16":
            assert header["depth"]["length"] * 4 == decode(encode_frame(full, None, "png", enc))[0]["depth"]["length"]
        np.testing.assert_array_equal(decode_frame(header, payload, K, default_index=0).depth, frame.depth, err_msg=enc)
    assert "width" not in decode(encode_frame(first_frame(recording)))[0]["depth"]
    records, summary = stream(half, server.server.url, tmp_path / "out")
    assert [r["frame"] for r in records] == list(range(N_FRAMES)) and not summary["errors"]
    for r, sh in zip(records, direct_lighting(half)):
        np.testing.assert_allclose(r["sh"], sh, atol=2e-7)


def test_asynchronous_lighting_through_the_server(server, recording, tmp_path):
    """`photoreg stream --async` asks for lighting.asynchronous (a hello option): frame 0 is estimated in line and
    equals the direct pipeline's, every later reply carries a finite estimate of an earlier frame or its own
    frame's (diagnostics.estimated_frame, never going back), and neither the connection's worker thread nor its solve
    process (lighting.solve_process) outlives the connection."""
    before = set(multiprocessing.active_children())
    records, summary = stream(recording, server.server.url, tmp_path / "out", "--async")
    assert [r["frame"] for r in records] == list(range(N_FRAMES)) and not summary["errors"]
    est = [r["diagnostics"]["estimated_frame"] for r in records]
    assert est[0] == 0 and all(e <= r["frame"] for e, r in zip(est, records)) and est == sorted(est), est
    assert all(np.isfinite(r["sh"]).all() for r in records)
    np.testing.assert_allclose(records[0]["sh"], direct_lighting(recording)[0], atol=2e-7)

    def left() -> list:   # the connection's worker thread and solve process (lighting.solve_process)
        return ([t for t in threading.enumerate() if t.name.startswith("photoreg-lighting")]
                + list(set(multiprocessing.active_children()) - before))

    deadline = time.monotonic() + 30
    while left() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not left()


def test_stream_reads_the_recording_as_its_session_says(server, recording, tmp_path, capsys):
    """`photoreg stream REC --session S.toml` opens REC as `photoreg run S.toml` opens its recording: the session's
    [recording] format (before: autodetected, whatever the session said) and its frames unless --frames is given."""
    session = tmp_path / "s.toml"
    session.write_text('frames = "1:3"\n[recording]\npath = "elsewhere"\nformat = "redwood"\n')
    assert main(["stream", str(recording), "--url", server.server.url, "--session", str(session), *STREAM_ARGS]) == 2
    assert "no color/ or image/ folder" in capsys.readouterr().err
    session.write_text('frames = "1:3"\n[recording]\npath = "elsewhere"\nformat = "native"\n')
    records, _ = stream(recording, server.server.url, tmp_path / "out", "--session", str(session))
    assert [r["frame"] for r in records] == [1, 2]
    records, _ = stream(recording, server.server.url, tmp_path / "out2", "--session", str(session), "--frames", "1")
    assert [r["frame"] for r in records] == [0]


def test_streamed_composites_equal_the_direct_pipeline_s(tmp_path):
    """`photoreg stream data/demo --session data/demo/session.toml --composite png --every 2 --render-stride 2`
    through a server whose mesh folder holds the demo's object: each frame's composite arrives (after its lighting)
    and equals, pixel for pixel, what the pipeline composites in-process for that session (photoreg run's
    composite/NNNNNN.png), the frame between estimates (lighting.every, a hello option) included."""
    demo = REPO / "data" / "demo"
    with ServerThread(ServerConfig(port=0, device="cpu", idle_timeout=60, meshes=str(demo), processes=False)) as running:
        out = tmp_path / "out"
        assert main(["stream", str(demo), "--url", running.server.url, "--out", str(out), "--session",
                     str(demo / "session.toml"), "--frames", "0:3", "--rays", "16", "--composite", "png",
                     "--every", "2", "--render-stride", "2", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["composites"] == 3 and summary["settings"]["composite"] == "png" and not summary["errors"]
    assert summary["settings"]["render"]["stride"] == 2
    records = [json.loads(line) for line in (out / "lighting.jsonl").read_text().splitlines()]
    assert ["solve" in r["timings_ms"] for r in records] == [True, False, True]
    s = load_session(demo / "session.toml")
    s.device, s.lighting.rays, s.lighting.every, s.render.stride = "cpu", 16, 2, 2
    s.reconstruction.block_count = ServerConfig().block_count
    rec = open_recording(demo)
    pipe = Pipeline(s, rec.intrinsics)
    for i in range(3):
        composite = pipe.process(rec.frame(i)).composite
        got = cv2.cvtColor(cv2.imread(str(out / "composite" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(got, linear_to_srgb(composite))


def test_a_composite_crosses_to_the_server_as_its_region(tmp_path):
    """A connection's pipeline hands the server only the box of the composite that differs from the frame
    (host.CompositePatch): on the demo 81% of the frame, and the frame's colour with the box converted is the
    whole composite in sRGB, pixel for pixel; with the luminance denoised (lighting.denoise) the pipeline's colour is
    not the frame's, and the box is the whole frame."""
    from photoreg.service.host import PipelineHost

    demo = REPO / "data" / "demo"
    rec = open_recording(demo)
    frames = [rec.frame(i) for i in range(2)]
    for denoise in ("none", "guided"):
        s = load_session(demo / "session.toml")
        s.device, s.lighting.rays, s.lighting.denoise = "cpu", 16, denoise
        pipe = Pipeline(s, rec.intrinsics)
        expected = [pipe.process(f).composite for f in frames]
        pipe.close()
        host = PipelineHost(False)
        try:
            host.open(s, rec.intrinsics).result()
            patches = [host.process(f).result()[2] for f in frames]
        finally:
            host.close()
        for f, patch, composite in zip(frames, patches, expected):
            x0, y0, x1, y1 = patch.box
            share = (x1 - x0) * (y1 - y0) / (rec.intrinsics.width * rec.intrinsics.height)
            assert share < 1.0 if denoise == "none" else share == 1.0, (denoise, patch.box)
            np.testing.assert_array_equal(patch.over(f.color), linear_to_srgb(composite))


def test_frames_are_encoded_ahead_in_order_and_bounded(recording):
    """encoded_ahead: the messages of protocol.encode_frame, in the frames' order, on several threads; it draws at
    most 2 * threads + 1 frames beyond the one the caller holds, and stops drawing when the caller stops."""
    first_frames = list(open_recording(recording))
    frames = [dataclasses.replace(first_frames[k % len(first_frames)], index=k) for k in range(20)]
    drawn = []

    def source():
        for frame in frames:
            drawn.append(frame.index)
            yield frame

    got = iter(encoded_ahead(source(), "png", "png16", threads=2))
    first, message = next(got)
    time.sleep(0.3)   # time to draw all it may
    assert first.index == 0 and message == encode_frame(frames[0], None, "png", "png16")
    assert len(drawn) == 1 + 2 * 2 + 1
    rest = [(f.index, m) for f, m in got]
    assert rest == [(f.index, encode_frame(f, None, "png", "png16")) for f in frames[1:]]
    drawn.clear()
    ahead = encoded_ahead(source(), "png", "png16", threads=1)
    next(iter(ahead))
    ahead.close()
    assert len(drawn) <= 1 + 2 + 1


def test_the_next_frame_is_handed_in_and_runs_while_a_composite_is_encoded(tmp_path, monkeypatch):
    """The server hands the pipeline the next queued frame while it runs one, and encodes a done frame's composite
    while the next one runs: with the encoding slowed down (0.5 s a composite), frame 1 is handed in before frame
    0's pipeline is done and runs before frame 0's composite is encoded; the composites still arrive, in order,
    after their lighting."""
    import photoreg.service.server as server_module
    from photoreg.service.host import PipelineHost

    events = []
    encode, process, hand = server_module.encode_composite, Pipeline.process, PipelineHost.process

    def slow_encode(composite, encoding):
        events.append(("encode start", time.perf_counter()))
        time.sleep(0.5)
        events.append(("encode end", time.perf_counter()))
        return encode(composite, encoding)

    def recorded_process(self, frame):
        events.append((f"process {frame.index}", time.perf_counter()))
        result = process(self, frame)
        events.append((f"done {frame.index}", time.perf_counter()))
        return result

    def recorded_hand(self, frame):
        events.append((f"handed {frame.index}", time.perf_counter()))
        return hand(self, frame)

    monkeypatch.setattr(server_module, "encode_composite", slow_encode)
    monkeypatch.setattr(Pipeline, "process", recorded_process)
    monkeypatch.setattr(PipelineHost, "process", recorded_hand)
    demo = REPO / "data" / "demo"
    with ServerThread(ServerConfig(port=0, device="cpu", idle_timeout=60, meshes=str(demo), processes=False,
                                   queue=4)) as running:
        client = connect(running.server.url, open_recording(demo).intrinsics,
                         {**session_options(demo / "session.toml"), "lighting": {"rays": 16, "bands": 2}})
        order = []
        summary = replay(client, list(open_recording(demo))[:3], window=3,
                         on_record=lambda r: order.append(("lighting", r["frame"])),
                         on_composite=lambda i, enc, image: order.append(("composite", i)))
    assert summary["composites"] == 3 and not summary["errors"]
    assert order == [(kind, i) for i in range(3) for kind in ("lighting", "composite")]
    at = dict(events[::-1])   # the first time of each event
    assert at["handed 1"] < at["done 0"] and at["process 1"] < at["encode end"]


def test_a_reply_that_cannot_be_encoded_is_an_error_and_the_replies_go_on(recording, monkeypatch):
    """A frame whose reply cannot be encoded (a value JSON cannot hold: NaN, as a pose 1e308 m off once gave): that
    frame gets an 'internal' error naming it, the frames after it their replies, and bye its answer. Before, the
    connection's replies stopped there for good, and the client slot and the server's shutdown waited for ever."""
    import photoreg.service.server as server_module

    made = server_module.lighting_message

    def with_nan(record, *args):
        msg = made(record, *args)
        return {**msg, "latency_ms": float("nan")} if record["frame"] == 1 else msg

    monkeypatch.setattr(server_module, "lighting_message", with_nan)
    with ServerThread(ServerConfig(port=0, device="cpu", idle_timeout=60, processes=False, queue=4)) as running:
        client = connect(running.server.url, open_recording(recording).intrinsics,
                         {"lighting": {"rays": 16, "bands": 2, "stride": 4}})
        summary = replay(client, list(open_recording(recording))[:3], window=1, reply_timeout=60)
    assert summary["frames_processed"] == 2 and summary["server_bye"]["reason"] == "client said bye"
    (error,) = summary["errors"]
    assert error["frame"] == 1 and error["code"] == "internal" and "frame 1: the reply could not be made" in \
        error["message"]


def test_frames_decode_two_at_a_time_and_are_answered_in_order(recording, monkeypatch):
    """The server decodes a connection's frames DECODING (2) at once on helper threads and queues them in the order
    they came: with decoding slowed down (frame 0 0.4 s, the others 0.1 s), two frames are decoding or decoded and
    waiting at once, never three;
    frame 1, decoded first, still waits for frame 0; a frame whose PNG does not decode gets its error (frame 2)
    and the rest are answered in order; a bye after them waits for every reply."""
    import photoreg.service.server as server_module

    real_decode, lock = server_module.decode_frame, threading.Lock()
    state = {"now": 0, "most": 0, "zero": False, "beside_zero": 0}
    decoded = []

    def slow_decode(header, payload, intr, default_index):
        with lock:
            state["now"] += 1
            state["most"] = max(state["most"], state["now"])
            state["beside_zero"] += state["zero"]
            state["zero"] |= header.get("index") == 0
        try:
            time.sleep(0.4 if header.get("index") == 0 else 0.1)
            return real_decode(header, payload, intr, default_index)
        finally:
            with lock:
                state["now"] -= 1
                state["zero"] &= header.get("index") != 0
                decoded.append(header.get("index"))

    monkeypatch.setattr(server_module, "decode_frame", slow_decode)
    frames = list(open_recording(recording))[:5]
    messages = [encode_frame(f) for f in frames]
    header, payload = decode(messages[2])
    payload = bytearray(payload)
    payload[header["color"]["offset"] + 20:header["color"]["offset"] + 60] = b"\x00" * 40   # a corrupt colour PNG
    messages[2] = raw_message(header, bytes(payload))
    with ServerThread(ServerConfig(port=0, device="cpu", idle_timeout=60, processes=False, queue=8)) as running:
        with ws_connect(running.server.url, compression=None) as ws:
            ws.send(encode(hello_message(K, OPTIONS)))
            assert json.loads(ws.recv(60))["type"] == "ready"
            for m in messages:
                ws.send(m)
            ws.send(encode({"type": "bye"}))
            replies = [json.loads(ws.recv(60)) for _ in range(6)]
    assert state["most"] == 2 and decoded.index(1) < decoded.index(0), (state, decoded)
    # frame 1, decoded, holds its slot until frame 0 is taken: no frame decodes beside frame 0 but it (before: 1, 2
    # and 3 did, one after another, piling up decoded behind the slow one)
    assert state["beside_zero"] == 1, state
    errors = [r for r in replies if r["type"] == "error"]
    assert len(errors) == 1 and errors[0]["frame"] == 2, errors
    assert [r["frame"] for r in replies if r["type"] == "lighting"] == [0, 1, 3, 4]
    assert replies[-1]["type"] == "bye" and replies[-1]["frames_processed"] == 4 and replies[-1]["errors"] == 1


def test_a_stream_into_a_folder_another_run_writes_is_refused(server, recording, tmp_path, capsys):
    """`photoreg stream --out` holds its folder as `photoreg run` does: into one another run holds, it is refused
    before it connects and writes nothing there (before: it overwrote the other's lighting.jsonl.partial)."""
    from photoreg.io.atomic import hold_folder

    out = tmp_path / "out"
    out.mkdir()
    fd = hold_folder(out, "test")
    try:
        assert main(["stream", str(recording), "--url", server.server.url, "--out", str(out), *STREAM_ARGS]) == 2
        assert f"output folder {out} (--out) is in use by another run" in capsys.readouterr().err
        assert not any(out.iterdir())
    finally:
        os.close(fd)
    records, _ = stream(recording, server.server.url, out)
    assert records


def test_stream_reports_an_unreadable_frame_and_sends_the_rest(server, tmp_path):
    """`photoreg stream` of a recording with a corrupt colour image: the frames around it are read ahead, sent and
    answered in order; the bad one is named in summary.json's frames_skipped."""
    rec = write_recording(tmp_path / "rec", K, 4)
    bad = open_recording(rec).color_files[2]
    bad.write_bytes(b"not a png")
    records, summary = stream(rec, server.server.url, tmp_path / "out")
    assert [r["frame"] for r in records] == [0, 1, 3] and not summary["errors"]
    (skipped,) = summary["frames_skipped"]
    assert skipped["frame"] == 2 and str(bad) in skipped["error"]


def test_stream_leaves_only_its_own_outputs(server, tmp_path, capsys):
    """A stream into a folder an earlier one wrote: its trajectory and composites that this one did not write are
    gone (photoreg score would take them for this stream's), other files stay; a stream none of whose frames is
    answered replaces nothing (exit status 2, the first unreadable frame named); --window 0 is refused at once."""
    rec = write_recording(tmp_path / "rec", K, 3)
    out = tmp_path / "out"
    stream(rec, server.server.url, out, "--no-poses")
    assert (out / "trajectory.txt").is_file()
    (out / "composite").mkdir()
    for name in ("000010.png", "000000.jpg", "notes.txt"):
        (out / "composite" / name).write_text("earlier")
    records, summary = stream(rec, server.server.url, out)
    assert len(records) == 3 and not (out / "trajectory.txt").exists()
    assert sorted(p.name for p in (out / "composite").iterdir()) == ["notes.txt"]
    before = {name: (out / name).read_bytes() for name in ("lighting.jsonl", "summary.json")}
    for path in open_recording(rec).color_files:
        path.write_bytes(b"not a png")
    capsys.readouterr()
    assert main(["stream", str(rec), "--url", server.server.url, "--out", str(out), *STREAM_ARGS]) == 2
    err = capsys.readouterr().err
    assert "no frame was answered (frame 0: " in err and f"nothing in {out} was replaced" in err
    assert {name: (out / name).read_bytes() for name in before} == before
    assert main(["stream", str(rec), "--url", server.server.url, "--window", "0", *STREAM_ARGS]) == 2
    assert "--window must be >= 1" in capsys.readouterr().err


def test_a_server_that_stops_answering_costs_no_reply_already_received(recording, monkeypatch):
    """The pipeline stalls from frame 1 on (a server that stopped answering): replay stops at the reply timeout like a
    closed connection, keeping frame 0's reply (before: an error, and what had arrived was lost)."""
    process = Pipeline.process

    def stalling(self, frame):
        if frame.index >= 1:
            time.sleep(4.0)
        return process(self, frame)

    monkeypatch.setattr(Pipeline, "process", stalling)
    with ServerThread(ServerConfig(port=0, device="cpu", idle_timeout=60, processes=False, queue=4)) as running:
        client = connect(running.server.url, open_recording(recording).intrinsics,
                         {"lighting": {"rays": 16, "bands": 2, "stride": 4}})
        summary = replay(client, list(open_recording(recording))[:3], window=1, reply_timeout=2.0)
    assert summary["frames_processed"] >= 1 and summary["stopped"] == "no reply from the server within 2 s"


def test_a_stalled_server_ends_the_stream_in_one_line(monkeypatch, caplog):
    """A server whose event loop stops (SIGSTOP, a hung host) answers no keepalive ping: the client ends with a
    ServiceClosed that says so, and websockets' traceback of the failed ping stays off the terminal."""
    import asyncio
    import queue

    from websockets.asyncio.server import serve

    async def stalls(ws):
        await ws.recv()
        await ws.send(json.dumps({"type": "ready"}))
        time.sleep(6.0)   # blocks the server's loop: no pong, nor a close frame within the client's 5 s

    async def run(port: queue.Queue):
        async with serve(stalls, "127.0.0.1", 0) as server:
            port.put(server.sockets[0].getsockname()[1])
            await asyncio.sleep(8.0)

    port: queue.Queue = queue.Queue()
    threading.Thread(target=asyncio.run, args=(run(port),), daemon=True).start()
    monkeypatch.setattr(client_module, "KEEPALIVE_S", 0.3)
    c = connect(f"ws://127.0.0.1:{port.get(timeout=10)}", K, OPTIONS)
    with pytest.raises(ServiceClosed, match="answered no keepalive ping within 0.3 s"):
        c.recv(10)
    c.ws.keepalive_thread.join(10)   # where websockets logged its traceback
    c.close()
    assert not [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def _ended(pid: int) -> bool:
    """The process is gone or a zombie (its new parent may not reap it)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux) to watch the worker")
def test_a_pool_worker_ends_with_its_killed_parent(tmp_path):
    """A parent killed with SIGKILL (a server, a batch, a pipeline's solve process's owner) tells its pool's workers
    nothing; with exit_with_parent as the initializer the worker ends within seconds (before, a server's connection
    processes lived on, 1.2 GB, waiting on its pipe)."""
    script = tmp_path / "parent.py"
    script.write_text("import multiprocessing as mp, os, time\n"
                      "from concurrent.futures import ProcessPoolExecutor\n"
                      "from photoreg.device import exit_with_parent\n"
                      "if __name__ == '__main__':\n"
                      "    spawn = mp.get_context('spawn')\n"
                      "    pool = ProcessPoolExecutor(1, mp_context=spawn, initializer=exit_with_parent)\n"
                      "    print(pool.submit(os.getpid).result(), flush=True)\n"
                      "    time.sleep(600)\n")
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    worker = int(parent.stdout.readline())
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 15.0
    while not _ended(worker) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _ended(worker), "the pool's worker outlived its killed parent"


def test_four_concurrent_clients(server, recording, tmp_path):
    results: dict[int, tuple] = {}

    def one(k: int) -> None:
        results[k] = stream(recording, server.server.url, tmp_path / f"c{k}")

    threads = [threading.Thread(target=one, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert sorted(results) == [0, 1, 2, 3]
    reference = results[0][0]
    for records, summary in results.values():
        assert summary["frames_processed"] == N_FRAMES and not summary["errors"]
        for a, b in zip(records, reference):
            np.testing.assert_allclose(a["sh"], b["sh"], atol=2e-7)   # separate sessions, same answers


def test_a_process_per_connection(recording, tmp_path):
    """ServerConfig.processes (the default; `photoreg serve --threads` turns it off): each connection's pipeline runs
    in a child process of its own, the next one started and warmed ahead (a spare). Two clients at once get the
    direct pipeline's answers; the server holds one child per ready client plus the spare, the spare alone once
    they have left, none once it stops; a hello takes the spare; a child ignores SIGINT (Ctrl-C reaches the whole process group; the server finishes
    the frames in work itself); a child that dies ends its own connection (an error naming the frame, then close
    code 1011) while the other client is served on."""
    before = set(multiprocessing.active_children())

    def children() -> set:
        return set(multiprocessing.active_children()) - before

    with ServerThread(ServerConfig(port=0, device="cpu", idle_timeout=60, processes=True)) as running:
        url, results = running.server.url, {}
        threads = [threading.Thread(target=lambda k=k: results.__setitem__(k, stream(recording, url, tmp_path / f"c{k}")))
                   for k in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(180)
        direct = direct_lighting(recording)
        assert sorted(results) == [0, 1]
        for records, summary in results.values():
            assert summary["frames_processed"] == N_FRAMES and not summary["errors"]
            for r, sh in zip(records, direct):
                np.testing.assert_allclose(r["sh"], sh, atol=2e-7)
        wait_for(lambda: len(children()) == 1)

        frame = first_frame(recording)
        spare = children()
        with connect(url, K, OPTIONS) as a:
            (doomed,) = spare
            assert doomed in children() and len(children()) == 2   # a's process and the next spare
            os.kill(doomed.pid, signal.SIGINT)
            a.send_frame(frame)
            assert a.recv(60)["type"] == "lighting"
            with connect(url, K, OPTIONS) as b:
                assert len(children()) == 3
                os.kill(doomed.pid, signal.SIGKILL)
                a.send_frame(frame)
                reply = a.recv(60)
                assert reply["type"] == "error" and reply["code"] == "pipeline" and reply["frame"] == 0
                assert "process stopped" in reply["message"]
                with pytest.raises(ServiceClosed) as closed:
                    a.recv(60)
                assert closed.value.code == 1011
                b.send_frame(frame)
                assert b.recv(60)["type"] == "lighting"
        wait_for(lambda: len(children()) == 1)
    wait_for(lambda: not children())   # the server's stop closes the spare too


def wait_for(predicate, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.05)


def test_client_disconnecting_mid_frame(server, recording):
    frame = first_frame(recording)
    before = server.server.stats()["received"]
    # 1. Gone while its frame is in the pipeline.
    c = connect(server.server.url, K, OPTIONS)
    c.send_frame(frame)
    c.ws.socket.close()
    # 2. Gone in the middle of a WebSocket message: a handshake, then half of a 1000-byte masked frame.
    port = server.server.port
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                  "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
        assert b" 101 " in s.recv(4096)
        s.sendall(b"\x82\xfe" + struct.pack(">H", 1000) + b"abcd" + b"x" * 500)
    wait_for(lambda: server.server.stats()["connections"] == 0)
    assert server.server.stats()["received"] == before + 1   # the half message never counted
    with connect(server.server.url, K, OPTIONS) as c:   # the server carries on
        c.send_frame(frame)
        assert c.recv(60)["type"] == "lighting"


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def test_slow_client_hurts_nobody_and_memory_stays_bounded(server, recording, tmp_path):
    """A client that floods 320x240 raw frames (0.5 MB each, ~400 MB in all) and never reads its replies:
    its worker stalls on a full socket, its queue drops the oldest frames, another client is served,
    and the process's memory does not follow the flood."""
    big = Intrinsics(320, 240, 280.0, 280.0, 159.5, 119.5, 5000.0)
    frame = first_frame(write_recording(tmp_path / "big", big, 1))
    frame_mb = big.width * big.height * 7 / 2**20   # rgb8 + f32
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)   # fills after a few replies
    sock.connect(("127.0.0.1", server.server.port))
    with ws_connect(server.server.url, sock=sock, max_queue=1, compression=None) as ws:
        ws.send(encode(hello_message(big, OPTIONS)))
        slow = Client(ws, json.loads(ws.recv(60)))
        fast = connect(server.server.url, K, OPTIONS)
        frames = list(open_recording(recording))
        fast.send_frame(frames[0])
        assert fast.recv(60)["type"] == "lighting"
        before = server.server.stats()
        slow.send_frame(frame, 0, "rgb8", "f32")
        wait_for(lambda: server.server.stats()["processed"] > before["processed"], 60)
        gc.collect()
        baseline = rss_mb()   # both sessions have fused a frame: volumes and bricks allocated
        peak = [baseline]
        flood_done = threading.Event()

        def flood() -> None:
            for i in range(1, N_FLOOD):
                slow.send_frame(frame, i, "rgb8", "f32")
                peak[0] = max(peak[0], rss_mb())
            flood_done.set()

        threading.Thread(target=flood, daemon=True).start()
        summary = replay(fast, frames[1:])
        flood_done.wait(120)
        assert flood_done.is_set()
        assert summary["frames_processed"] == N_FRAMES - 1 and summary["frames_dropped"] == 0
        assert not summary["errors"]
        growth = max(peak[0], rss_mb()) - baseline   # thread arenas and buffers warming up: ~70 MB here
        dropped = server.server.stats()["dropped"] - before["dropped"]
        print(f"\nslow client: {N_FLOOD} frames sent ({N_FLOOD * frame_mb:.0f} MB), {dropped} dropped by the server; "
              f"peak RSS growth {growth:.0f} MB; the other client's p95 latency {summary['latency_ms']['p95']:.0f} ms")
        assert dropped > 0.9 * N_FLOOD - N_FRAMES
        assert growth < 150, f"memory grew by {growth:.0f} MB while {N_FLOOD * frame_mb:.0f} MB were flooded"
        ws.socket.close()
    wait_for(lambda: server.server.stats()["connections"] == 0)


def test_messages_out_of_order_and_versions(server, recording):
    frame_bytes = encode_frame(first_frame(recording))
    with ws_connect(server.server.url, compression=None) as ws:
        ws.send(frame_bytes)
        assert json.loads(ws.recv(10))["code"] == "not_ready"
        ws.send(encode({**hello_message(K, OPTIONS), "version": "2.0"}))
        err = json.loads(ws.recv(10))
        assert err["code"] == "version" and "1.2" in err["message"]
        ws.send(encode(hello_message(K, OPTIONS)))
        ready = json.loads(ws.recv(60))
        assert ready["type"] == "ready" and ready["version"] == "1.2" and ready["compositing"] is False
        ws.send(encode(hello_message(K, OPTIONS)))
        assert json.loads(ws.recv(10))["code"] == "already_ready"
        ws.send(frame_bytes)
        reply = json.loads(ws.recv(60))
        assert reply["type"] == "lighting" and reply["frame"] == 0 and reply["dropped"] == 0
        ws.send(encode({"type": "bye"}))
        bye = json.loads(ws.recv(10))
        assert bye["type"] == "bye" and bye["frames_processed"] == 1
        with pytest.raises(ConnectionClosed) as e:
            ws.recv(10)
        assert e.value.rcvd.code == 1000


# Messages that are wrong whatever hypothesis draws: each must get exactly one error reply.
# (finite floats: JSON has no infinity, and protocol.encode refuses one)
def _nested(inner):
    """Lists and objects of `inner` (a named function: hypothesis read the multi-line lambda it replaced as one that
    ignores its argument, and warned)."""
    return st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3)


_junk_json = st.recursive(st.none() | st.booleans() | st.floats(allow_nan=False, allow_infinity=False)
                          | st.text(max_size=8), _nested, max_leaves=8)
_not_a_number = st.none() | st.booleans() | st.text(max_size=8) | st.lists(st.integers(), max_size=3)


@st.composite
def malformed(draw, valid_frame: bytes):
    header, payload = decode(valid_frame)
    payload = bytes(payload)
    kind = draw(st.sampled_from(["bytes", "text", "type", "drop", "timestamp", "encoding", "range", "pose",
                                 "corrupt", "hello"]))
    if kind == "bytes":
        return draw(st.binary(max_size=64))
    if kind == "text":
        return draw(st.text(max_size=40).filter(lambda t: '"type"' not in t))
    if kind == "type":
        return encode({"type": draw(st.text(max_size=10).filter(lambda t: t not in CLIENT_TYPES)),
                       "x": draw(_junk_json)})
    h = json.loads(json.dumps(header))
    if kind == "drop":
        key = draw(st.sampled_from(["timestamp", "color", "depth"]))
        del h[key]
    elif kind == "timestamp":
        h["timestamp"] = draw(_not_a_number)
    elif kind == "encoding":
        part = draw(st.sampled_from(["color", "depth"]))
        h[part]["encoding"] = draw(st.text(max_size=8).filter(lambda t: t not in ("png", "jpeg", "rgb8", "png16",
                                                                                  "u16", "f32")))
    elif kind == "range":
        part, key = draw(st.sampled_from(["color", "depth"])), draw(st.sampled_from(["offset", "length"]))
        h[part][key] = draw(st.integers(max_value=-1) | st.integers(min_value=len(payload) + 1) | _not_a_number)
    elif kind == "pose":
        h["pose"] = draw(st.lists(st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=4, max_size=4),
                                  max_size=3) | _not_a_number.filter(lambda v: v is not None))
    elif kind == "corrupt":   # colour PNG cut short or overwritten inside its image data (IDAT chunk)
        c = h["color"]
        data = bytearray(payload[:c["length"]])
        idat = data.index(b"IDAT")
        cut = draw(st.integers(min_value=idat + 4, max_value=idat + 3 + struct.unpack(">I", data[idat - 4:idat])[0]))
        if draw(st.booleans()):
            data = data[:cut]
        else:
            data[cut:] = draw(st.binary(min_size=len(data) - cut, max_size=len(data) - cut))
            data[cut:cut + 8] = b"\x00" * min(8, len(data) - cut)   # make sure the image data is damaged
        h["color"]["length"] = len(data)
        h["depth"]["offset"] = len(data)
        return raw_message(h, bytes(data) + payload[c["length"]:])
    elif kind == "hello":
        return encode(hello_message(K, OPTIONS))   # a second hello on a ready connection
    return raw_message(h, payload)


@pytest.fixture(scope="module")
def ready_ws(server):
    with ws_connect(server.server.url, compression=None) as ws:
        ws.send(encode(hello_message(K, OPTIONS)))
        assert json.loads(ws.recv(60))["type"] == "ready"
        yield ws


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_malformed_messages_get_an_error_and_the_connection_stays_usable(ready_ws, recording, data):
    valid = encode_frame(first_frame(recording))
    ready_ws.send(data.draw(malformed(valid)))
    reply = json.loads(ready_ws.recv(30))
    assert reply["type"] == "error" and reply["code"] in ERROR_CODES and reply["message"], reply
    ready_ws.send(valid)   # ... and a valid frame is still served
    assert json.loads(ready_ws.recv(60))["type"] == "lighting"


def test_odd_input_is_a_clear_error_not_internal(tmp_path):
    """An integer past Python's 4300 digits in a header, a mesh name too long for the file system: bad_message and
    bad_field naming no server path (before: 'internal', the mesh folder in it); fill bytes of a JPEG skipped at
    once, the frame header found after them (a run of 30 MB took 5.6 s of the server's interpreter)."""
    from photoreg.service.protocol import _jpeg_size, resolve_mesh

    with pytest.raises(ProtocolError) as e:
        decode('{"type": "hello", "x": ' + "1" * 5000 + "}")
    assert e.value.code == "bad_message" and "not valid JSON" in e.value.message
    with pytest.raises(ProtocolError) as e:
        resolve_mesh("a" * 300 + ".obj", tmp_path, "hello.options.objects[0].mesh")
    assert e.value.code == "bad_field" and str(tmp_path) not in e.value.message
    jpeg = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))[1].tobytes()
    assert _jpeg_size(jpeg[:2] + b"\xff" * 3_000_000 + jpeg[2:]) == (64, 48)
    assert decode(encode({"type": "ping"}))[0] == {"type": "ping"}


def test_serve_options_are_checked(capsys):
    from photoreg.cli import main

    for argv, message in ((["--port", "70000"], "--port must be in 0..65535, got 70000"),
                          (["--max-message-mb", "nan"], "--max-message-mb must be a positive number of MiB, got nan"),
                          (["--max-message-mb", "0"], "--max-message-mb must be a positive number of MiB, got 0.0")):
        assert main(["serve", *argv]) == 2
        assert message in capsys.readouterr().err


def test_limits_clients_token_idle(recording):
    """One client at most, a token, a short idle timeout: extra, unauthorised and idle clients are closed
    with an error naming why."""
    with ServerThread(ServerConfig(port=0, device="cpu", max_clients=1, token="s3cret", idle_timeout=1.0,
                                   processes=False)) as running:
        url = running.server.url
        with pytest.raises(ProtocolError) as e:
            connect(url, K, OPTIONS, token="guess")
        assert e.value.code == "unauthorized"
        with pytest.raises(ProtocolError) as e:
            connect(url, K, OPTIONS)
        assert e.value.code == "unauthorized"
        with pytest.raises(ProtocolError) as e:   # a lone surrogate (valid JSON, not UTF-8): refused like any other
            connect(url, K, OPTIONS, token="\ud800")
        assert e.value.code == "unauthorized"
        wait_for(lambda: running.server.stats()["connections"] == 0)
        c = connect(url, K, OPTIONS, token="s3cret")
        with ws_connect(url, compression=None) as extra:
            err = json.loads(extra.recv(10))
            assert err["code"] == "too_many_clients"
            with pytest.raises(ConnectionClosed) as closed:
                extra.recv(10)
            assert closed.value.rcvd.code == 1013

        def late(*args, **kwargs):   # a client whose hello goes out after the server has refused and closed
            ws = ws_connect(*args, **kwargs)
            entered = ws.__enter__()
            wait_for(lambda: entered.close_code is not None, 10)
            return contextlib.nullcontext(entered)

        with pytest.MonkeyPatch.context() as mp:   # the refusal's error, not a raw ConnectionClosed from the send
            mp.setattr(client_module, "ws_connect", late)
            with pytest.raises((ProtocolError, ServiceClosed)) as refused:
                connect(url, K, OPTIONS, token="s3cret")
        assert "too_many_clients" in str(refused.value)
        time.sleep(1.5)   # idle
        assert c.recv(10)["code"] == "idle_timeout"
        with pytest.raises(ServiceClosed) as closed:
            c.recv(10)
        assert closed.value.code == 1000 and closed.value.reason == "idle timeout"
    # with a token, a connection has hello_timeout for its hello: pings do not keep it (before: they held the slot
    # until the idle timeout, and a client with the token was refused meanwhile)
    with ServerThread(ServerConfig(port=0, device="cpu", max_clients=1, token="s3cret", idle_timeout=60,
                                   hello_timeout=1.0, processes=False)) as running:
        with ws_connect(running.server.url, compression=None) as squatter:
            t0 = time.monotonic()
            for _ in range(4):
                squatter.send(encode({"type": "ping"}))
                time.sleep(0.3)
            replies = []
            with pytest.raises(ConnectionClosed) as closed:
                while True:
                    replies.append(json.loads(squatter.recv(10)))
            assert closed.value.rcvd.code == 1008 and time.monotonic() - t0 < 5
            assert replies[-1]["code"] == "unauthorized"
            assert "no hello with the token within 1 s" in replies[-1]["message"]
        wait_for(lambda: running.server.stats()["connections"] == 0)
        connect(running.server.url, K, OPTIONS, token="s3cret").close()


def test_replies_read_before_the_connection_closed_are_kept(server, recording):
    """Client.poll after the server's bye and close: the replies that came before (its bye among them) are returned,
    the next call raises (before: poll raised and lost them, and a stream's summary had no server_bye). websockets
    marks the connection closed a moment before it closes its queue: that moment is stretched to 1 s here (CI hit
    it: the second poll found the queue open and empty and returned [])."""
    c = connect(server.server.url, K, OPTIONS)
    close_queue = c.ws.recv_messages.close
    c.ws.recv_messages.close = lambda: (time.sleep(1), close_queue())
    c.send_frame(first_frame(recording))
    c.send_message(encode({"type": "bye"}))
    wait_for(lambda: c.ws.close_code is not None, 30)
    replies = c.poll()
    assert [r["type"] for r in replies][-1] == "bye" and "lighting" in [r["type"] for r in replies]
    with pytest.raises(ServiceClosed):
        c.poll()


@pytest.mark.parametrize("ctrl_c", [False, True], ids=["sigterm", "sigint-to-the-group"])
def test_sigterm_finishes_frames_and_closes_with_1001(recording, ctrl_c):
    """`photoreg serve` as a process (its connections' pipelines in processes of their own): SIGTERM, or SIGINT to
    its whole process group as Ctrl-C in a terminal sends it (the connection's process too, which ignores it) ->
    the frame in work is answered, clients get bye and close code 1001, the process exits 0."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "photoreg", "serve", "--port", "0", "--device", "cpu"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        lines = []
        while not (m := re.search(r"listening on (ws://\S+)", lines[-1] if lines else "")):
            lines.append(proc.stdout.readline())
            assert lines[-1] or proc.poll() is None, ("".join(lines), proc.stderr.read())
        c = connect(m.group(1), K, OPTIONS)
        c.send_frame(first_frame(recording))
        assert c.recv(120)["type"] == "lighting"   # warm: kernels loaded
        c.send_frame(first_frame(recording), 1)
        if ctrl_c:
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)
        replies = []
        with pytest.raises(ServiceClosed) as closed:
            while True:
                replies.append(c.recv(60))
        assert closed.value.code == 1001
        assert replies[-1]["type"] == "bye" and "shutting down" in replies[-1]["reason"]
        assert [r["type"] for r in replies[:-1]] in (["lighting"], [])   # finished, or cancelled before starting
        assert proc.wait(30) == 0
        assert "stopped after" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.slow
def test_load_figures(server, tmp_path):
    """Frames/s and latency at stride 4 through the service (printed; the assertion only bounds time)."""
    k = Intrinsics(160, 120, 140.0, 140.0, 79.5, 59.5, 5000.0)
    rec = write_recording(tmp_path / "load", k, 30)
    records, summary = stream(rec, server.server.url, tmp_path / "out")
    lat = summary["latency_ms"]
    print(f"\nload: {summary['frames_processed']} frames {k.width}x{k.height}, stride 4, 16 rays, 2 bands, "
          f"window 2, device {summary['device']}: {summary['frames_per_s']:.2f} frames/s, latency p50 "
          f"{lat['p50']:.0f} ms, p95 {lat['p95']:.0f} ms, p99 {lat['p99']:.0f} ms; server-side p95 "
          f"{summary['server_latency_ms']['p95']:.0f} ms; mean pipeline {summary['timings_ms_mean']['total']:.0f} ms")
    assert summary["frames_processed"] == 30 and summary["wall_s"] < 120
