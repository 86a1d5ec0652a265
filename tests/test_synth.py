"""Ground-truth generator (`photoreg synth`): Mitsuba camera and envmap conventions, depth geometry, CLI output.

The orientation trap: the GT SH must describe the light Mitsuba actually renders with, in world
coordinates. A white sphere lit only by the environment is rendered and compared, at analytically
known normals, with albedo * E(n) / pi from (a) the exact cosine convolution of the environment
image and (b) the 8-band GT SH; wrong rotations of the same SH must fail the comparison.
"""
from __future__ import annotations

import json
import math
import os

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

pytest.importorskip("mitsuba")

from photoreg import cli  # noqa: E402
from photoreg.io.images import linear_to_srgb, read_exr  # noqa: E402
from photoreg.io.poses import read_tum_trajectory  # noqa: E402
from photoreg.lighting.sh import fibonacci_sphere, irradiance  # noqa: E402
from photoreg.synth.cameras import default_intrinsics, look_at  # noqa: E402
from photoreg.synth.depth import depth_sigma, kinect_like  # noqa: E402
from photoreg.synth.environment import (ProceduralSky, emitter_rotation, environment_sh,  # noqa: E402
                                        load_environment, node_directions)
from photoreg.synth.generate import SynthConfig, generate, rerender_inserts  # noqa: E402
from photoreg.synth.render import MitsubaScene  # noqa: E402
from photoreg.synth.scenes import INSERT_MESH_SCALE, SceneObject, placement  # noqa: E402
from photoreg.types import Intrinsics  # noqa: E402

ALBEDO = 0.8


def pixel_rays(K: Intrinsics, pose: np.ndarray) -> np.ndarray:
    """World unit directions (H*W, 3) through the pixel centres (OpenCV convention)."""
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.shape)], axis=-1).reshape(-1, 3)
    return (d / np.linalg.norm(d, axis=1, keepdims=True)) @ pose[:3, :3].T


def mitsuba_envmap_lookup(image: np.ndarray, rotation: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """FACTS.md mapping with bilinear interpolation between nodes at u=(j+0.5)/W, t=i/(H-1)."""
    h, w, _ = image.shape
    v = dirs @ rotation  # R^T w
    x = (np.arctan2(v[:, 0], -v[:, 2]) / (2 * np.pi) * w - 0.5) % w
    y = np.arccos(np.clip(v[:, 1], -1, 1)) / np.pi * (h - 1)
    x0, y0 = np.floor(x).astype(int), np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x1 = (x0 + 1) % w
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x1] * fx
    return top * (1 - fy) + bottom * fy


def test_envmap_and_camera_mapping_match_mitsuba():
    """Background pixels equal the envmap looked up along our pixel rays: camera frame, intrinsics,
    emitter rotation and lat-long mapping all agree with Mitsuba (a mirrored camera or rows at pixel
    centres would be off by tens of percent)."""
    env = np.random.default_rng(1).uniform(0.2, 1.2, (16, 32, 3)).astype(np.float32)
    R = emitter_rotation(37.0)
    K = default_intrinsics(128, 96)  # pixels (0.5 deg) much finer than texels (11 deg)
    pose = look_at([0, 0, 0], [math.cos(0.7), math.sin(0.7), 0.35])
    img = MitsubaScene([], env, R, K, max_depth=2).render(pose, spp=64, seed=0).reshape(-1, 3)
    dirs = pixel_rays(K, pose)
    away_from_poles = np.abs(dirs[:, 2]) < 0.9
    err = np.abs(img - mitsuba_envmap_lookup(env, R, dirs))[away_from_poles]
    assert err.max() < 0.01, err.max()
    # The trap would be caught: the same lookup through a mirrored camera (x right vs left) disagrees.
    mirrored = pixel_rays(K, pose @ np.diag([-1.0, 1.0, 1.0, 1.0]))
    assert np.abs(img - mitsuba_envmap_lookup(env, R, mirrored))[away_from_poles].max() > 0.2


