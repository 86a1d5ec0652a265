"""Fusion (Open3D VoxelBlockGrid), its dense Warp export, the Warp surface ray cast and the transfer
kernel, on analytic scenes (photoreg.synth.analytic) with exact depth, normals and visibility."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from photoreg.device import init_warp, warp_cache_dir
from photoreg.kernels.grid import SDF_NUMPY
from photoreg.kernels.raycast import raycast_surface
from photoreg.kernels.transfer import make_direction_set, radiance_transfer
from photoreg.lighting.sh import unoccluded_transfer
from photoreg.recon.fusion import RESTART_AFTER, FusionConfig, TSDFVolume, VolumeLimitError
from photoreg.synth.analytic import PrimitiveScene, box_room
from photoreg.synth.cameras import default_intrinsics, look_at
from photoreg.types import Intrinsics

wp = init_warp()

VOXEL = 0.02
K320 = default_intrinsics(320, 240, hfov_deg=70.0)
K160 = default_intrinsics(160, 120, hfov_deg=70.0)


def room_poses(n: int, seed: int = 0) -> list[np.ndarray]:
    """Views of box_room(): three fixed ones (the x = 1 wall's foot, the floor centre, the box) plus
    random ones looking at least 0.8 m ahead."""
    poses = [look_at([-0.6, 0.0, 1.4], [0.8, 0.1, 0.1]), look_at([0.1, -0.3, 1.5], [0.0, 0.0, 0.0]),
             look_at([0.0, 0.2, 1.3], [0.7, -0.7, 0.2])]
    rng = np.random.default_rng(seed)
    while len(poses) < n:
        eye, target = rng.uniform([-0.7, -0.7, 0.8], [0.7, 0.7, 1.6]), rng.uniform([-0.9, -0.9, 0.0], [0.9, 0.9, 1.0])
        if np.linalg.norm(target - eye) > 0.8:
            poses.append(look_at(eye, target))
    return poses


def fuse(scene: PrimitiveScene, intr, poses, cfg: FusionConfig) -> TSDFVolume:
    vol = TSDFVolume(cfg, "cpu")
    for pose in poses:
        depth, _ = scene.render_depth(intr, pose)
        vol.integrate(depth, intr, pose)
    return vol


@pytest.fixture(scope="module")
def room():
    """box_room() fused from 12 views at 320x240 with 2 cm voxels, and its dense grid."""
    scene, poses = box_room(), room_poses(12)
    vol = fuse(scene, K320, poses, FusionConfig(voxel_size=VOXEL, block_resolution=16))
    return scene, poses, vol, vol.dense_grid()


def vbg_voxels(vol: TSDFVolume):
    """World position, normalised tsdf and weight of every allocated Open3D voxel, plus its block key
    and (x, y, z) inside the block, decoded from the flattened index."""
    R = vol.cfg.block_resolution
    coords, flat = vol.vbg.voxel_coordinates_and_flattened_indices()
    flat = flat.numpy().ravel()
    buf, local = flat // R ** 3, flat % R ** 3
    xyz = np.stack([local % R, (local // R) % R, local // (R * R)], axis=1)  # z-major storage
    key = vol.vbg.hashmap().key_tensor().numpy()[buf]
    tsdf = vol.vbg.attribute("tsdf").numpy().reshape(-1)[flat]
    weight = vol.vbg.attribute("weight").numpy().reshape(-1)[flat]
    return coords.numpy().astype(np.float64), tsdf, weight, key, xyz


def dense_values(grid, points: np.ndarray) -> np.ndarray:
    idx = np.rint(grid.world_to_index(points)).astype(int)
    return grid.sdf.numpy()[idx[:, 0], idx[:, 1], idx[:, 2]]


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def smooth_region(normal: np.ndarray, depth: np.ndarray, k: int) -> np.ndarray:
    """Pixels whose (2k+1)^2 neighbourhood lies on one smooth surface (true normals within 20 degrees)."""
    H, W = depth.shape
    padded = np.pad(normal, ((k, k), (k, k), (0, 0)))
    ok = depth > 0
    for dy in range(2 * k + 1):
        for dx in range(2 * k + 1):
            ok &= (padded[dy:dy + H, dx:dx + W] * normal).sum(-1) > np.cos(np.radians(20.0))
    return ok


# --- Open3D conventions and the dense export ------------------------------------------------------

def test_open3d_voxel_layout_and_tsdf_convention():
    """Voxel (x, y, z) of block b lies at (b * res + (x, y, z)) * voxel, stored z-major; tsdf is the
    projective SDF (depth at the nearest pixel - camera z) / trunc, clamped to 1; extrinsic = world-to-camera."""
    floor = PrimitiveScene(boxes=[(np.array([-3.0, -3.0, -1.0]), np.array([3.0, 3.0, 0.0]))])
    pose = look_at([0.2, -0.1, 1.0], [0.6, 0.3, 0.0])
    cfg = FusionConfig(voxel_size=VOXEL, block_resolution=8)
    vol = fuse(floor, K160, [pose], cfg)
    coords, tsdf, weight, key, xyz = vbg_voxels(vol)
    np.testing.assert_allclose(coords, (key * 8 + xyz) * VOXEL, atol=1e-5)

    depth, _ = floor.render_depth(K160, pose)
    cam = (coords - pose[:3, 3]) @ pose[:3, :3]  # world -> camera
    uf, vf = K160.fx * cam[:, 0] / cam[:, 2] + K160.cx, K160.fy * cam[:, 1] / cam[:, 2] + K160.cy
    u, v = np.rint(uf).astype(int), np.rint(vf).astype(int)
    tie = (np.abs(np.abs(uf - u) - 0.5) < 1e-3) | (np.abs(np.abs(vf - v) - 0.5) < 1e-3)  # float32 rounding in Open3D
    seen = (weight > 0) & ~tie
    assert seen.sum() > 10000
    expected = np.clip((depth[v[seen], u[seen]] - cam[seen, 2]) / cfg.trunc, -1.0, 1.0)
    np.testing.assert_allclose(tsdf[seen], expected, atol=1e-4)
    assert np.all(weight[weight > 0] == 1.0)


def test_dense_export_places_a_known_value():
    """A value written into one Open3D voxel shows up at that voxel's world position in the brick."""
    cfg = FusionConfig(voxel_size=VOXEL, block_resolution=8)
    scene, pose = box_room(), room_poses(1)[0]
    vol = fuse(scene, K160, [pose], cfg)
    keys = vol.active_block_coords().numpy()
    buf = int(vol.vbg.hashmap().find(vol.active_block_coords())[0].numpy()[0])
    key = keys[0]
    vol.vbg.attribute("tsdf")[buf, 3, 2, 1, 0] = -0.375  # z = 3, y = 2, x = 1
    vol.vbg.attribute("weight")[buf, 3, 2, 1, 0] = 5.0
    grid = vol.dense_grid()
    world = (key * 8 + np.array([1, 2, 3])) * VOXEL
    assert dense_values(grid, world[None])[0] == pytest.approx(-0.375 * cfg.trunc)
    idx = grid.world_to_index(world[None])[0]
    np.testing.assert_allclose(idx, np.rint(idx), atol=1e-9)  # voxel centres on the grid


def test_dense_export_matches_voxel_block_grid_and_grows():
    cfg = FusionConfig(voxel_size=VOXEL, block_resolution=8, grid_margin_blocks=1)
    scene = box_room()
    vol = TSDFVolume(cfg, "cpu")
    first = look_at([0.0, 0.0, 1.2], [1.0, 0.0, 0.6])    # the +x wall
    second = look_at([0.0, 0.0, 1.2], [-1.0, 0.0, 0.6])  # the -x wall: outside the first brick
    depth, _ = scene.render_depth(K160, first)
    vol.integrate(depth, K160, first)
    g1 = vol.dense_grid()
    before = g1.sdf.numpy().copy()
    depth, _ = scene.render_depth(K160, second)
    vol.integrate(depth, K160, second)
    g2 = vol.dense_grid()
    assert g2.origin[0] < g1.origin[0] and g2.shape[0] > g1.shape[0]
    # only the side that fell short grows, and by a share of the extent, so a turning camera regrows it rarely
    assert g2.shape[0] - g1.shape[0] >= cfg.grid_growth * g1.shape[0]
    assert g2.origin[0] + (g2.shape[0] - 1) * VOXEL == pytest.approx(g1.origin[0] + (g1.shape[0] - 1) * VOXEL)

    coords, tsdf, weight, *_ = vbg_voxels(vol)
    expected = np.where(weight >= cfg.min_weight, tsdf * cfg.trunc, cfg.trunc)
    np.testing.assert_allclose(dense_values(g2, coords), expected, atol=1e-6, rtol=2.0 ** -11)  # float16 brick
    # what the first brick held survives the copy, voxel for voxel
    off = np.rint((g1.origin - g2.origin) / VOXEL).astype(int)
    copied = g2.sdf.numpy()[off[0]:off[0] + g1.shape[0], off[1]:off[1] + g1.shape[1], off[2]:off[2] + g1.shape[2]]
    changed = copied != before
    assert changed.mean() < 0.2  # only where the second view overlapped
    # voxels outside every allocated block read +trunc (unobserved = empty)
    assert np.count_nonzero(g2.sdf.numpy() < cfg.trunc) <= np.count_nonzero(weight > 0)

    # a view inside the brick reuses it
    depth, _ = scene.render_depth(K160, first)
    vol.integrate(depth, K160, first)
    assert vol.dense_grid().sdf is g2.sdf


def test_empty_space_distance_field(room):
    """grid.empty = Chebyshev distance (in cells, capped) to the nearest cell holding anything below +trunc."""
    from scipy.ndimage import distance_transform_cdt

    from photoreg.kernels.grid import EMPTY_CAP

    *_, grid = room
    c = grid.cell
    sdf = grid.sdf.numpy()
    cells = sdf.reshape(sdf.shape[0] // c, c, sdf.shape[1] // c, c, sdf.shape[2] // c, c).min(axis=(1, 3, 5))
    occupied = cells < grid.trunc
    assert 0.05 < occupied.mean() < 0.6
    expected = np.minimum(distance_transform_cdt(~occupied, metric="chessboard"), EMPTY_CAP)
    np.testing.assert_array_equal(grid.empty.numpy(), expected)


def test_empty_volume_gives_an_empty_grid():
    vol = TSDFVolume(FusionConfig(voxel_size=VOXEL, block_resolution=8), "cpu")
    vol.integrate(np.zeros((K160.height, K160.width), np.float32), K160, np.eye(4))  # no valid depth
    assert vol.frames_integrated == 0
    grid = vol.dense_grid()
    assert np.all(grid.sdf.numpy() == SDF_NUMPY(grid.trunc))
    maps = raycast_surface(grid, K160, look_at([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]), 0.1, 4.0)
    assert not maps.valid.any()
    # a pixel of depth in a tiny frame, where Open3D's touch pass finds no block and raised ("No block is touched";
    # a client's 2 x 2 camera had the server send that C++ message): nothing fused, nothing raised
    tiny = Intrinsics(8, 6, 8.0, 8.0, 3.5, 2.5, 1000.0)
    depth = np.zeros((6, 8), np.float32)
    depth[3, 4] = 1.0
    vol.integrate(depth, tiny, np.eye(4))
    assert vol.frames_integrated == 0


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not init_warp().is_cuda_available(), reason="no CUDA device here (runs on the GPU machine: gpu_run.sh fusion)"))])
def test_a_frame_past_the_brick_limit_is_not_fused(device):
    """A frame whose depth would stretch the brick past max_dense_voxels (a wrong pose, as a rule) raises before
    anything is fused, and the volume stays as it was; far-off poses do not overflow the count. RESTART_AFTER such
    frames in a row start the volume again (the wrong pose was the earlier one, or the camera walked off)."""
    scene, pose = box_room(), room_poses(1)[0]
    depth, _ = scene.render_depth(K160, pose)
    small = TSDFVolume(FusionConfig(voxel_size=VOXEL, block_resolution=8, max_dense_voxels=20000), device)
    with pytest.raises(VolumeLimitError, match="max_dense_voxels = 20000"):
        small.integrate(depth, K160, pose)
    assert small.frames_integrated == 0 and small.active_block_coords().shape[0] == 0

    vol = TSDFVolume(FusionConfig(voxel_size=VOXEL, block_resolution=8), device)
    vol.integrate(depth, K160, pose)
    g1 = vol.dense_grid()
    before, blocks = g1.sdf.numpy().copy(), vol.active_block_coords().shape[0]
    for shift in (100.0, 1e6):
        far = pose.copy()
        far[:3, 3] += shift
        with pytest.raises(VolumeLimitError, match="was not fused"):
            vol.integrate(depth, K160, far)
    assert vol.frames_integrated == 1 and vol.active_block_coords().shape[0] == blocks
    g2 = vol.dense_grid()
    assert g2.shape == g1.shape and np.array_equal(g2.sdf.numpy(), before)
    # a frame that fits ends the run of refusals; RESTART_AFTER far ones in a row start the volume again from the last
    vol.integrate(depth, K160, pose)
    assert vol.rejected_in_row == 0 and vol.frames_integrated == 2
    far = pose.copy()
    far[:3, 3] += 100.0
    for _ in range(RESTART_AFTER - 1):
        with pytest.raises(VolumeLimitError):
            vol.integrate(depth, K160, far)
    vol.integrate(depth, K160, far)
    assert vol.restarts == 1 and vol.rejected_in_row == 0 and vol.frames_integrated == 3
    g3 = vol.dense_grid()
    assert np.all(g3.origin > g1.origin + 90.0) and vol.active_block_coords().shape[0] == blocks


