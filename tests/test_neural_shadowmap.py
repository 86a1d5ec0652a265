"""neural_shadowmap renderer (issue 6): the committed ONNX network in cv2.dnn, the shadow-map buffers, the
network's shadow against the voxel renderer on a held-out procedural scene (and a scrambled-weight control
that must fail the same bar), and the renderer's layers. No PyTorch needed."""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from photoreg.config import ObjectConfig
from photoreg.kernels.raycast import raycast_surface
from photoreg.kernels.transfer import make_direction_set
from photoreg.lighting.parametric import lobe_sh, parametric_light
from photoreg.render.composite import RenderInput, composite
from photoreg.render.gbuffer import GBufferRenderer
from photoreg.render.neural_shadowmap import WEIGHTS, load_net, predict_visibility
from photoreg.render.registry import get_renderer
from photoreg.render.scene import load_scene, sdf_grid, voxel_grid
from photoreg.render.shadow_buffers import CHANNELS, SM_RESOLUTION, shadow_buffers
from photoreg.render.shadowmap import fit_shadow_map
from photoreg.types import Intrinsics

INTR = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
LOOK_DOWN = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1.0], [0, 0, 0, 1]])  # camera at z=1 facing -z
SUN = np.array([math.sin(math.radians(30)), 0.0, math.cos(math.radians(30))])        # 30 degrees off zenith


def _floor_grid(voxel=0.02, trunc=0.08):
    """Real geometry: the plane z = 0 over [-0.64, 0.64]^2 (occupied below)."""
    origin = np.array([-0.64, -0.64, -0.32])
    z = origin[2] + np.arange(32) * voxel
    return sdf_grid(np.broadcast_to(z[None, None, :], (64, 64, 32)).copy(), origin, voxel, trunc, "cpu")


def _cube_scene(tmp_path):
    path = tmp_path / "cube.obj"
    trimesh.creation.box(extents=(1, 1, 1)).export(path)
    return load_scene([ObjectConfig(mesh=str(path), position=[0.0, 0.0, 0.1], scale=0.2)])  # on the floor


def _sun_sky(direction=SUN, bands=5):
    return lobe_sh(np.array([3.0, 2.9, 2.7]), direction, math.radians(3.0), bands) + np.outer([0.3, 0.3, 0.35],
                                                                                              np.eye(bands * bands)[0])


def test_committed_network_loads_in_cv2_dnn():
    assert WEIGHTS.is_file() and WEIGHTS.stat().st_size <= 2 * 1024 * 1024
    rng = np.random.default_rng(0)
    for shape in [(96, 128), (50, 70)]:                           # a multiple of 32, and one padded to it
        x = rng.uniform(-1, 1, (len(CHANNELS),) + shape).astype(np.float32)
        v = predict_visibility(x, load_net())
        assert v.shape == shape and v.dtype == np.float32 and np.all(np.isfinite(v))
        assert v.min() >= 0.0 and v.max() <= 1.0


def test_missing_weights_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.onnx"):
        load_net(tmp_path / "nope.onnx")


def test_buffers_emitter_depths(tmp_path):
    """Lit virtual receivers read the map's depth = their own light depth; floor receivers behind the cube
    read the cube's depth along their light ray (slab test), the others their own depth."""
    scene = _cube_scene(tmp_path)
    floor = _floor_grid()
    maps = raycast_surface(floor, INTR, LOOK_DOWN, 0.1, 3.0)
    gb = GBufferRenderer(scene, INTR, 2).render(LOOK_DOWN, maps.depth)
    light = parametric_light(_sun_sky())
    assert np.allclose(light.direction, SUN, atol=1e-3)
    verts, faces, _ = scene.triangles()
    smap = fit_shadow_map(verts, faces, light.direction, "cpu", SM_RESOLUTION)
    buf = shadow_buffers(maps, gb, light, smap)
    e_sm, e_px = buf.data[4], buf.data[5]
    assert np.all(e_sm <= e_px) and np.all(buf.data[:, ~buf.valid] == 0)
    top = buf.virtual & np.isclose(gb.depth, 0.8, atol=1e-3)           # the cube's top face, lit
    assert top.sum() > 20 and np.abs(e_sm[top] - e_px[top]).max() < 2e-3
    real = buf.valid & ~buf.virtual
    p = maps.vertex[real].astype(np.float64)
    d = light.direction
    with np.errstate(divide="ignore", invalid="ignore"):               # slab test of p + t d against the cube
        t0, t1 = (np.array([-0.1, -0.1, 0.0]) - p) / d, (np.array([0.1, 0.1, 0.2]) - p) / d
    t_in = np.nanmax(np.minimum(t0, t1), axis=1)
    t_out = np.nanmin(np.maximum(t0, t1), axis=1)
    hit = (t_in < t_out - 0.01) & (t_in > 0.01)
    assert hit.sum() > 20 and (~hit).sum() > 100
    gap = (e_px - e_sm)[real]
    assert np.abs(gap[hit] - t_out[hit]).max() < 5e-3                 # blocker depth = the far slab hit
    clear = (t_in > t_out + 0.01) | (t_out < 0)
    assert np.all(gap[clear] == 0)
    assert np.allclose(buf.data[6][real], maps.normal[real] @ d + light.angle, atol=1e-5)