def _exact_irradiance(image, rotation, normals):
    """E(n) by quadrature of the environment as Mitsuba interpolates it (no SH truncation)."""
    dirs, weights = node_directions(*image.shape[:2])
    world = (dirs.reshape(-1, 3) @ rotation.T).astype(np.float32)
    weighted = (image.reshape(-1, 3) * np.repeat(weights, image.shape[1])[:, None]).astype(np.float32)
    chunks = np.array_split(normals.astype(np.float32), max(1, len(normals) // 128))
    return np.concatenate([np.maximum(n @ world.T, 0) @ weighted for n in chunks]).astype(np.float64)


@pytest.mark.slow
@pytest.mark.parametrize("env, yaw, floor", [("procedural", 40.0, 1.0), ("pisa.hdr", 0.0, 0.5), ("wells.hdr", 75.0, 0.5)])
def test_orientation_trap(request, env, yaw, floor):
    """Rendered radiance of a white sphere under the envmap alone = albedo E(n)/pi, per 4x4 pixel block
    (Monte-Carlo noise about 0.5%, at most about 2.5%):
    - against the exact convolution of the environment image: |I - P| <= 3% of max(P, 0.1 P_max);
    - against the 8-band GT SH: |I - P| <= 3% of max(P, floor * P_max), where P_max = albedo max_n E(n)/pi.
      floor = 0.5 for the HDR maps; 1.0 (errors relative to max E) for the procedural sun, whose
      8-band irradiance itself is off by up to 5.5% of max(E, 0.5 E_max) (2.8% of E_max): truncation;
    - the same SH under wrong emitter rotations (no up->z turn, mirrored map, opposite yaw) fails by far.
    """
    if env == "procedural":
        image = ProceduralSky(width=512, height=256).bake()  # the default sky at half resolution (speed)
    else:
        image, _ = load_environment(str(request.getfixturevalue("data_dir") / "hdr" / env))
    R = emitter_rotation(yaw)
    sh = environment_sh(image, R, bands=8)
    p_max = ALBEDO / np.pi * _exact_irradiance(image, R, fibonacci_sphere(500)).max(axis=0)

    n_px, block = 96, 4
    K = Intrinsics(n_px, n_px, 1.7 * n_px, 1.7 * n_px, (n_px - 1) / 2, (n_px - 1) / 2)
    sphere = SceneObject("sphere", "sphere", (1.0,), placement([0, 0, -1.0]), (ALBEDO,) * 3)  # unit sphere at 0
    scene = MitsubaScene([sphere], image, R, K, max_depth=2)
    wrong = {"no up->z": Rotation.from_euler("z", yaw, degrees=True).as_matrix(),
             "mirrored map": R @ np.diag([-1.0, 1.0, 1.0])}
    if yaw:
        wrong["opposite yaw"] = emitter_rotation(-yaw)
    worst_wrong = dict.fromkeys(wrong, 0.0)
    for eye in ([3.0, 1.5, 2.4], [-3.0, -1.2, -2.0]):  # upper and lower hemisphere
        eye = 4.0 * np.asarray(eye) / np.linalg.norm(eye)
        pose = look_at(eye, [0, 0, 0])
        img = scene.render(pose, spp=2048, seed=1)
        d = pixel_rays(K, pose)
        b = d @ eye
        disc = b * b - (eye @ eye - 1.0)
        n = eye + (-b - np.sqrt(np.maximum(disc, 0)))[:, None] * d  # hit point = normal
        usable = (disc > 0) & (np.sum(-d * n, axis=1) > 0.4)  # footprint well inside the silhouette

        def blocks(a):
            return a.reshape(n_px // block, block, n_px // block, block, -1).transpose(0, 2, 1, 3, 4)

        keep = blocks(usable[:, None])[..., 0].all(axis=(2, 3))
        measured = blocks(img.reshape(-1, 3))[keep].reshape(-1, block * block, 3).mean(axis=1)
        normals = blocks(n)[keep].reshape(-1, 3)

        def predicted(E):
            return (ALBEDO / np.pi * E).reshape(-1, block * block, 3).mean(axis=1)

        def rel_err(P, c):
            return np.max(np.abs(measured - P) / np.maximum(P, c * p_max))

        assert keep.sum() > 150
        assert rel_err(predicted(_exact_irradiance(image, R, normals)), 0.1) < 0.03
        assert rel_err(predicted(irradiance(sh, normals)), floor) < 0.03
        for name, Rw in wrong.items():
            worst_wrong[name] = max(worst_wrong[name], rel_err(predicted(irradiance(environment_sh(image, Rw, 8), normals)), floor))
    assert min(worst_wrong.values()) > 0.1, worst_wrong


def test_camera_projects_known_point():
    """A small sphere at a known world point appears where the OpenCV projection puts it, in the geometry
    pass (back-projected depth lies on its surface) and in the colour render (same pixels)."""
    centre, r = np.array([0.1, -0.05, 0.2]), 0.05
    sphere = SceneObject("s", "sphere", (r,), placement(centre - [0, 0, r]), (0.5, 0.5, 0.5))
    K = default_intrinsics(160, 120)
    pose = look_at([0.8, -0.6, 0.5], [0.0, 0.0, 0.1])
    scene = MitsubaScene([sphere], np.ones((8, 16, 3), np.float32), emitter_rotation(0), K, max_depth=2)
    z = scene.geometry(pose)
    hit = z > 0
    v, u = np.nonzero(hit)
    pc = np.linalg.inv(pose) @ np.append(centre, 1.0)
    proj = (K.K @ pc[:3])[:2] / pc[2]
    assert np.hypot(u.mean() - proj[0], v.mean() - proj[1]) < 0.25
    pts = (np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.shape)], 1) * z[hit][:, None]) @ pose[:3, :3].T + pose[:3, 3]
    assert np.abs(np.linalg.norm(pts - centre, axis=1) - r).max() < 1e-4
    colour = scene.render(pose, spp=16, seed=0).mean(axis=-1)  # background radiance 1, sphere at most 0.5
    dark = colour < 0.75
    assert (dark & hit).sum() / (dark | hit).sum() > 0.9