def test_volume_holds_depth_only_and_meshes():
    """No colour is fused (nothing reads it): 8 bytes a voxel, and the mesh (benchmarks/peers.py) still comes out."""
    vol = fuse(box_room(), K160, room_poses(1), FusionConfig(voxel_size=VOXEL, block_resolution=8))
    values = vol.vbg.hashmap().value_tensors()
    assert sum(v[0].num_elements() * v.dtype.byte_size() for v in values) == 8 * 8 ** 3
    assert len(vol.extract_mesh().vertex.positions) > 1000


def test_bad_inputs_are_clear_errors(room):
    _, poses, vol, grid = room
    depth = np.ones((K160.height, K160.width), np.float32)
    bad = poses[0].copy()
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        vol.integrate(depth, K160, bad)
    with pytest.raises(ValueError, match="depth shape"):
        vol.integrate(depth[:-1], K160, poses[0])
    with pytest.raises(ValueError, match="finite"):
        raycast_surface(grid, K160, bad, 0.1, 4.0)
    dirs, Y = make_direction_set(8, 2)
    with pytest.raises(ValueError, match="count"):
        radiance_transfer(grid, np.zeros((3, 3)), np.zeros((2, 3)), dirs, Y, VOXEL, 0.5)
    with pytest.raises(ValueError, match="rows"):
        radiance_transfer(grid, np.zeros((3, 3)), np.zeros((3, 3)), dirs, Y[:-1], VOXEL, 0.5)


