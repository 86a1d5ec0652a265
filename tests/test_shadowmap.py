"""`shadowmap` renderer (photoreg.render.shadowmap): a cube floating over the real floor grid under a known
sun plus sky. The shadow lands where the analytic projection puts it, PCSS widens the penumbra with the
light's size, a real shadow is not darkened twice, and lighting without a light leaves the frame alone."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import trimesh

from photoreg.config import ObjectConfig
from photoreg.kernels.raycast import raycast_surface
from photoreg.kernels.shadowmap import shadow_lookup
from photoreg.kernels.transfer import make_direction_set
from photoreg.lighting import sh
from photoreg.lighting.parametric import lobe_sh, parametric_light
from photoreg.render.composite import RenderInput, composite
from photoreg.render.gbuffer import GBufferRenderer
from photoreg.render.registry import get_renderer
from photoreg.render.scene import load_scene, sdf_grid, voxel_grid
from photoreg.render.shadowmap import fit_shadow_map
from photoreg.types import Intrinsics

INTR = Intrinsics(128, 96, 100.0, 100.0, 63.5, 47.5)
LOOK_DOWN = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1.0], [0, 0, 0, 1]])  # camera at z=1 facing -z
SUN = np.array([math.sin(math.radians(30)), 0.0, math.cos(math.radians(30))])       # 30 deg from zenith, +x
CUBE_Z = (0.1, 0.3)                                                                   # 0.2 m cube, floating
WALL = (np.array([0.15, -0.6, 0.0]), np.array([0.25, 0.0, 0.8]))                     # a real box for the test


def _sun_and_sky(angle=math.radians(2.0), sun=8.0, sky=0.3, bands=5):
    """F of a disc sun (integrated radiance `sun`) toward SUN plus a uniform sky of radiance `sky`."""
    F = lobe_sh(np.array([sun, sun, sun]), SUN, angle, bands)
    F[:, 0] += sky * math.sqrt(4 * math.pi)
    return F


def _real_grid(wall: bool, voxel=0.02, trunc=0.08):
    """Real geometry: the floor z = 0 over [-0.64, 0.64]^2, optionally with the WALL box standing on it."""
    origin = np.array([-0.64, -0.64, -0.32])
    idx = np.stack(np.meshgrid(*[np.arange(64)] * 3, indexing="ij"), -1)
    p = origin + idx * voxel
    sdf = p[..., 2].copy()
    if wall:
        c, h = (WALL[0] + WALL[1]) / 2, (WALL[1] - WALL[0]) / 2
        q = np.abs(p - c) - h
        box = np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)
        sdf = np.minimum(sdf, box)
    return sdf_grid(sdf, origin, voxel, trunc, "cpu")


def _wall_shadow_pixels() -> np.ndarray:
    """Floor pixels in the WALL's real shadow (the sun is toward +x, 30 deg from zenith)."""
    xs = np.arange(INTR.width)
    ys = np.arange(INTR.height)
    x = (xs[None, :] - INTR.cx) / INTR.fx                     # floor z = 0 is 1 m from the camera
    y = -(ys[:, None] - INTR.cy) / INTR.fy
    reach = WALL[1][2] * math.tan(math.radians(30))
    return (x > WALL[0][0] - reach + 0.02) & (x < WALL[0][0] - 0.02) & (y < -0.02) & (y > WALL[0][1] + 0.02)


def _input(tmp_path, F, wall=False, wall_ratio=None) -> RenderInput:
    mesh = tmp_path / "cube.obj"
    trimesh.creation.box(extents=(1, 1, 1)).export(mesh)
    scene = load_scene([ObjectConfig(mesh=str(mesh), position=[0.0, 0.0, sum(CUBE_Z) / 2], scale=0.2)])
    grid = _real_grid(wall)
    maps = raycast_surface(grid, INTR, LOOK_DOWN, 0.1, 3.0, stride=2)
    gb = GBufferRenderer(scene, INTR, 2).render(LOOK_DOWN, raycast_surface(grid, INTR, LOOK_DOWN, 0.1, 3.0).depth)
    camera = np.full((INTR.height, INTR.width, 3), 0.4, np.float32)
    if wall_ratio is not None:                                    # the frame shows the wall's real shadow
        camera[_wall_shadow_pixels()] *= np.asarray(wall_ratio, np.float32)
    return RenderInput(camera, F, 1.0, grid, voxel_grid(scene, 0.02, "cpu"), maps, gb, scene.bounds,
                       lambda b: make_direction_set(32, b, seed=0), 0.03, 1.5, scene=scene)