def _read_depth(root, name: str, K: dict) -> np.ndarray:
    d = cv2.imread(str(root / name), cv2.IMREAD_UNCHANGED)
    assert d is not None and d.dtype == np.uint16
    return d.astype(np.float64) / K["depth_scale"]


def _backproject(depth: np.ndarray, K: dict, pose: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    cam = np.stack([(u - K["cx"]) / K["fx"] * z, (v - K["cy"]) / K["fy"] * z, z], axis=1)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def test_plane_depth_lands_on_floor(tmp_path):
    """Clean depth of the floor-only scene, back-projected with the written poses and intrinsics: z = 0."""
    root = generate(SynthConfig("plane", str(tmp_path / "rec"), frames=3, width=64, height=48, spp=1,
                                camera="handheld", noise=False, insert_frames="none"), log=None)
    K = json.loads((root / "intrinsics.json").read_text())
    _, poses = read_tum_trajectory(root / "groundtruth.txt")
    for i, pose in enumerate(poses):
        pts = _backproject(_read_depth(root, f"depth/{i:06d}.png", K), K, pose)
        assert len(pts) > 0.5 * 64 * 48
        assert np.abs(pts[:, 2]).max() < 0.01


def test_overexposed_recording_saturates(tmp_path):
    """--overexpose K: K times the chosen exposure (in lighting_gt.json, whose SH the estimate should match times
    it), so the brightest surfaces saturate as a camera's do; the command line reproducing it names it."""
    roots = [generate(SynthConfig("plane", str(tmp_path / f"x{k}"), frames=1, width=48, height=32, spp=2,
                                  insert_frames="none", overexpose=k), log=None) for k in (1.0, 2.5)]
    exposure = [json.loads((r / "lighting_gt.json").read_text())["exposure"] for r in roots]
    assert exposure[1] == pytest.approx(2.5 * exposure[0])
    saturated = [(cv2.imread(str(r / "rgb" / "000000.png")).max(axis=2) >= 250).mean() for r in roots]
    assert saturated[0] < 0.02 and saturated[1] > 0.3
    assert "--overexpose 2.5" in SynthConfig("plane", "o", overexpose=2.5).command_line()


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A tiny tabletop recording made through the CLI (handheld camera, noisy + clean depth, inserts)."""
    out = tmp_path_factory.mktemp("synth") / "rec"
    assert cli.main(["synth", "tabletop", "--out", str(out), "--frames", "6", "--size", "128x96", "--spp", "16",
                     "--camera", "handheld", "--seed", "3"]) == 0
    return out


def _surface_distance(points: np.ndarray, objects: list[dict]) -> np.ndarray:
    """Distance from world points to the union of scene.json's objects (analytic shapes, base on local z=0)."""
    best = np.full(len(points), np.inf)
    for o in objects:
        T = np.asarray(o["transform"])
        p = (points - T[:3, 3]) @ T[:3, :3]
        s = o["size"]
        if o["type"] == "plane":
            q = np.stack([np.abs(p[:, 0]) - s[0] / 2, np.abs(p[:, 1]) - s[1] / 2], 1)
            d = np.hypot(np.linalg.norm(np.maximum(q, 0), axis=1), p[:, 2])
        elif o["type"] == "sphere":
            d = np.abs(np.linalg.norm(p - [0, 0, s[0]], axis=1) - s[0])
        elif o["type"] in ("box", "cylinder"):
            if o["type"] == "box":
                q = np.abs(p - [0, 0, s[2] / 2]) - np.asarray(s) / 2
            else:
                q = np.stack([np.hypot(p[:, 0], p[:, 1]) - s[0], np.abs(p[:, 2] - s[1] / 2) - s[1] / 2], 1)
            d = np.abs(np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0))
        else:
            pytest.fail(f"unexpected object type {o['type']}")
        best = np.minimum(best, d)
    return best