# --- surface ray cast -----------------------------------------------------------------------------

def test_raycast_matches_truth_and_open3d(room):
    """On smooth surfaces (3 voxels away from edges): Warp within half a voxel and 5 degrees of the
    analytic scene; against Open3D's ray_cast on the same volume, surfaces within one voxel along the
    normal. Open3D's own ray cast (nearest-lower voxel lookups, one-cell gradients) is the looser one:
    its normals are within 5 degrees of the truth on only ~90% of these pixels, so the Warp-Open3D
    normal agreement is bounded by that, not by the Warp kernel."""
    scene, poses, vol, grid = room
    for pose in poses[:3]:
        maps = raycast_surface(grid, K320, pose, 0.1, 4.0)
        d_o3d, n_o3d = vol.raycast_open3d(K320, pose)
        d_true, n_true = scene.render_depth(K320, pose)
        k = int(np.ceil(3 * VOXEL / (np.median(d_true) / K320.fx)))
        smooth = smooth_region(n_true, d_true, k)
        assert smooth.mean() > 0.5
        assert maps.valid[smooth].mean() > 0.999 and (d_o3d > 0)[smooth].mean() > 0.99
        both = smooth & maps.valid & (d_o3d > 0)

        assert (np.abs(maps.depth - d_true)[both] < VOXEL / 2).mean() > 0.99
        assert (angle_deg(maps.normal, n_true)[both] < 5.0).mean() > 0.98
        np.testing.assert_allclose(np.linalg.norm(maps.normal[maps.valid], axis=-1), 1.0, atol=1e-5)
        ray = np.stack([*np.meshgrid((np.arange(K320.width) - K320.cx) / K320.fx,
                                     (np.arange(K320.height) - K320.cy) / K320.fy), np.ones((K320.height, K320.width))],
                       -1) @ pose[:3, :3].T  # world ray per unit camera z
        np.testing.assert_allclose(maps.vertex[maps.valid], (pose[:3, 3] + ray * maps.depth[..., None])[maps.valid],
                                   atol=1e-4)

        along_normal = np.abs(((maps.depth - d_o3d)[..., None] * ray * maps.normal).sum(-1))
        assert (along_normal[both] < VOXEL).mean() > 0.95
        warp_err, o3d_err = angle_deg(maps.normal, n_true)[both], angle_deg(n_o3d, n_true)[both]
        assert np.median(warp_err) < np.median(o3d_err)
        assert (angle_deg(maps.normal, n_o3d)[both] < 5.0).mean() > 0.85
        assert (angle_deg(maps.normal, n_o3d)[both] < 10.0).mean() > 0.98