def _project(points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of world points under LOOK_DOWN."""
    c = (points - LOOK_DOWN[:3, 3]) @ LOOK_DOWN[:3, :3]
    return np.stack([INTR.fx * c[:, 0] / c[:, 2] + INTR.cx, INTR.fy * c[:, 1] / c[:, 2] + INTR.cy], 1)


def _analytic_shadow() -> np.ndarray:
    """Mask of the floor pixels inside the cube's shadow: the hull of its corners projected along -SUN."""
    corners = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.1, 0.1) for z in CUBE_Z])
    on_floor = corners - SUN * (corners[:, 2] / SUN[2])[:, None]
    hull = cv2.convexHull(np.round(_project(on_floor) * 16).astype(np.int32))
    mask = np.zeros((INTR.height, INTR.width), np.uint8)
    cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def test_shadow_falls_at_the_projected_position(tmp_path):
    inp = _input(tmp_path, _sun_and_sky())
    layers = get_renderer("shadowmap")(inp)
    out = composite(inp.camera, layers)
    assert np.all(np.isfinite(out)) and layers.ratio.min() >= 0 and layers.ratio.max() <= 1
    light = parametric_light(inp.F)
    real = inp.gbuffer.coverage == 0
    shadow = (layers.ratio[..., 0] < 1 - light.opacity[0] / 2) & real
    truth = _analytic_shadow() & real
    iou = (shadow & truth).sum() / (shadow | truth).sum()
    assert truth.sum() > 150 and iou > 0.85, iou
    # full shadow strength is the parametric opacity: ratio = 1 - o inside the umbra
    core = cv2.erode(truth.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    np.testing.assert_allclose(layers.ratio[core].mean(0), 1 - light.opacity, atol=0.03)
    # the side away from the light is untouched, the object's top is lit, its side facing away is not
    assert np.all(layers.ratio[:, 90:] == 1)
    top = inp.gbuffer.coverage == 1
    lit = top & (inp.gbuffer.normal[..., 2] > 0.9)
    assert layers.colour[lit].mean() > 0


def test_virtual_surface_self_shadow(tmp_path):
    """A face turned away from the light gets the ambient only; the top gets ambient plus the sun."""
    inp = _input(tmp_path, _sun_and_sky())
    layers = get_renderer("shadowmap")(inp)
    light = parametric_light(inp.F)
    gb = inp.gbuffer
    top = (gb.coverage == 1) & (gb.normal[..., 2] > 0.99)
    e_top = sh.irradiance(light.residual, np.array([[0, 0, 1.0]]))[0] + light.lobe_irradiance() * SUN[2]
    np.testing.assert_allclose(layers.colour[top].mean(0), 0.8 * e_top / math.pi, rtol=0.03)


def test_pcss_penumbra_widens_with_the_light_size(tmp_path):
    inp = _input(tmp_path, _sun_and_sky())
    vertices, faces, _ = inp.scene.triangles()
    smap = fit_shadow_map(vertices, faces, SUN, "cpu", resolution=256)
    x = np.linspace(-0.45, 0.25, 281)                              # a line across the shadow, y = 0
    dx = x[1] - x[0]
    pts = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (len(x), 1))
    widths = []
    for deg in (0.5, 3.0, 8.0):
        s, radius = shadow_lookup(smap, pts, nrm, math.tan(math.radians(deg)), 0.01)
        assert s.max() > 0.99 and s.min() == 0                    # umbra and open floor on the line
        widths.append(((s > 0.02) & (s < 0.98)).sum() * dx)      # both edges' penumbrae, metres along x
    assert widths[0] < widths[1] < widths[2], widths
    # the light's disc spans 30 +- 8 deg: edges from the top (0.3 m) and bottom (0.1 m) corners are
    # 0.3 (tan 38 - tan 22) + 0.1 (tan 38 - tan 22) = 0.15 m wide together
    assert 0.1 < widths[2] < 0.2, widths
    hard, _ = shadow_lookup(smap, pts, nrm, math.tan(math.radians(8.0)), 0.01, pcss=False)
    assert ((hard > 0.02) & (hard < 0.98)).sum() * dx < 0.01     # plain PCF: a texel or two per edge