def test_depth_lands_on_known_geometry(recording):
    """Clean depth of every frame lies on scene.json's objects (within 1 cm, the 48-gon cylinder
    included); noisy depth stays within its noise; two frames' clouds agree (median NN < 1 cm)."""
    K = json.loads((recording / "intrinsics.json").read_text())
    scene = json.loads((recording / "scene.json").read_text())
    _, poses = read_tum_trajectory(recording / "groundtruth.txt")
    clouds = []
    for i, pose in enumerate(poses):
        clean = _read_depth(recording, f"depth_clean/{i:06d}.png", K)
        pts = _backproject(clean, K, pose)
        assert np.max(_surface_distance(pts, scene["objects"])) < 0.01
        noisy = _read_depth(recording, f"depth/{i:06d}.png", K)
        both = (noisy > 0) & (clean > 0)
        assert 0.5 < both.sum() / (clean > 0).sum() < 0.99  # holes at edges, most pixels kept
        assert np.median(np.abs(noisy - clean)[both]) < 3 * np.median(depth_sigma(clean[both]))
        clouds.append(pts)
    for a, b in [(0, 1), (2, 3)]:  # neighbouring views (36 degrees apart), overlap = points within 5 cm
        nn, _ = cKDTree(clouds[b]).query(clouds[a], distance_upper_bound=0.05)
        overlap = np.isfinite(nn)
        assert overlap.mean() > 0.5 and np.median(nn[overlap]) < 0.01