def test_normal_smoothing_averages_noise_and_keeps_edges():
    """normal_smoothing (reconstruction.normal_smoothing_voxels): box_room fused from 4 views of depth with
    Gaussian noise (sigma 5 mm, 2 cm voxels). Where the truth is smooth over the radius the tangent mean is much
    closer to the true normals than each point's own; near edges no worse; the surface itself is unchanged."""
    scene, poses = box_room(), room_poses(4)
    rng = np.random.default_rng(0)
    vol = TSDFVolume(FusionConfig(voxel_size=VOXEL, block_resolution=16), "cpu")
    for pose in poses:
        depth, _ = scene.render_depth(K320, pose)
        vol.integrate(np.where(depth > 0, depth + rng.normal(0.0, 0.005, depth.shape), 0.0).astype(np.float32),
                      K320, pose)
    grid = vol.dense_grid()
    for pose in poses[:2]:
        plain = raycast_surface(grid, K320, pose, 0.1, 4.0)
        smooth = raycast_surface(grid, K320, pose, 0.1, 4.0, normal_smoothing=3.0)
        np.testing.assert_array_equal(plain.depth, smooth.depth)
        d_true, n_true = scene.render_depth(K320, pose)
        px = 4 * VOXEL / (np.median(d_true) / K320.fx)   # 4 voxels in pixels at the median depth
        flat = smooth_region(n_true, d_true, int(np.ceil(px))) & plain.valid
        edge = plain.valid & (d_true > 0) & ~smooth_region(n_true, d_true, int(np.ceil(px / 2)))
        assert flat.mean() > 0.3 and edge.sum() > 200
        e_plain, e_smooth = angle_deg(plain.normal, n_true), angle_deg(smooth.normal, n_true)
        assert np.median(e_smooth[flat]) < 0.5 * np.median(e_plain[flat])   # 4.9 -> 0.6 degrees when written
        assert np.percentile(e_smooth[edge], 90) < np.percentile(e_plain[edge], 90) + 1.0
        np.testing.assert_allclose(np.linalg.norm(smooth.normal[smooth.valid], axis=-1), 1.0, atol=1e-5)
    with pytest.raises(ValueError, match="normal_smoothing"):
        raycast_surface(grid, K320, poses[0], 0.1, 4.0, normal_smoothing=-1.0)