def _scrambled_net():
    """The committed network with every weight tensor's entries shuffled: same graph, no learnt structure."""
    net = load_net(WEIGHTS)
    scrambled = __import__("cv2").dnn.readNetFromONNX(str(WEIGHTS))
    rng = np.random.default_rng(0)
    for name in net.getLayerNames():
        lid = scrambled.getLayerId(name)
        layer = scrambled.getLayer(lid)
        for k, blob in enumerate(layer.blobs):
            if blob.ndim == 4 and blob.shape[2:] != (2, 2):            # not the fixed space-to-depth
                scrambled.setParam(lid, k, rng.permutation(blob.ravel()).reshape(blob.shape).astype(blob.dtype))
    return scrambled


def test_network_shadow_follows_voxel_on_held_out_scene():
    """A procedural scene from a seed family the training never used: the network's shadow correlates with
    the voxel renderer's and beats `none` and the unfiltered shadow map; the scrambled control does not
    reach the same bar."""
    from photoreg.train.shadow_data import make_views
    from photoreg.train.shadow_eval import evaluate

    views = make_views(np.random.default_rng([7, 0]), 2)
    v = {k: np.stack([getattr(x, k) for x in views]) for k in ("buffers", "target", "opacity", "weight")}
    trained = evaluate(v, lambda b: np.stack([predict_visibility(x, load_net()) for x in b]))
    scrambled = _scrambled_net()
    control = evaluate(v, lambda b: np.stack([predict_visibility(x, scrambled) for x in b]))
    assert trained["roi_pixels"] > 500
    assert trained["shadow_correlation"] > 0.8 and trained["rmse_roi"] < 0.6 * trained["rmse_none"], trained
    assert trained["rmse_roi"] < trained["rmse_hard_shadowmap"], trained       # better than its raw input
    assert control["shadow_correlation"] < 0.8 or control["rmse_roi"] > 0.6 * control["rmse_none"], control


def test_renderer_layers(tmp_path):
    """A 128x96 view (lighting stride 2: 120 px focal at the buffers, inside the training range) of the cube
    on the floor from 1 m above: finite layers, and under a sun 30 degrees off zenith the floor beside the
    cube's -x face is darker than beside its +x face, and the floor the shadow map holds no blocker over is left as
    it is (the network's visibility strays below 1 there); with a band-0 lighting nothing changes."""
    intr = Intrinsics(128, 96, 240.0, 240.0, 63.5, 47.5)
    scene = _cube_scene(tmp_path)
    floor, virt = _floor_grid(), voxel_grid(scene, 0.02, "cpu")
    maps = raycast_surface(floor, intr, LOOK_DOWN, 0.1, 3.0, stride=2)
    gb = GBufferRenderer(scene, intr, 2).render(LOOK_DOWN, raycast_surface(floor, intr, LOOK_DOWN, 0.1, 3.0).depth)
    camera = np.full((96, 128, 3), 0.4, np.float32)
    render = get_renderer("neural_shadowmap")
    # the cube's 11.5 cm shadow lies at -0.215 < x < -0.1 on the floor: columns 12-39 at 1 m, its side faces
    # reach column 33; the mirror image at +x (columns 96-111) is lit
    rows, shadow_cols, lit_cols = slice(35, 60), slice(16, 31), slice(96, 111)
    for F, shadowed in [(_sun_sky(), True), (np.outer([0.5, 0.5, 0.5], np.eye(25)[0]), False)]:
        inp = RenderInput(camera, F, 1.0, floor, virt, maps, gb, scene.bounds,
                          lambda b: make_direction_set(32, b, seed=0), 0.03, 0.3, scene=scene)
        layers = render(inp)
        out = composite(camera, layers)
        assert np.all(np.isfinite(out)) and np.all(np.isfinite(layers.colour))
        assert layers.ratio.shape == camera.shape and layers.ratio.min() >= 0 and layers.ratio.max() <= 1
        assert np.array_equal(layers.alpha, gb.coverage)
        real = gb.coverage == 0
        assert np.all(out[real] <= camera[real] + 1e-6) and real[rows, shadow_cols].all() and real[rows, lit_cols].all()
        if shadowed:
            assert layers.ratio[rows, shadow_cols].mean() < layers.ratio[rows, lit_cols].mean() - 0.1
            assert (layers.colour[gb.coverage == 1] > 0).all()
            assert np.all(layers.ratio[:, 96:] == 1.0) and np.all(layers.ratio[:8] == 1.0)   # nothing blocks there
        else:
            assert np.all(layers.ratio == 1.0) and any("no directional light" in n for n in layers.notes)