def test_real_shadow_is_not_darkened_twice(tmp_path):
    light = parametric_light(_sun_and_sky())
    inp = _input(tmp_path, _sun_and_sky(), wall=True, wall_ratio=1 - light.opacity)   # as the light predicts
    layers = get_renderer("shadowmap")(inp)
    truth = _analytic_shadow() & (inp.gbuffer.coverage == 0)
    core = cv2.erode(truth.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    rows = np.arange(INTR.height)[:, None]
    # image rows above cy are world y > 0 (camera y = -world y): the wall shades world y < 0 only; rows
    # within 5 px (5 cm, 2.5 voxels of the real grid) of y = 0 see the wall's voxelised edge
    open_part, walled = core & (rows < INTR.cy - 5), core & (rows > INTR.cy + 5)
    assert open_part.sum() > 20 and walled.sum() > 20
    np.testing.assert_allclose(layers.ratio[open_part].mean(0), 1 - light.opacity, atol=0.03)
    assert layers.ratio[walled].min() > 0.95                      # already in the wall's shadow: left alone


@pytest.mark.parametrize("shadow", [(0.5, 0.5, 0.5), (0.3, 0.45, 0.75)], ids=["grey", "sky-tinted"])
def test_virtual_shadow_takes_the_measured_strength(tmp_path, shadow):
    """Jacobs et al.: where the frame shows real shadows, the virtual shadow is as dark as they are
    (here half the lit radiance, or a shadow the sky tints blue), not as dark as the parametric light says (about
    0.9 of it blocked). The tinted shadow is a colour group of its own, joined to the floor it falls on (before:
    the floor kept no shadowed point and the parametric strength stood)."""
    inp = _input(tmp_path, _sun_and_sky(), wall=True, wall_ratio=shadow)
    layers = get_renderer("shadowmap")(inp)
    assert any("material 0 shadow strength measured" in n for n in layers.notes)
    core = cv2.erode((_analytic_shadow() & (inp.gbuffer.coverage == 0)).astype(np.uint8),
                     np.ones((5, 5), np.uint8)).astype(bool)
    open_part = core & (np.arange(INTR.height)[:, None] < INTR.cy - 5)
    assert open_part.sum() > 20
    np.testing.assert_allclose(layers.ratio[open_part].mean(0), shadow, atol=0.05)
    assert parametric_light(inp.F).opacity.min() > 0.8                # the parametric strength would differ


@pytest.mark.parametrize("F", [np.zeros((3, 25)), np.full((3, 25), np.nan), _sun_and_sky(sun=0.0)])
def test_no_light_gives_ratio_one(tmp_path, F):
    inp = _input(tmp_path, F)
    layers = get_renderer("shadowmap")(inp)
    assert np.all(layers.ratio == 1) and np.all(np.isfinite(layers.colour))
    assert np.array_equal(layers.alpha, inp.gbuffer.coverage) and layers.notes
    assert np.all(np.isfinite(composite(inp.camera, layers)))


def test_missing_scene_is_an_error(tmp_path):
    inp = _input(tmp_path, _sun_and_sky())
    inp.scene = None
    with pytest.raises(ValueError, match="RenderInput.scene"):
        get_renderer("shadowmap")(inp)