def test_raycast_stride_samples_every_nth_pixel(room):
    _, poses, _, grid = room
    full = raycast_surface(grid, K320, poses[1], 0.1, 4.0)
    strided = raycast_surface(grid, K320, poses[1], 0.1, 4.0, stride=4)
    assert strided.depth.shape == (60, 80)
    np.testing.assert_array_equal(strided.depth, full.depth[::4, ::4])
    np.testing.assert_array_equal(strided.normal, full.normal[::4, ::4])


# --- transfer ---------------------------------------------------------------------------------------

# Quadrature error of the direction set alone (V = 1) against (1/pi) A_l Y_lm(n), max over 2000 random
# normals, B = 3: 6.3e-3 at 32 rays, 2.2e-3 at 64, 1.0e-3 at 128, 4e-4 at 256 (R_00 = 0.282), so
# 64 rays get a 3e-3 tolerance; the kernel itself must equal that quadrature to float32 rounding.
QUADRATURE_TOL = {64: 3e-3, 256: 6e-4}


def host_quadrature(normals: np.ndarray, dirs: np.ndarray, Y: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """R by the same quadrature in float64, visibility (N, D) given."""
    cos = np.clip(normals @ dirs.T.astype(np.float64), 0.0, None) * visible
    return cos @ Y.astype(np.float64) * 4.0 / len(dirs)


@pytest.mark.parametrize("rays", [64, 256])
def test_transfer_unoccluded_equals_analytic(room, rays):
    """Points with nothing within the ray length: a floor point at the room's centre (normal up) and
    points in mid-air with random normals."""
    _, _, _, grid = room
    rng = np.random.default_rng(1)
    normals = rng.normal(size=(6, 3))
    normals = np.vstack([[0.0, 0.0, 1.0], normals / np.linalg.norm(normals, axis=1, keepdims=True)])
    points = np.vstack([[0.0, 0.0, 0.0], np.tile([0.0, 0.0, 1.0], (6, 1))])
    dirs, Y = make_direction_set(rays, 3, seed=7)
    res = radiance_transfer(grid, points, normals, dirs, Y, offset=VOXEL, ray_length=0.5)
    assert res.transfer.shape == (7, 9) and res.transfer.dtype == np.float32
    np.testing.assert_array_equal(res.visible_fraction, 1.0)
    np.testing.assert_allclose(res.transfer, host_quadrature(normals, dirs, Y, 1.0), atol=2e-6)
    np.testing.assert_allclose(res.transfer, unoccluded_transfer(normals, 3), atol=QUADRATURE_TOL[rays])


def test_transfer_next_to_a_wall(room):
    """A floor point 5 cm from the x = 1 wall (nothing else within 0.7 m): rays of length L <= 0.7 m
    are blocked by the wall iff w_x > 0.05 / L, so (x-marginal uniform over a hemisphere) the visible
    fraction is (1 + 0.05 / L) / 2, tending to 0.5 (the corner's half-space) for long rays; R matches
    the same quadrature with exact visibility from the analytic scene. (Longer rays would reach parts
    of the room the views never saw, which count as empty.)"""
    scene, _, _, grid = room
    point, normal = np.array([[0.95, 0.2, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    dirs, Y = make_direction_set(256, 3, seed=3)
    hemi = (normal @ dirs.T)[0] > 0
    for length in (0.25, 0.5):
        res = radiance_transfer(grid, point, normal, dirs, Y, offset=VOXEL, ray_length=length)
        assert res.visible_fraction[0] == pytest.approx((1 + 0.05 / length) / 2, abs=0.025)
        t_hit, _ = scene.intersect(point + normal * VOXEL, dirs)
        visible = t_hit > length
        assert res.visible_fraction[0] == pytest.approx(visible[hemi].mean(), abs=0.015)
        np.testing.assert_allclose(res.transfer, host_quadrature(normal, dirs, Y, visible[None]), atol=0.01)
        assert res.transfer[0, 0] < 0.8 * unoccluded_transfer(normal, 3)[0, 0]
        assert np.all(np.isfinite(res.transfer))


def test_transfer_on_raycast_samples(room, monkeypatch):
    """The full chain on a strided ray cast: Warp maps go straight in (no host copy); all finite. The projection's
    thread layouts (a point's coefficients in one thread on the CPU, one thread each on a GPU) give the same bits,
    up to the 8 bands a session allows."""
    import photoreg.kernels.transfer as transfer

    _, poses, _, grid = room
    maps = raycast_surface(grid, K320, poses[0], 0.1, 4.0, stride=8)
    dirs, Y = make_direction_set(32, 3, seed=0)
    res = radiance_transfer(grid, maps.vertex_wp, maps.normal_wp, dirs, Y, offset=VOXEL, ray_length=0.5)
    n = maps.depth.size
    assert res.transfer.shape == (n, 9) and res.occlusion_wp.shape == (n, 64)
    assert np.all(np.isfinite(res.transfer)) and np.all(np.isfinite(res.visible_fraction))
    valid = maps.valid.ravel()
    assert np.all(res.transfer[~valid] == 0) and np.all(res.visible_fraction[~valid] == 0)
    layouts = []
    for group in (lambda device, K: K, lambda device, K: 1):
        monkeypatch.setattr(transfer, "_project_group", group)
        layouts.append(radiance_transfer(grid, maps.vertex_wp, maps.normal_wp, *make_direction_set(40, 8, seed=0),
                                         offset=VOXEL, ray_length=0.5))
    assert layouts[0].transfer.shape == (n, 64) and np.abs(layouts[0].transfer).max() > 0
    np.testing.assert_array_equal(layouts[0].transfer, layouts[1].transfer)
    np.testing.assert_array_equal(layouts[0].visible_fraction, layouts[1].visible_fraction)
    with pytest.raises(ValueError, match="81 coefficients, more than 64"):
        radiance_transfer(grid, maps.vertex_wp, maps.normal_wp, *make_direction_set(48, 9, seed=0), offset=VOXEL,
                          ray_length=0.5)
    frac = res.visible_fraction[valid]
    assert np.all((frac >= 0) & (frac <= 1)) and 0.3 < frac.mean() < 1.0
    from_numpy = radiance_transfer(grid, maps.vertex, maps.normal, dirs, Y, offset=VOXEL, ray_length=0.5)
    np.testing.assert_array_equal(res.transfer, from_numpy.transfer)


# --- determinism and the kernel cache ----------------------------------------------------------------

def test_relaunch_is_identical_and_uses_the_loaded_kernels(room):
    _, poses, _, grid = room
    dirs, Y = make_direction_set(16, 3, seed=0)

    def run():
        maps = raycast_surface(grid, K160, poses[2], 0.1, 4.0)
        res = radiance_transfer(grid, maps.vertex_wp, maps.normal_wp, dirs, Y, offset=VOXEL, ray_length=0.5)
        return maps, res

    a, ra = run()
    modules = [wp.get_module(name) for name in ("photoreg.kernels.grid", "photoreg.kernels.raycast",
                                                "photoreg.kernels.transfer")]
    loaded = [dict(m.execs) for m in modules]
    b, rb = run()
    for arr_a, arr_b in [(a.depth, b.depth), (a.vertex, b.vertex), (a.normal, b.normal),
                         (ra.transfer, rb.transfer), (ra.visible_fraction, rb.visible_fraction)]:
        np.testing.assert_array_equal(arr_a, arr_b)
    for m, before in zip(modules, loaded):
        assert before and all(m.execs[key] is exe for key, exe in before.items())  # no reload, no recompile
    # compiled once into the project's cache folder (conftest: PHOTOREG_WARP_CACHE), reused by later sessions
    cache = Path(wp.config.kernel_cache_dir)
    assert cache.is_relative_to(warp_cache_dir())
    for m in modules:
        assert all((cache / m.get_module_identifier(block_dim)).is_dir() for _, block_dim in m.execs)


def test_empty_space_distance_on_random_occupancy():
    """update_empty_distance (three separable passes) equals scipy's chessboard distance,
    capped at EMPTY_CAP, on random bricks from empty to full, odd shapes included."""
    from scipy.ndimage import distance_transform_cdt

    from photoreg.kernels.grid import EMPTY_CAP, update_empty_distance

    rng = np.random.default_rng(1)
    for trial, density in enumerate([0.0, 1.0, 0.001, 0.01, 0.1, 0.5] * 3):
        shape = tuple(int(x) for x in rng.integers(1, 25, 3))
        occupied = rng.random(shape) < density
        occ = wp.array(occupied.astype(np.uint8) * (trial + 1), dtype=wp.uint8, device="cpu")
        empty = wp.empty_like(occ)
        update_empty_distance(occ, empty)
        expected = (np.minimum(distance_transform_cdt(~occupied, metric="chessboard"), EMPTY_CAP) if occupied.any()
                    else np.full(shape, EMPTY_CAP))
        np.testing.assert_array_equal(empty.numpy(), expected, err_msg=f"shape {shape}, density {density}")


def test_clean_depth_is_fused_as_the_raw_depth_would_be():
    """integrate(..., clean=True) skips the masking the pipeline's prepare already did: the depth of prepare (holes,
    NaN, +-inf, depth nearer than depth_min in the raw frame) fuses into the same brick as the raw depth masked by
    integrate itself."""
    from photoreg.config import Session
    from photoreg.preprocess import prepare
    from photoreg.types import Frame

    scene, poses = box_room(), room_poses(3)
    rng = np.random.default_rng(2)
    vols = [TSDFVolume(FusionConfig(voxel_size=VOXEL, block_resolution=16), "cpu") for _ in range(2)]
    s = Session()
    for pose in poses:
        depth, _ = scene.render_depth(K160, pose)
        spoilt = rng.random(depth.shape)
        depth[spoilt < 0.05], depth[spoilt > 0.97] = np.nan, np.inf
        depth[(spoilt > 0.5) & (spoilt < 0.52)] = 0.05   # nearer than depth_min (0.1)
        prep = prepare(Frame(0, 0.0, np.full((K160.height, K160.width, 3), 128, np.uint8), depth, K160, pose),
                       s.lighting, s.reconstruction)
        assert s.reconstruction.depth_min == vols[0].cfg.depth_min
        vols[0].integrate(prep.depth, K160, pose, clean=True)
        vols[1].integrate(depth, K160, pose)
    a, b = (v.dense_grid().sdf.numpy() for v in vols)
    assert (a < vols[0].cfg.trunc).mean() > 0.01 and np.array_equal(a, b)