def test_cli_recording_files(recording):
    """Every file of the native layout and the ground truth is there and consistent."""
    n = 6
    for sub in ("rgb", "depth", "depth_clean"):
        assert sorted(p.name for p in (recording / sub).iterdir()) == [f"{i:06d}.png" for i in range(n)]
    for kind in ("rgb", "depth"):
        lines = [ln.split() for ln in (recording / f"{kind}.txt").read_text().splitlines() if not ln.startswith("#")]
        assert lines == [[f"{i / 30:.6f}", f"{kind}/{i:06d}.png"] for i in range(n)]
    ts, poses = read_tum_trajectory(recording / "groundtruth.txt")
    assert np.allclose(ts, np.arange(n) / 30, atol=1e-6) and poses.shape == (n, 4, 4)

    K = json.loads((recording / "intrinsics.json").read_text())
    assert K == default_intrinsics(128, 96).to_json() and K["depth_scale"] == 5000.0
    gt = json.loads((recording / "lighting_gt.json").read_text())
    scene = json.loads((recording / "scene.json").read_text())
    assert gt["bands"] == 8 and gt["frame"] == "world" and np.shape(gt["sh"]) == (3, 64)
    assert gt["exposure"] == scene["exposure"] > 0
    sky = ProceduralSky()
    assert np.allclose(gt["sh"], environment_sh(sky.bake(), emitter_rotation(0.0), 8))
    assert scene["generator"]["version"] and scene["command"].startswith("photoreg synth tabletop")
    assert scene["render"]["spp"] == 16 and scene["lighting"]["type"] == "procedural"
    assert {o["type"] for o in scene["objects"]} == {"plane", "box", "sphere", "cylinder"}
    assert all(set(o) >= {"type", "size", "transform", "albedo"} for o in scene["objects"])

    clipped = [np.mean(cv2.imread(str(recording / "rgb" / f"{i:06d}.png")).max(axis=-1) == 255) for i in range(n)]
    assert max(clipped) < 0.01, clipped

    session = tomllib.loads((recording / "session.toml").read_text())
    assert session["recording"] == {"path": ".", "format": "native"}
    assert session["render"]["shadows"] == "voxel" and session["output"]["dir"] == "out"
    (obj,) = session["objects"]
    mesh = trimesh.load(recording / obj["mesh"], force="mesh")
    assert len(mesh.vertices) == 8 and np.allclose(mesh.bounds, [[-0.5, -0.5, 0], [0.5, 0.5, 1]])
    assert scene["insert"]["frames"] == [1, 2, 4]
    R = Rotation.from_euler("xyz", obj["rotation"], degrees=True).as_matrix()
    world = (obj["scale"] * mesh.vertices) @ R.T + obj["position"]
    for i in scene["insert"]["frames"]:
        png = cv2.cvtColor(cv2.imread(str(recording / "insert" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB)
        exr = read_exr(recording / "insert" / f"{i:06d}.exr")
        assert np.abs(linear_to_srgb(exr).astype(int) - png).max() <= 1
        mask = cv2.imread(str(recording / "insert_mask" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) == 255
        assert mask.sum() > 20
        # the mask lies inside the projection of the session's object placement
        cam = (world - poses[i][:3, 3]) @ poses[i][:3, :3]
        uv = cam[:, :2] / cam[:, 2:] * [K["fx"], K["fy"]] + [K["cx"], K["cy"]]
        v, u = np.nonzero(mask)
        assert uv[:, 0].min() - 1 <= u.min() and u.max() <= uv[:, 0].max() + 1
        assert uv[:, 1].min() - 1 <= v.min() and v.max() <= uv[:, 1].max() + 1
        rgb = cv2.cvtColor(cv2.imread(str(recording / "rgb" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB)
        assert np.abs(png.astype(int) - rgb)[mask].mean() > 10  # the object is there


def test_rerender_inserts_is_the_insert_up_to_noise(recording):
    """The insert frames rendered again with other seeds: the same picture (object and surroundings as bright,
    within render noise), not the same pixels."""
    again = rerender_inserts(recording)
    assert sorted(again) == [1, 2, 4]
    for i, img in again.items():
        exr = read_exr(recording / "insert" / f"{i:06d}.exr")
        mask = cv2.imread(str(recording / "insert_mask" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) == 255
        assert img.shape == exr.shape and np.abs(img - exr).mean() > 1e-3           # other noise
        assert abs(img[mask].mean() / exr[mask].mean() - 1.0) < 0.1
        assert abs(img.mean() / exr.mean() - 1.0) < 0.03


def test_kinect_like_noise():
    """Noise follows depth_sigma; holes open along depth steps and next to missing depth, not elsewhere."""
    z = np.full((100, 100), 1.5, np.float32)
    z[:, 50:] = 2.5
    z[:10, :10] = 0.0
    noisy = kinect_like(z, np.random.default_rng(0))
    flat = (noisy > 0) & (z == 1.5)
    assert abs(np.std(noisy[flat] - 1.5) / depth_sigma(1.5) - 1) < 0.05
    assert np.all(noisy[:, 49:51] == 0) and np.all(noisy[10, :11] == 0)
    assert np.mean(noisy[20:, 12:48] > 0) == 1.0


@pytest.mark.parametrize("argv, message", [
    (["nosuch"], "unknown scene kind 'nosuch'"),
    (["plane", "--size", "320by240"], "--size '320by240'"),
    (["plane", "--env", "/nonexistent/sky.hdr"], "no such HDR file"),
    (["plane", "--insert-frames", "1,99", "--frames", "4"], "outside 0..3"),
    (["corner", "--mesh", "bunny.obj"], "--mesh is used by the tabletop scene only"),
    (["plane", "--overexpose", "0"], "--overexpose 0"),
    (["plane", "--insert-mesh", "/nonexistent/bunny.obj"], "--insert-mesh /nonexistent/bunny.obj: no such mesh file"),
    (["plane", "--insert-mesh", __file__, "--insert-texture"], "does not combine with --insert-mesh"),
    (["plane", "--shutter", "0.05"], "--shutter 0.05: seconds in 0..0.0333"),
    (["plane", "--yaw", "nan"], "--yaw nan: need a finite angle"),
    (["plane", "--seed", "-1"], "--seed -1: need an integer in 0..2^32-1"),
    (["plane", "--size", "40000x30000"], "--size 40000x30000: need 8..8192 pixels a side"),
    (["plane", "--frames", "100000000"], "--frames 100000000: need 1..100000"),
])
def test_bad_input_is_named(tmp_path, capsys, argv, message):
    assert cli.main(["synth", *argv[:1], "--out", str(tmp_path / "o"), *argv[1:]]) == 2
    assert message in capsys.readouterr().err


def test_a_mesh_without_area_is_named(tmp_path, capsys):
    """A mesh whose triangles are all degenerate: named, before any frame (before: a ZeroDivisionError traceback, or a
    recording whose insert masks were empty and whose session.toml `photoreg run` then refused)."""
    mesh = tmp_path / "line.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    assert cli.main(["synth", "plane", "--out", str(tmp_path / "o"), "--insert-mesh", str(mesh), "--frames", "1",
                     "--size", "16x12", "--spp", "1"]) == 2
    assert f"{mesh}: mesh has no area" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_an_interrupted_render_leaves_no_recording(tmp_path, monkeypatch):
    """Interrupted at frame 1 (Ctrl-C), the render leaves OUT.partial, not OUT: nothing that passes for a recording;
    the next run starts the partial folder again and renames it when whole."""
    import photoreg.synth.generate as gen

    exposed = gen._exposed

    def interrupted(scene, cfg, layout, i, pose, seed):
        if i == 1:
            raise KeyboardInterrupt
        return exposed(scene, cfg, layout, i, pose, seed)

    cfg = SynthConfig("plane", str(tmp_path / "rec"), frames=2, width=32, height=24, spp=1, insert_frames="none")
    monkeypatch.setattr(gen, "_exposed", interrupted)
    with pytest.raises(KeyboardInterrupt):
        generate(cfg, log=None)
    assert not (tmp_path / "rec").exists() and (tmp_path / "rec.partial" / "rgb").is_dir()
    monkeypatch.setattr(gen, "_exposed", exposed)
    # a run still writing its partial folder holds it (here this test, as another synth would): a second run into the
    # same --out is refused and leaves it alone (before: it removed the folder under the first, and both failed)
    from photoreg.io.atomic import hold_folder

    writing = hold_folder(tmp_path / "rec.partial", "--out")
    try:
        with pytest.raises(ValueError, match=r"rec.partial \(--out\) is in use by another run"):
            generate(cfg, log=None)
        assert (tmp_path / "rec.partial" / gen.PARTIAL_MARK).is_file()
    finally:
        os.close(writing)
    assert generate(cfg, log=None) == tmp_path / "rec"
    assert (tmp_path / "rec" / "scene.json").is_file() and not (tmp_path / "rec.partial").exists()
    assert not (tmp_path / "rec" / gen.PARTIAL_MARK).exists()


def test_an_unfinished_render_is_made_on_the_output_s_own_file_system_and_others_are_kept(tmp_path, monkeypatch):
    """An existing empty --out (a mount point, as docker/compose.yaml's /out) gets its unfinished recording inside it,
    OUT/.partial, whose files then move within one file system (before: OUT.partial beside it, on the parent's, and
    the move failed with 'Invalid cross-device link' after the whole render); an interrupted one there is started
    again. A folder OUT.partial that no run of synth made is refused and kept (before: removed)."""
    import photoreg.synth.generate as gen

    exposed = gen._exposed

    def interrupted(scene, cfg, layout, i, pose, seed):
        raise KeyboardInterrupt

    (tmp_path / "mnt").mkdir()
    monkeypatch.chdir(tmp_path)   # --out relative, as typed (its .partial was taken for another's content)
    cfg = SynthConfig("plane", "mnt", frames=1, width=16, height=12, spp=1, insert_frames="none")
    monkeypatch.setattr(gen, "_exposed", interrupted)
    with pytest.raises(KeyboardInterrupt):
        generate(cfg, log=None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mnt"]
    assert [p.name for p in (tmp_path / "mnt").iterdir()] == [gen.PARTIAL]
    assert (tmp_path / "mnt" / gen.PARTIAL / gen.PARTIAL_MARK).is_file()
    monkeypatch.setattr(gen, "_exposed", exposed)
    assert str(generate(cfg, log=None)) == "mnt"
    assert (tmp_path / "mnt" / "scene.json").is_file() and not (tmp_path / "mnt" / gen.PARTIAL).exists()

    (tmp_path / "y.partial").mkdir()
    (tmp_path / "y.partial" / "thesis.txt").write_text("precious")
    cfg = SynthConfig("plane", str(tmp_path / "y"), frames=1, width=16, height=12, spp=1, insert_frames="none")
    with pytest.raises(ValueError, match=r"y.partial exists and is not an interrupted photoreg synth run's"):
        generate(cfg, log=None)
    assert (tmp_path / "y.partial" / "thesis.txt").read_text() == "precious" and not (tmp_path / "y").exists()


def test_an_empty_folder_given_as_dot_or_a_link_receives_the_recording(tmp_path, monkeypatch):
    """--out . (an empty working folder) and a link to an empty folder: the files move into it (before: '.' has an
    empty name; a link rendered every frame, then failed, leaving LINK.partial)."""
    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    assert cli.main(["synth", "plane", "--out", ".", "--frames", "1", "--size", "16x12", "--spp", "1",
                     "--insert-frames", "none"]) == 0
    assert (tmp_path / "here" / "scene.json").is_file() and not (tmp_path / "here.partial").exists()
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    cfg = SynthConfig("plane", str(tmp_path / "link"), frames=1, width=16, height=12, spp=1, insert_frames="none")
    assert generate(cfg, log=None) == tmp_path / "link"
    assert (tmp_path / "link").is_symlink() and (tmp_path / "real" / "rgb" / "000000.png").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["here", "link", "real"]


def test_refuses_non_empty_output(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("x")
    assert cli.main(["synth", "plane", "--out", str(tmp_path)]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    assert cli.main(["synth", "plane", "--out", str(tmp_path / "keep.txt" / "sub")]) == 2   # not a raw [Errno 20]
    assert f"{tmp_path / 'keep.txt'} is a file, not a folder" in capsys.readouterr().err


def test_input_files_are_recorded_by_absolute_path(tmp_path, monkeypatch):
    """--insert-mesh (as --mesh and --env) given relative to the working folder goes into scene.json as an absolute
    path: rerender_inserts (photoreg bench renderers) reads it from another folder (before: as typed, and the bench
    failed after its last frame, 'mesh file not found')."""
    for name in ("here", "elsewhere"):
        (tmp_path / name).mkdir()
    (tmp_path / "here" / "ball.obj").write_text(trimesh.exchange.obj.export_obj(trimesh.creation.icosphere(1)))
    monkeypatch.chdir(tmp_path / "here")
    rec = tmp_path / "rec"
    assert cli.main(["synth", "plane", "--out", str(rec), "--frames", "1", "--size", "16x12", "--spp", "1",
                     "--insert-frames", "0", "--insert-mesh", "ball.obj"]) == 0
    meta = json.loads((rec / "scene.json").read_text())
    assert meta["config"]["insert_mesh"] == str(tmp_path / "here" / "ball.obj")
    assert f"--insert-mesh {tmp_path / 'here' / 'ball.obj'}" in meta["command"]
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert sorted(rerender_inserts(rec)) == [0]



def test_textured_insert_against_mitsuba(tmp_path):
    """`photoreg synth --insert-texture`: Mitsuba renders the inserted cube with scenes.insert_texture() over every
    face, and the recording's session asks for albedo = "texture" of object.obj (+ object.mtl and its image). Inside
    the cube (the insert mask, eroded a pixel) the pipeline's composites follow those renders' pattern (correlation
    per channel) far better with the texture than with its mean colour or with the image upside down: the texture
    lands where the independent renderer puts it (the shading error all three share cancels out)."""
    from PIL import Image

    from photoreg.config import load_session
    from photoreg.io.images import srgb_to_linear
    from photoreg.runner import run_session

    rec = tmp_path / "rec"
    assert cli.main(["synth", "tabletop", "--out", str(rec), "--frames", "8", "--size", "128x96", "--spp", "16",
                     "--insert-frames", "3,7", "--insert-texture"]) == 0
    assert "--insert-texture" in json.loads((rec / "scene.json").read_text())["command"]
    session = load_session(rec / "session.toml")
    assert session.objects[0].albedo == "texture" and (rec / "object.mtl").is_file()
    image = rec / (rec / "object.mtl").read_text().split("map_Kd ")[1].split()[0]
    texture = np.asarray(Image.open(image).convert("RGB"))

    def correlation(name: str, albedo=None) -> float:
        s = load_session(rec / "session.toml")
        s.output.dir, s.output.pictures_every = str(tmp_path / name), 0
        if albedo is not None:
            s.objects[0].albedo = albedo
        run_session(s, quiet=True)
        values = []
        for f in sorted((rec / "insert_mask").glob("*.png")):
            inside = cv2.erode((cv2.imread(str(f))[..., 0] > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            truth, ours = (cv2.imread(str(folder / f.name)).astype(float)[inside]
                           for folder in (rec / "insert", tmp_path / name / "composite"))
            values += [np.corrcoef(truth[:, k], ours[:, k])[0, 1] for k in range(3)]
        return float(np.mean(values))

    textured = correlation("textured")
    mean = correlation("mean", list(map(float, srgb_to_linear(texture).mean((0, 1)))))
    Image.fromarray(texture[::-1].copy()).save(image)                  # the image upside down
    flipped = correlation("flipped")
    assert textured > 0.5 and textured > mean + 0.2 and textured > flipped + 0.3, (textured, mean, flipped)


def test_inserted_mesh_against_mitsuba(tmp_path):
    """`photoreg synth --insert-mesh`: Mitsuba renders the file's mesh, smooth, where the recording's session places
    object.obj (its vertex normals written out, `smooth = true`): the session's object projects onto the insert
    mask (the convex mesh's projected hull), and inside the object the composites with smooth normals follow the
    path tracer's shading pattern (correlation per channel: the small recording's lighting is off in scale and colour
    for both) far better than with the faces' own, on an icosahedron whose 20 facets flat shading shows."""
    from photoreg.config import load_session
    from photoreg.render.scene import load_object
    from photoreg.runner import run_session

    mesh = tmp_path / "ball.obj"
    mesh.write_text(trimesh.exchange.obj.export_obj(trimesh.creation.icosphere(subdivisions=0)))
    rec = tmp_path / "rec"
    assert cli.main(["synth", "tabletop", "--out", str(rec), "--frames", "8", "--size", "128x96", "--spp", "64",
                     "--insert-frames", "3,7", "--insert-mesh", str(mesh)]) == 0
    assert "--insert-mesh" in json.loads((rec / "scene.json").read_text())["command"]
    assert "\nvn " in (rec / "object.obj").read_text()
    session = load_session(rec / "session.toml")
    assert session.objects[0].smooth and session.objects[0].scale == INSERT_MESH_SCALE
    K = json.loads((rec / "intrinsics.json").read_text())
    _, poses = read_tum_trajectory(rec / "groundtruth.txt")
    world = load_object(session.objects[0]).vertices
    masks = {int(f.stem): cv2.imread(str(f))[..., 0] > 0 for f in sorted((rec / "insert_mask").glob("*.png"))}
    overlap = []
    for i, mask in masks.items():
        cam = (world - poses[i][:3, 3]) @ poses[i][:3, :3]
        u, v = K["fx"] * cam[:, 0] / cam[:, 2] + K["cx"], K["fy"] * cam[:, 1] / cam[:, 2] + K["cy"]
        hull = np.zeros(mask.shape, np.uint8)   # the convex object's projection, pixel centres inside it
        cv2.fillConvexPoly(hull, cv2.convexHull(np.round(np.stack([u, v], 1) * 16).astype(np.int32)), 1,
                           lineType=cv2.LINE_8, shift=4)
        assert mask[cv2.dilate(hull, np.ones((3, 3), np.uint8)) == 0].sum() <= 0.02 * mask.sum(), i
        overlap.append((mask & (hull > 0)).sum() / (mask | (hull > 0)).sum())
    assert max(overlap) > 0.85, overlap   # real objects hide part of it in some frames

    def correlation(smooth: bool) -> float:
        """Mean correlation per channel and frame of the composites (linear) with the insert renders inside the
        insert masks, eroded a pixel."""
        s = load_session(rec / "session.toml")
        s.output.dir, s.output.pictures_every = str(tmp_path / f"smooth{smooth}"), 0
        s.objects[0].smooth = smooth
        run_session(s, quiet=True)
        values = []
        for i, mask in masks.items():
            inside = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            truth, ours = (read_exr(folder / f"{i:06d}.exr")
                           for folder in (rec / "insert", tmp_path / f"smooth{smooth}" / "composite_linear"))
            values += [np.corrcoef(truth[inside][:, k], ours[inside][:, k])[0, 1] for k in range(3)]
        return float(np.mean(values))

    smooth, flat = correlation(True), correlation(False)
    assert smooth > 0.6 and smooth > flat + 0.06, (smooth, flat)


def test_an_environment_must_be_high_dynamic_range(tmp_path):
    """--env takes radiance (.hdr, .exr); an 8-bit picture's display values are refused (they were taken for linear
    radiance, and the ground-truth SH made of them)."""
    picture = tmp_path / "sky.png"
    cv2.imwrite(str(picture), np.full((8, 16, 3), 200, np.uint8))
    with pytest.raises(ValueError, match=r"sky.png: a uint8 image, not a high dynamic range one"):
        load_environment(str(picture))
    radiance = tmp_path / "sky.hdr"
    cv2.imwrite(str(radiance), np.full((8, 16, 3), 2.5, np.float32))
    image, _ = load_environment(str(radiance))
    assert np.allclose(image, 2.5, rtol=0.02)
