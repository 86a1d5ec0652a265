"""Virtual objects (issue 5): scene transform, bad objects, G-buffer projection and occlusion, voxel
shadows, differential compositing. Small frames and few rays, so the whole file runs in seconds."""
from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from photoreg.config import ObjectConfig
from photoreg.device import init_warp
from photoreg.kernels.raycast import raycast_surface
from photoreg.kernels.transfer import VIRTUAL, any_blocked, make_direction_set, radiance_transfer, shaded_pass
from photoreg.lighting import sh
from photoreg.render.composite import RenderInput, composite, shade, upsample_ratio
from photoreg.render.gbuffer import GBufferRenderer
from photoreg.render.registry import get_renderer
from photoreg.render.scene import load_scene, object_transform, sdf_grid, voxel_grid
from photoreg.types import Intrinsics

REPO = Path(__file__).resolve().parents[1]
INTR = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
LOOK_DOWN = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1.0], [0, 0, 0, 1]])  # camera at z=1 facing -z
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(   # the G-buffer kernels' devices
    not init_warp().is_cuda_available(), reason="no CUDA device here (runs on the GPU machine: gpu_run.sh gbcheck)"))]


def _cube(tmp_path, **kw) -> ObjectConfig:
    path = tmp_path / "cube.obj"
    trimesh.creation.box(extents=(1, 1, 1)).export(path)
    return ObjectConfig(mesh=str(path), **kw)


def _sphere(tmp_path):
    path = tmp_path / "sphere.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=0.5).export(path)
    return path


def _floor_grid(voxel=0.02, trunc=0.08):
    """Real geometry: the plane z = 0 over [-0.64, 0.64]^2 (occupied below)."""
    n = 64
    origin = np.array([-0.64, -0.64, -0.32])
    z = origin[2] + np.arange(32) * voxel
    sdf = np.broadcast_to(z[None, None, :], (n, n, 32)).copy()
    return sdf_grid(sdf, origin, voxel, trunc, "cpu")


def test_transform_convention(tmp_path):
    obj = _cube(tmp_path, position=[1.0, 2.0, 3.0], rotation=[0.0, 0.0, 90.0], scale=2.0)
    T = object_transform(obj)
    assert np.allclose(T @ [1, 0, 0, 1], [1.0, 4.0, 3.0, 1.0])      # world = R (s v) + p, R_z(90) x -> y
    v = load_scene([obj]).objects[0].vertices
    assert np.allclose(v.min(0), [0, 1, 2]) and np.allclose(v.max(0), [2, 3, 4])


def test_bad_objects_are_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        load_scene([ObjectConfig(mesh=str(tmp_path / "nope.obj"))])
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(ValueError, match="empty.obj"):
        load_scene([ObjectConfig(mesh=str(empty))])
    with pytest.raises(ValueError, match="cube.obj"):
        load_scene([_cube(tmp_path, position=[0.0, math.nan, 0.0])])
    with pytest.raises(ValueError, match=r"cube.obj: the object spans 100 m as placed \(scale 100.0\), more than 50 m"):
        load_scene([_cube(tmp_path, scale=100.0)])
    flat = tmp_path / "flat.obj"                     # every triangle a line: nothing to draw or to cast a shadow
    flat.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="flat.obj: mesh has no area"):
        load_scene([ObjectConfig(mesh=str(flat))])
    with pytest.raises(ValueError, match="no renderer"):
        get_renderer("raytraced")


def test_objects_far_apart_get_a_coarser_grid(tmp_path):
    """The objects' SDF grid holds at most GRID_MAX_VOXELS: two 1 m cubes 40 m apart (at the TSDF's 1 cm some 4000 x
    120 x 120 voxels) get coarser ones, and both are still inside (negative) at their centres."""
    from photoreg.render.scene import GRID_MAX_VOXELS, voxel_grid

    scene = load_scene([_cube(tmp_path, position=[0.0, 0.0, 0.0]), _cube(tmp_path, position=[40.0, 0.0, 0.0])])
    grid = voxel_grid(scene, 0.01, "cpu")
    assert math.prod(grid.shape) <= GRID_MAX_VOXELS and grid.voxel_size > 0.015
    idx = np.rint(grid.world_to_index(np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0]]))).astype(int)
    assert (grid.sdf.numpy()[tuple(idx.T)] < 0).all()


def test_gbuffer_known_projection_and_real_occlusion(tmp_path):
    scene = load_scene([_cube(tmp_path, position=[0.0, 0.0, 2.0], scale=0.4)])   # front face z = 1.8
    gb_r = GBufferRenderer(scene, INTR, supersample=2)
    gb = gb_r.render(np.eye(4))
    half = 50.0 * 0.2 / 1.8                                                      # 5.56 px
    rows, cols = np.nonzero(gb.coverage > 0.5)
    assert abs(cols.min() - math.ceil(31.5 - half)) <= 1 and abs(cols.max() - math.floor(31.5 + half)) <= 1
    assert abs(rows.min() - math.ceil(23.5 - half)) <= 1 and abs(rows.max() - math.floor(23.5 + half)) <= 1
    assert np.isclose(gb.coverage.sum(), (2 * half) ** 2, rtol=0.08)            # area, edges anti-aliased
    assert ((gb.coverage > 0) & (gb.coverage < 1)).any()
    assert np.allclose(gb.depth[23, 31], 1.8, atol=1e-3) and np.allclose(gb.normal[23, 31], [0, 0, -1], atol=1e-3)
    assert np.allclose(gb.albedo[23, 31], 0.8)
    real = np.zeros((48, 64), np.float32)
    real[:, :32] = 1.0                                                           # a real box in front, left half
    gb2 = gb_r.render(np.eye(4), real)
    assert gb2.coverage[:, :31].max() == 0 and gb2.coverage[:, 33:].max() > 0.99


def _resolve_reference(g, pose, color, zbuf, real, window, tolerance):
    """The G-buffer resolve by its definition (photoreg.kernels.gbuffer), in numpy: coverage and the window's depth,
    position, normal and albedo."""
    s, (x0, y0, x1, y1) = g.s, window
    h, w = y1 - y0, x1 - x0
    p0, normals, albedos = g.faces.p0.numpy(), g.faces.normal.numpy(), g.faces.albedo.numpy()
    code = color[..., :3].astype(np.int64)
    face = (code[..., 0] | (code[..., 1] << 8) | (code[..., 2] << 16)) - 1
    rd = np.repeat(np.repeat(real, s, 0), s, 1)
    hit = (zbuf > 0) & ~((rd > 0) & np.isfinite(rd) & (zbuf > rd + np.float32(tolerance)))
    v, u = np.nonzero(hit & (face >= 0) & (face < len(p0)))
    f = face[v, u]
    ray = np.stack([(u + x0 * s - g.hi.cx) / g.hi.fx, (v + y0 * s - g.hi.cy) / g.hi.fy, np.ones(len(u))], -1)
    ray = ray @ pose[:3, :3].T
    nf = normals[f]
    den = np.einsum("ij,ij->i", nf, ray)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.einsum("ij,ij->i", nf, p0[f] - pose[:3, 3]) / den
    ok = np.isfinite(z) & (np.abs(z - zbuf[v, u]) <= 2e-3 + 2e-3 * zbuf[v, u])
    v, u, f, z, ray, nf, den = v[ok], u[ok], f[ok], z[ok], ray[ok], nf[ok], den[ok]
    pix = (v // s) * w + u // s            # sequential: the last valid subsample of a pixel wins
    out = [np.zeros(h * w, np.float32)] + [np.zeros((h * w, 3), np.float32) for _ in range(3)]
    out[0][pix], out[1][pix] = z, pose[:3, 3] + ray * z[:, None]
    out[2][pix], out[3][pix] = nf * -np.sign(den)[:, None], albedos[f]
    shown = np.zeros(h * w, bool)
    shown[pix] = True
    cover = np.where(shown.reshape(h, w), hit.reshape(h, s, w, s).sum(axis=(1, 3)) / (s * s), 0.0)
    return [cover] + [a.reshape((h, w) + a.shape[1:]) for a in out]


def test_gbuffer_resolve_kernel_follows_its_definition(tmp_path):
    """The resolve kernel against its definition in numpy on real draws (a rotated cube and a bunny-like sphere
    behind it, anti-aliased edges, a real surface hiding part of it, a window): the same values, the coverage too."""
    from photoreg.render.gbuffer import _on_gl

    objs = [_cube(tmp_path, position=[0.05, 0.0, 2.0], scale=0.35, rotation=[20.0, 35.0, 10.0]),
            ObjectConfig(mesh=str(_sphere(tmp_path)), position=[-0.15, 0.05, 2.4], scale=0.3, albedo=[0.2, 0.6, 0.3])]
    g = GBufferRenderer(load_scene(objs), INTR, supersample=3)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [2.0, -3.0, 1.0], degrees=True).as_matrix()
    real = np.zeros((48, 64), np.float32)
    real[:, :30] = 1.9                                    # a real wall cutting through the cube's left part
    real[5:9, 40:44] = np.nan
    for window in ((0, 0, 64, 48), (10, 6, 55, 41)):
        x0, y0, x1, y1 = window
        h, w, s = y1 - y0, x1 - x0, g.s
        color, zbuf = _on_gl(g._draw, pose, g.viewport(w, h), x0 * s, y0 * s).result()
        ref = _resolve_reference(g, pose, color[:h * s, :w * s], zbuf[:h * s, :w * s], real[y0:y1, x0:x1], window,
                                 0.01)
        gb = g.render(pose, real, tolerance=0.01, window=window)
        got = [gb.coverage[y0:y1, x0:x1], gb.window_depth, gb.window_position, gb.window_normal, gb.window_albedo]
        assert ref[0].max() > 0.99 and 0 < ((ref[0] > 0) & (ref[0] < 1)).sum()   # covered, edges anti-aliased
        for a, b in zip(got, ref):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def _gbuffers_agree(a, b, pixels: int) -> None:
    """Two G-buffers of one view agree: coverage in all but `pixels` pixels (by one subsample there), every layer at
    the pixels both cover alike."""
    d = np.abs(a.coverage - b.coverage)
    assert (d > 0).sum() <= pixels and d.max() <= 1.0 / 4 + 1e-6, ((d > 0).sum(), d.max())
    same = (d == 0) & (a.coverage > 0)
    assert same.sum() > 0.95 * (a.coverage > 0).sum()
    for name in ("depth", "position", "normal", "albedo"):
        np.testing.assert_allclose(getattr(a, name)[same], getattr(b, name)[same], rtol=0, atol=1e-5, err_msg=name)


@pytest.mark.parametrize("device", DEVICES)
def test_raycast_gbuffer_is_the_draws(tmp_path, device):
    """render.gbuffer = 'raycast' traces each subsample's ray through the faces' BVH instead of drawing: the draw's
    G-buffer (coverage, anti-aliased edges, depth test against the real surface, attributes), windowed and whole, on
    the rotated cube and sphere of the resolve's test, with the kernels on `device` (pyrender draws on OSMesa here, on
    NVIDIA's EGL on a GPU machine); and pyrender's culling of back faces: an open quad turned away from the camera
    hides nothing, in both."""
    objs = [_cube(tmp_path, position=[0.05, 0.0, 2.0], scale=0.35, rotation=[20.0, 35.0, 10.0]),
            ObjectConfig(mesh=str(_sphere(tmp_path)), position=[-0.15, 0.05, 2.4], scale=0.3, albedo=[0.2, 0.6, 0.3])]
    quad = tmp_path / "quad.obj"                          # a square in z = 0 whose front faces +z
    trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]]).export(quad)
    back = ObjectConfig(mesh=str(quad), position=[0.2, 0.0, 1.5], scale=0.1)   # the camera looks along +z: its back
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [2.0, -3.0, 1.0], degrees=True).as_matrix()
    real = np.zeros((48, 64), np.float32)
    real[:, :30] = 1.9                                    # a real wall cutting through the cube's left part
    real[5:9, 40:44] = np.nan
    scene = load_scene(objs + [back])
    for s in (2, 3):
        drawn, traced = GBufferRenderer(scene, INTR, s, device), GBufferRenderer(scene, INTR, s, device, "raycast")
        assert not hasattr(traced, "gl")                  # no OpenGL at all
        for window in (None, (10, 6, 55, 41)):
            a, b = drawn.render(pose, real, 0.01, window), traced.render(pose, real, 0.01, window)
            assert b.coverage.max() == 1 and ((b.coverage > 0) & (b.coverage < 1)).any()   # edges anti-aliased
            assert (b.coverage[:, 30:] > 0).any() and not (b.coverage[:, :28] > 0).any()   # the wall hides the left
            _gbuffers_agree(a, b, pixels=2)
    alone = GBufferRenderer(load_scene(objs), INTR, 3, device, "raycast").render(pose, real, 0.01)
    np.testing.assert_array_equal(alone.coverage, traced.render(pose, real, 0.01).coverage)   # the quad hides nothing
    front = load_scene(objs + [ObjectConfig(mesh=str(quad), position=[0.2, 0.0, 1.5], scale=0.1,
                                            rotation=[180.0, 0.0, 0.0])])   # turned: its front faces the camera
    drawn, traced = GBufferRenderer(front, INTR, 2, device), GBufferRenderer(front, INTR, 2, device, "raycast")
    a, b = drawn.render(pose, real), traced.render(pose, real)
    nearest = b.depth == b.depth[b.depth > 0].min()
    assert b.coverage.sum() > alone.coverage.sum() + 5 and np.allclose(b.normal[nearest], [0, 0, -1], atol=1e-6)
    _gbuffers_agree(a, b, pixels=2)
    with pytest.raises(ValueError, match="backend"):
        GBufferRenderer(scene, INTR, 2, backend="optix")


def _textured_quad(path: Path, texture: np.ndarray, material=None) -> Path:
    """The square [-1, 1]^2 in z = 0, its front facing +z, texture coordinates (x + 1) / 2, (y + 1) / 2, exported
    with `texture` (8-bit RGB) through trimesh (OBJ: an .mtl and a PNG beside it; GLB: embedded)."""
    from PIL import Image

    image = Image.fromarray(texture)
    visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], image=image, material=material)
    trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]], visual=visual,
                    process=False).export(path)
    return path


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("backend", ["pyrender", "raycast"])
def test_gbuffer_albedo_from_the_mesh_texture(tmp_path, backend, device):
    """objects.albedo = "texture": a pixel's albedo is the mesh's base-colour texture at its point's texture
    coordinates, decoded from sRGB, bilinear between texel centres; checked against trimesh's own lookup
    (visual.color.uv_to_color, nearest texel) where the two agree (inside 2 x 2 blocks of equal texels), for an OBJ and
    for a GLB whose baseColorFactor scales the texture; a glTF material without an image gives its baseColorFactor;
    an object with neither (an OBJ with texture coordinates and no material among them) is a clear error."""
    from PIL import Image

    from photoreg.io.images import srgb_to_linear

    rng = np.random.default_rng(3)
    texture = np.kron(rng.integers(0, 256, (4, 4, 3)), np.ones((2, 2, 1))).astype(np.uint8)   # 8 x 8 texels
    factor = np.array([255, 128, 255, 255], np.uint8)
    glb = trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(texture), baseColorFactor=factor)
    scale = 0.4
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    local = np.stack([(u - INTR.cx) / INTR.fx, -(v - INTR.cy) / INTR.fy], -1) / scale   # LOOK_DOWN's hit on z = 0
    uv = ((local + 1) / 2).reshape(-1, 2)
    x, y = uv[:, 0] * 8 - 0.5, (1 - uv[:, 1]) * 8 - 0.5                             # texel coordinates
    exact = ((x % 2 >= 0.05) & (x % 2 <= 0.95) & (y % 2 >= 0.05) & (y % 2 <= 0.95)   # between a block's centres
             & (uv.min(1) > 0) & (uv.max(1) < 1)).reshape(INTR.height, INTR.width)
    looked_up = trimesh.visual.color.uv_to_color(np.clip(uv, 0, 1), Image.fromarray(texture))   # (trimesh 4.5: no wrap)
    want = srgb_to_linear(looked_up[:, :3].astype(np.uint8).reshape(INTR.height, INTR.width, 3))
    for mesh, gain in ((_textured_quad(tmp_path / "quad.obj", texture), 1.0),
                       (_textured_quad(tmp_path / "quad.glb", texture, glb), factor[:3] / 255.0)):
        scene = load_scene([ObjectConfig(mesh=str(mesh), scale=scale, albedo="texture")])
        gb = GBufferRenderer(scene, INTR, 2, device, backend).render(LOOK_DOWN)
        inside = exact & (gb.coverage == 1)
        assert inside.sum() > 150, inside.sum()
        np.testing.assert_allclose(gb.albedo[inside], (want * gain)[inside], rtol=0, atol=1e-5, err_msg=str(mesh))
        assert np.ptp(gb.albedo[gb.coverage == 1], axis=0).min() > 0.2                 # a texture, not one colour
        assert np.allclose(scene.objects[0].albedo, srgb_to_linear(texture).mean((0, 1)) * gain, atol=1e-5)
    colour = trimesh.visual.material.PBRMaterial(baseColorFactor=[255, 51, 0, 255])   # a glTF colour, no image
    flat = ObjectConfig(mesh=str(_textured_quad(tmp_path / "flat.glb", texture, colour)), scale=scale, albedo="texture")
    gb = GBufferRenderer(load_scene([flat]), INTR, 2, device, backend).render(LOOK_DOWN)
    assert (gb.coverage > 0).sum() > 200 and np.allclose(gb.albedo[gb.coverage > 0], [1.0, 0.2, 0.0], atol=1e-6)
    plain = tmp_path / "plain.obj"
    trimesh.creation.box().export(plain)
    bare = tmp_path / "bare.obj"                                   # texture coordinates, no material library
    bare.write_text("".join(line for line in (tmp_path / "quad.obj").read_text().splitlines(True)
                            if not line.startswith(("mtllib", "usemtl"))))
    for mesh in (plain, bare):
        with pytest.raises(ValueError, match=f"{mesh.name}.*no texture image, base colour or vertex"):
            load_scene([ObjectConfig(mesh=str(mesh), albedo="texture")])
    with pytest.raises(ValueError, match="albedo"):
        load_scene([ObjectConfig(mesh=str(plain), albedo="wood")])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("suffix", ["glb", "obj"])
@pytest.mark.parametrize("backend", ["pyrender", "raycast"])
def test_gbuffer_albedo_of_a_mesh_of_several_materials(tmp_path, backend, suffix, device):
    """A GLB (an OBJ) of two quads with materials of their own (one a texture image, one a glTF base colour alone,
    an OBJ's Kd): each quad's pixels take their own material's albedo up to its edges, the imaged quad's as the
    one-material texture test checks it. trimesh's merged mesh packs both into one atlas image, whose padding
    bleeds into the faces near its tiles' edges (and which made a base colour an 8-bit image): every pixel of the
    plain quad was off."""
    from PIL import Image

    from photoreg.io.images import srgb_to_linear

    texture = np.kron(np.random.default_rng(5).integers(0, 256, (2, 2, 3)), np.ones((4, 4, 1))).astype(np.uint8)
    plain = np.array([230, 89, 26]) / 255.0             # glTF base colours, Kd: linear (trimesh keeps 8 bits)
    quad = [[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]]
    left, right = (trimesh.Trimesh(np.c_[np.array(quad[0]) + [x, -0.5], np.zeros(4)], quad[1], process=False,
                                   visual=trimesh.visual.TextureVisuals(uv=quad[0], material=m))
                   for x, m in ((-1.0, trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(texture))),
                                (0.0, trimesh.visual.material.PBRMaterial(baseColorFactor=[*plain, 1.0]))))
    path = tmp_path / f"two.{suffix}"
    trimesh.Scene([left, right]).export(path)
    scale = 0.4
    scene = load_scene([ObjectConfig(mesh=str(path), scale=scale, albedo="texture")])
    assert len(scene.objects[0].textures) == 2 and np.isfinite(scene.objects[0].albedo).all()
    gb = GBufferRenderer(scene, INTR, 2, device, backend).render(LOOK_DOWN)
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    x, y = (u - INTR.cx) / INTR.fx / scale, -(v - INTR.cy) / INTR.fy / scale   # LOOK_DOWN's hit, the quads' frame
    full = gb.coverage == 1
    on_plain = full & (x > 0.02)
    assert on_plain.sum() > 300 and (full & (x > 0.95)).any()                   # up to the outer edge
    np.testing.assert_allclose(gb.albedo[on_plain], np.broadcast_to(plain, (on_plain.sum(), 3)), rtol=0, atol=1e-6)
    tx, ty = (x + 1) * 8 - 0.5, (0.5 - y) * 8 - 0.5                              # the image's texel coordinates
    blocks = ((tx % 4 >= 0.05) & (tx % 4 <= 2.95) & (ty % 4 >= 0.05) & (ty % 4 <= 2.95)   # between a block's centres
              & (x < -0.02) & (x > -0.98) & (np.abs(y) < 0.48))
    on_image = full & blocks
    want = srgb_to_linear(texture)[np.clip(ty, 0, 7).astype(int), np.clip(tx, 0, 7).astype(int)]
    assert on_image.sum() > 150
    np.testing.assert_allclose(gb.albedo[on_image], want[on_image], rtol=0, atol=1e-5)


def test_gbuffer_albedo_of_kenneys_desk_chair(data_dir):
    """Kenney's chairDesk.glb (three glTF materials, base colours alone) from four sides: every pixel wholly on the
    chair takes exactly one of its materials' colours (through trimesh's packed atlas, a tenth of them were off by
    more than 0.01 and every one by the 8-bit image's rounding)."""
    from photoreg.synth.cameras import look_at

    path = data_dir / "meshes" / "kenney_chairs" / "chairDesk.glb"
    colours = np.unique([g.visual.material.baseColorFactor[:3] for g in trimesh.load(path).geometry.values()],
                        axis=0) / 255.0
    assert len(colours) == 2
    scene = load_scene([ObjectConfig(mesh=str(path), rotation=[90, 0, 0], scale=0.5, albedo="texture")])
    centre, size = scene.bounds.mean(0), np.ptp(scene.bounds, 0).max()
    K = Intrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)
    renderer = GBufferRenderer(scene, K, 2, "cpu", "raycast")
    seen = np.zeros(len(colours), int)
    for azimuth in np.radians([30, 120, 210, 300]):
        gb = renderer.render(look_at(centre + 1.6 * size * np.array([np.cos(azimuth), np.sin(azimuth), 0.6]), centre))
        albedo = gb.albedo[gb.coverage == 1]
        gap = np.abs(albedo[:, None] - colours[None]).max(-1)
        assert len(albedo) > 1500 and gap.min(1).max() < 1e-6, gap.min(1).max()
        seen += np.bincount(gap.argmin(1), minlength=len(colours))
    assert seen.min() > 1000, seen


@pytest.mark.parametrize("backend", ["pyrender", "raycast"])
def test_gbuffer_albedo_from_vertex_and_face_colours(tmp_path, backend):
    """objects.albedo = "texture" on a mesh with vertex colours (a PLY) interpolates their linear values over each
    face; with face colours each face takes its own; both decoded from sRGB (the quad of the texture test, split
    along its diagonal y = x)."""
    from photoreg.io.images import srgb_to_linear

    corners = np.array([[200, 30, 30, 255], [30, 200, 30, 255], [30, 30, 200, 255], [220, 220, 40, 255]], np.uint8)
    quad = [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]]
    trimesh.Trimesh(*quad, vertex_colors=corners, process=False).export(tmp_path / "vertex.ply")
    trimesh.Trimesh(*quad, face_colors=corners[:2], process=False).export(tmp_path / "face.ply")
    scale = 0.4
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    x, y = (u - INTR.cx) / INTR.fx / scale, -(v - INTR.cy) / INTR.fy / scale   # LOOK_DOWN's hit, the quad's frame
    L = srgb_to_linear(corners[None, :, :3])[0]
    lower = (y <= x)[..., None]                                                # triangle 0 1 2, else 0 2 3
    b1, b2 = np.where(lower[..., 0], (x - y) / 2, (x + 1) / 2), np.where(lower[..., 0], (y + 1) / 2, (y - x) / 2)
    want_vertex = (L[0] * (1 - b1 - b2)[..., None] + np.where(lower, L[1], L[2]) * b1[..., None]
                   + np.where(lower, L[2], L[3]) * b2[..., None])
    want_face = np.where(lower, L[0], L[1])
    for name, want in (("vertex", want_vertex), ("face", want_face)):
        gb = GBufferRenderer(load_scene([ObjectConfig(mesh=str(tmp_path / f"{name}.ply"), scale=scale,
                                                      albedo="texture")]), INTR, 2, "cpu", backend).render(LOOK_DOWN)
        inside = (gb.coverage == 1) & (np.abs(x - y) > 0.1)                    # the footprint on one face
        assert inside.sum() > 300, inside.sum()
        np.testing.assert_allclose(gb.albedo[inside], want[inside], rtol=0, atol=1e-4, err_msg=name)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("backend", ["pyrender", "raycast"])
def test_smooth_object_normals_follow_the_surface(tmp_path, backend, device):
    """objects.smooth: a coarse sphere's (320 faces) G-buffer normals are its vertex normals interpolated over each
    face and over the pixel: against the true sphere's normal at the pixel's point 1.5 degrees off on average, where
    its faces' own normals (flat, the default) are 4.7 degrees off."""
    path = tmp_path / "coarse.obj"
    trimesh.creation.icosphere(subdivisions=2, radius=0.5).export(path)
    error = {}
    for smooth in (False, True):
        scene = load_scene([ObjectConfig(mesh=str(path), position=[0.0, 0.0, -0.3], scale=0.8, smooth=smooth)])
        gb = GBufferRenderer(scene, INTR, 2, device, backend).render(LOOK_DOWN)
        inside = gb.coverage == 1
        truth = gb.position[inside] - [0.0, 0.0, -0.3]
        truth /= np.linalg.norm(truth, axis=1, keepdims=True)
        assert np.allclose(np.linalg.norm(gb.normal[inside], axis=1), 1, atol=1e-5) and inside.sum() > 200
        error[smooth] = np.degrees(np.arccos(np.clip((gb.normal[inside] * truth).sum(1), -1, 1)))
    assert error[True].mean() < 2.5 and error[False].mean() > 2 * error[True].mean(), \
        (error[True].mean(), error[False].mean())


def test_gbuffer_viewport_holds_the_window(tmp_path):
    """A window's viewport holds its supersampled pixels, at most the supersampled frame's: with EGL rounded up to
    VIEWPORT_STEP (any size of framebuffer), with OSMesa (a context per size) to powers of two (few sizes)."""
    g = GBufferRenderer(load_scene([_cube(tmp_path)]), Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5), 2)
    for gl_windows, expected in ((False, [(1024, 960), (128, 64), (1280, 960)]),
                                 (True, [(640, 640), (128, 128), (1280, 960)])):
        g.gl_windows = gl_windows
        assert [g.viewport(w, h) for w, h in ((300, 320), (40, 20), (640, 480))] == expected


def test_gbuffer_renderers_share_one_offscreen_renderer(tmp_path):
    """Pipelines of one process share the offscreen renderer of their size (with EGL, deleting one renderer
    terminated the display of every other: EGL_NOT_INITIALIZED on an H100), and each still sees its own scene
    when they take turns."""
    import gc

    small = GBufferRenderer(load_scene([_cube(tmp_path, position=[0.0, 0.0, 2.0], scale=0.2)]), INTR, 2)
    big = GBufferRenderer(load_scene([_cube(tmp_path, position=[0.0, 0.0, 2.0], scale=0.4)]), INTR, 2)
    assert small.gl is big.gl
    areas = [small.render(np.eye(4)).coverage.sum(), big.render(np.eye(4)).coverage.sum()]
    assert np.isclose(small.render(np.eye(4)).coverage.sum(), areas[0]) and areas[1] > 3.5 * areas[0]
    window = (16, 12, 48, 36)                     # a window's viewport: with OSMesa a renderer of its own size,
    for g, area in ((small, areas[0]), (big, areas[1])):   # which both draw with, each its own scene
        assert np.isclose(g.render(np.eye(4), window=window).coverage.sum(), area)
    del small
    gc.collect()
    assert np.isclose(big.render(np.eye(4)).coverage.sum(), areas[1])
    assert np.isclose(big.render(np.eye(4), window=window).coverage.sum(), areas[1])


def test_gbuffer_draws_on_one_gl_thread_whatever_thread_asks(tmp_path, monkeypatch):
    """Every OpenGL call of the process runs on its GL thread: EGL makes a context current in one thread at a time,
    and on an H100 a G-buffer asked for from a thread other than the one that made the renderer failed with
    EGL_BAD_ACCESS (two `photoreg serve --threads` connections with objects). Threads in turn get the same G-buffer."""
    import threading

    import pyrender

    names = []
    draw = pyrender.OffscreenRenderer.render
    monkeypatch.setattr(pyrender.OffscreenRenderer, "render",
                        lambda self, *a, **k: (names.append(threading.current_thread().name), draw(self, *a, **k))[1])
    g = GBufferRenderer(load_scene([_cube(tmp_path, position=[0.0, 0.0, 2.0], scale=0.3)]), INTR, 2)
    areas = []
    for _ in range(3):
        t = threading.Thread(target=lambda: areas.append(g.render(np.eye(4)).coverage.sum()))
        t.start()
        t.join()
    areas.append(g.render(np.eye(4)).coverage.sum())
    assert len(set(names)) == 1 and names[0].startswith("photoreg-gl") and len(names) == 4
    assert len(areas) == 4 and all(np.isclose(a, areas[0]) for a in areas) and areas[0] > 50


def test_gbuffer_compiles_its_shader_once(tmp_path, monkeypatch):
    """pyrender keyed its shader programs by a context object that OSMesa makes anew at every call: every G-buffer
    compiled its shader again and kept the old program (258 MB more resident memory over 300 frames of TUM with
    the bunny). Frames after the first compile nothing, whole-frame or windowed."""
    import pyrender.shader_program

    g = GBufferRenderer(load_scene([_cube(tmp_path, position=[0.0, 0.0, 2.0], scale=0.3)]), INTR, 2)
    window = (8, 4, 56, 44)
    first = [g.render(np.eye(4)).coverage.sum(), g.render(np.eye(4), window=window).coverage.sum()]
    compiles = []
    add = pyrender.shader_program.ShaderProgram._add_to_context
    monkeypatch.setattr(pyrender.shader_program.ShaderProgram, "_add_to_context",
                        lambda self: (compiles.append(self), add(self))[1])
    for _ in range(4):
        assert np.isclose(g.render(np.eye(4)).coverage.sum(), first[0])
        assert np.isclose(g.render(np.eye(4), window=window).coverage.sum(), first[1])
    assert compiles == []


def test_virtual_visibility_never_exceeds_real(tmp_path):
    scene = load_scene([_cube(tmp_path, scale=0.2, albedo=[0.5, 0.5, 0.5])])
    virt, floor = voxel_grid(scene, 0.02, "cpu"), _floor_grid()
    dirs, Y = make_direction_set(48, 3, seed=0)
    xy = np.stack(np.meshgrid(np.linspace(-0.4, 0.4, 9), np.linspace(-0.4, 0.4, 9)), -1).reshape(-1, 2)
    pts = np.c_[xy, np.zeros(len(xy))]
    pts = pts[np.abs(xy).max(1) > 0.12]                                            # not under the cube
    tr = radiance_transfer(floor, pts, np.tile([0, 0, 1.0], (len(pts), 1)), dirs, Y, 0.03, 0.5, virtual=virt)
    assert np.all(tr.visible_fraction_rv <= tr.visible_fraction + 1e-6)
    assert tr.visible_fraction.min() > 0.99 and tr.visible_fraction_rv.min() < 0.9
    assert np.allclose(tr.transfer[:, 0], tr.transfer[0, 0])                       # open floor: same R_TR


def test_any_blocked_is_the_virtual_flags_of_the_ray_pass(tmp_path):
    """The pre-pass that spares the real march at points the objects cannot shadow finds exactly the points
    with a VIRTUAL-flagged ray in the full pass, and R_TRV = R_TR at every other point."""
    scene = load_scene([_cube(tmp_path, scale=0.2)])
    virt, floor = voxel_grid(scene, 0.02, "cpu"), _floor_grid()
    dirs, Y = make_direction_set(32, 3, seed=1)
    xy = np.stack(np.meshgrid(np.linspace(-0.6, 0.6, 13), np.linspace(-0.6, 0.6, 13)), -1).reshape(-1, 2)
    pts, up = np.c_[xy, np.zeros(len(xy))], np.tile([0, 0, 1.0], (len(xy), 1))
    tr = radiance_transfer(floor, pts, up, dirs, Y, 0.03, 0.3, virtual=virt)
    flagged = ((tr.occlusion_wp.numpy() & int(VIRTUAL)) != 0).any(axis=1)
    hit = any_blocked(virt, pts, up, dirs, 0.03, 0.3)
    assert np.array_equal(hit, flagged) and 0 < hit.sum() < len(hit)
    assert np.array_equal(tr.transfer_rv[~hit], tr.transfer[~hit])
    east = xy[:, 0] > 0.15                                              # facing away from the cube: no hit
    assert not any_blocked(virt, pts[east], np.tile([1.0, 0, 0], (east.sum(), 1)), dirs, 0.03, 0.3).any()


def test_shaded_pass_is_the_lighting_times_the_transfer(tmp_path):
    """shaded_pass's one thread per point gives F.R_TR, F.R_TRV and their blocked shares of radiance_transfer's SH
    projections (with a second ray set, a light's disc, that adds its own pass's shading, weighted 1 / its count,
    and no blocked share)."""
    scene = load_scene([_cube(tmp_path, scale=0.2)])
    virt, floor = voxel_grid(scene, 0.02, "cpu"), _floor_grid()
    dirs, Y = make_direction_set(32, 3, seed=1)
    cone = make_direction_set(8, 1, seed=5)[0]
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.5, 0.5, (200, 2))
    pts = np.c_[xy, np.zeros(len(xy))]
    normals = np.c_[rng.normal(0, 0.3, (len(xy), 2)), np.ones(len(xy))]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    F, colour = rng.uniform(-0.3, 1.0, (3, 9)), np.array([2.0, 1.5, 1.0])
    table = np.c_[Y @ F.T, np.ones(len(dirs))] * 4 / len(dirs)
    disc = np.c_[np.tile(colour / (np.pi * len(cone)), (len(cone), 1)), np.zeros(len(cone))]
    out = shaded_pass(floor, virt, pts, normals, np.concatenate([dirs, cone]), np.concatenate([table, disc]), 0.03,
                      0.3)
    tr = radiance_transfer(floor, pts, normals, dirs, Y, 0.03, 0.3, virtual=virt)
    ct = radiance_transfer(floor, pts, normals, cone, np.ones((len(cone), 1), np.float32), 0.03, 0.3, virtual=virt)
    np.testing.assert_allclose(out[:, :3], tr.transfer @ F.T + ct.transfer * colour / (4 * np.pi), atol=2e-6)
    np.testing.assert_allclose(out[:, 3:6], tr.transfer_rv @ F.T + ct.transfer_rv * colour / (4 * np.pi), atol=2e-6)
    np.testing.assert_allclose(out[:, 6], sh.blocked_share(tr.transfer)[:, 0], atol=1e-6)
    np.testing.assert_allclose(out[:, 7], sh.blocked_share(tr.transfer_rv)[:, 0], atol=1e-6)
    shadowed = np.abs(out[:, 3:6] - out[:, :3]).max(axis=1) > 1e-3
    assert 10 < shadowed.sum() < len(pts) and (out[:, 7] >= out[:, 6] - 1e-6).all()
    for bad, why in ((table[:, :3], r"must be \(\.\.\., 4\)"), (table[:-1], "rows for"),
                     (np.full_like(table, np.nan), "non-finite")):
        with pytest.raises(ValueError, match="weighted radiance.*" + why):
            shaded_pass(floor, virt, pts, normals, dirs, bad, 0.03, 0.3)


def _render_floor(tmp_path, shadows: str, stride: int = 2, surface: bool = False, window: bool = False,
                  obj: ObjectConfig | None = None):
    """A cube (or `obj`) on the real floor seen from above, lit from above: (camera, composite, layers, gbuffer); with
    `surface` the full-resolution real surface goes in too (composite.refine_seam); with `window` the G-buffer is
    drawn in the cube's box widened by stride + 1 pixels (as RenderStage.window), else in the whole frame."""
    scene = load_scene([obj or _cube(tmp_path, scale=0.2, albedo=[0.5, 0.5, 0.5])])
    floor, virt = _floor_grid(), voxel_grid(scene, 0.02, "cpu")
    maps = raycast_surface(floor, INTR, LOOK_DOWN, 0.1, 3.0, stride=stride)
    full = raycast_surface(floor, INTR, LOOK_DOWN, 0.1, 3.0)
    g = GBufferRenderer(scene, INTR, 2)
    gb = g.render(LOOK_DOWN, full.depth)
    if window:
        rows, cols = np.nonzero(gb.coverage > 0)
        m = stride + 1
        gb = g.render(LOOK_DOWN, full.depth, window=(max(cols.min() - m, 0), max(rows.min() - m, 0),
                                                     min(cols.max() + m + 1, 64), min(rows.max() + m + 1, 48)))
    up = sh.sh_basis(np.array([[0, 0, 1.0]]), 3)[0]
    F = np.outer([1.0, 0.9, 0.8], 2.0 * up) + np.outer([0.2, 0.2, 0.2], np.eye(9)[0])  # sky lobe overhead
    camera = np.ones((48, 64, 1), np.float32) * (0.5 * shade(F, sh.unoccluded_transfer(np.array([[0, 0, 1.0]]), 3)))
    camera = camera.astype(np.float32)                                # a floor of albedo 0.5 under F
    inp = RenderInput(camera, F, 1.0, floor, virt, maps, gb, scene.bounds,
                      lambda b: make_direction_set(32, b, seed=0), 0.03, 0.3, scene=scene,
                      surface=full if surface else None)
    layers = get_renderer(shadows)(inp)
    return camera, composite(camera, layers), layers, gb


def test_shadow_darkens_floor_and_far_pixels_unchanged(tmp_path):
    camera, out, layers, gb = _render_floor(tmp_path, "voxel")
    assert np.all(np.isfinite(out)) and np.all(np.isfinite(layers.ratio))
    real = gb.coverage == 0
    ring = cv2.dilate((gb.coverage > 0).astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & real
    assert out[ring].mean() < 0.985 * camera[ring].mean()         # the floor beside the cube loses sky light
    far = np.zeros_like(real)
    far[:, :4] = far[:, -4:] = True                               # > ray_length from the cube
    assert np.array_equal(out[far], camera[far])
    assert np.all(out[real] <= camera[real] + 1e-6)              # the object only takes light away
    top = gb.coverage == 1
    assert out[top].min() > 0                                       # lit top face


def test_voxel_marches_the_real_grid_only_where_the_objects_block_a_ray(tmp_path, monkeypatch):
    """render_voxel's shadow ratio with the virtual pre-pass (any_blocked) equals the full pass at every point,
    and the real grid is marched at fewer points than the near ones."""
    import photoreg.render.voxel as voxel

    marched = []
    real_pass = voxel.shaded_pass
    monkeypatch.setattr(voxel, "shaded_pass", lambda g, v, p, *a, **k: marched.append(len(p)) or
                        real_pass(g, v, p, *a, **k))
    _, fast_out, fast, _ = _render_floor(tmp_path, "voxel", surface=True)
    fast_marched = list(marched)
    monkeypatch.setattr(voxel, "any_blocked", lambda g, p, *a, **k: np.ones(len(p), bool))
    marched.clear()
    _, full_out, full, _ = _render_floor(tmp_path, "voxel", surface=True)
    assert np.array_equal(fast.ratio, full.ratio) and np.array_equal(fast_out, full_out)
    assert (full.ratio < 1).any()
    assert sum(fast_marched) < sum(marched) - 50                # calls: the object, the near samples, the seam


@pytest.mark.parametrize("shadows", ["voxel", "shadowmap"])
def test_no_seam_where_the_object_hides_stride_samples(tmp_path, shadows):
    """Stride samples under the cube are fully shadowed; interpolated into the floor pixels beside it they drew
    a dark seam along its silhouette. With the full-resolution surface those pixels get the ratio a stride-1
    run gives them (composite.refine_seam); without it, they are darker."""
    _, _, exact, gb = _render_floor(tmp_path, shadows, stride=1)
    _, _, seam, _ = _render_floor(tmp_path, shadows, stride=4)
    _, _, fixed, _ = _render_floor(tmp_path, shadows, stride=4, surface=True)
    ring = (cv2.dilate((gb.coverage > 0).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            & (gb.coverage == 0))
    assert ring.sum() > 20
    assert np.allclose(fixed.ratio[ring], exact.ratio[ring], atol=1e-3)
    assert seam.ratio[ring].mean() < exact.ratio[ring].mean() - 0.05
    changed = (fixed.ratio != seam.ratio).any(axis=-1)                # within a stride of the silhouette only
    assert not (changed & ~cv2.dilate((gb.coverage > 0).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)).any()
    real = changed & (gb.coverage == 0)
    assert np.allclose(fixed.ratio[real], exact.ratio[real], atol=1e-3)


def _check_window_gbuffer(stage, real, window) -> None:
    """The G-buffer of a window equals the whole frame's there (rasterised alone, with EGL, a subsample on an
    exact edge may flip)."""
    for depth in (None, real):
        a, b = stage.gbuffer.render(LOOK_DOWN, depth), stage.gbuffer.render(LOOK_DOWN, depth, window=window)
        d = np.abs(a.coverage - b.coverage)
        assert d.max() <= 0.25 and (d > 0).sum() <= 4, (d.max(), (d > 0).sum())
        same = (d == 0) & (a.coverage > 0)
        assert same.sum() > 0.9 * (a.coverage > 0).sum()
        for name in ("depth", "position", "normal", "albedo"):
            assert np.allclose(getattr(a, name)[same], getattr(b, name)[same], atol=1e-3), name
            full, kept = getattr(b, name), getattr(b, "window_" + name)   # the full view: the window's, zero outside
            outside = full.copy()
            outside[b.box] = 0
            assert np.array_equal(full[b.box], kept) and not outside.any(), name
            assert full.shape[:2] == b.coverage.shape and not full[b.coverage == 0].any(), name


def test_render_window_holds_the_object_and_its_seam(tmp_path):
    """The render stage ray casts the real surface only in a window round the objects' projection: it holds
    every pixel the cube covers plus one lighting stride and a pixel around them, is much smaller than the
    frame here, and is the whole frame when the objects reach behind the camera."""
    from photoreg.config import Session
    from photoreg.render.stage import RenderStage

    s = Session()
    s.objects = [_cube(tmp_path, scale=0.2)]
    s.lighting.stride = 4
    stage = RenderStage(s, INTR, "cpu")
    x0, y0, x1, y1 = stage.window(LOOK_DOWN)
    full = stage.gbuffer.render(LOOK_DOWN)
    v, u = np.nonzero(full.coverage > 0)
    assert x0 <= u.min() - 5 and u.max() + 5 < x1 and y0 <= v.min() - 5 and v.max() + 5 < y1
    assert (x1 - x0) * (y1 - y0) < 0.5 * INTR.width * INTR.height
    real = np.full((INTR.height, INTR.width), 0.9, np.float32)       # a real surface cutting the cube at z = 0.1
    _check_window_gbuffer(stage, real, (x0, y0, x1, y1))
    with pytest.raises(ValueError, match="window"):
        stage.gbuffer.render(LOOK_DOWN, window=(0, 0, INTR.width + 1, 4))
    s.render.gbuffer = "raycast"                                          # the session's G-buffer traced
    traced = RenderStage(s, INTR, "cpu")
    assert traced.gbuffer.backend == "raycast"
    _check_window_gbuffer(traced, real, (x0, y0, x1, y1))
    _gbuffers_agree(stage.gbuffer.render(LOOK_DOWN, real), traced.gbuffer.render(LOOK_DOWN, real), pixels=2)
    inside = LOOK_DOWN.copy()
    inside[2, 3] = 0.1                                                    # the camera within the cube's height
    assert stage.window(inside) == (0, 0, INTR.width, INTR.height)


def test_camera_inside_an_object_is_said(tmp_path):
    """An object placed round the camera (a scale or position mistake) is drawn from within: the frame's notes say
    which object; a camera in an object's box but outside its surface (a torus's hole) is not flagged; an open mesh
    (a box without its lid, as a teapot's rim) and overlapping parts hold what they enclose."""
    from photoreg.config import Session
    from photoreg.render.stage import RenderStage

    torus, lidless, two = tmp_path / "torus.obj", tmp_path / "lidless.obj", tmp_path / "two.obj"
    trimesh.creation.torus(major_radius=0.5, minor_radius=0.1).export(torus)
    box = trimesh.creation.box(extents=(1, 1, 1))
    box.update_faces(box.face_normals[:, 2] < 0.5)                 # the top's two triangles gone
    box.export(lidless)
    trimesh.util.concatenate([trimesh.creation.icosphere(radius=0.5),
                              trimesh.creation.icosphere(radius=0.5).apply_translation([0.4, 0, 0])]).export(two)
    scene = load_scene([_cube(tmp_path, scale=0.2), ObjectConfig(mesh=str(torus), position=[2.0, 0, 0]),
                        ObjectConfig(mesh=str(lidless), position=[0, 3.0, 0]), ObjectConfig(mesh=str(two),
                                                                                         position=[0, -3.0, 0])])
    assert scene.containing([0.0, 0.05, 0.02]) == [0]
    assert scene.containing([2.0, 0.0, 0.0]) == [] and scene.containing([2.5, 0.0, 0.0]) == [1]
    assert scene.containing([0.0, 0.0, 1.0]) == []
    assert scene.containing([0.0, 3.0, 0.0]) == [2] and scene.containing([0.2, -3.0, 0.0]) == [3]
    s = Session()
    s.objects = [_cube(tmp_path, scale=3.0)]
    s.lighting.stride, s.lighting.rays = 4, 16
    stage = RenderStage(s, INTR, "cpu")
    floor = _floor_grid()
    camera = np.full((INTR.height, INTR.width, 3), 0.5, np.float32)
    F = np.outer([1.0, 1.0, 1.0], np.eye(9)[0])
    stage(camera, np.ones((INTR.height, INTR.width), np.float32), floor, None, LOOK_DOWN, F)
    assert any("camera is inside object 0" in n for n in stage.last.notes)
    s.objects = [_cube(tmp_path, scale=0.2)]
    stage = RenderStage(s, INTR, "cpu")
    stage(camera, np.ones((INTR.height, INTR.width), np.float32), floor, None, LOOK_DOWN, F)
    assert not any("inside" in n for n in stage.last.notes)


def test_upsampled_ratio_in_a_window_is_the_full_frames_there():
    """upsample_ratio over a window (the seam band reads only the real surface's window) gives the full frame's
    values there, bit for bit, and 1 where the samples' box does not reach; a window off the box is all 1."""
    rng = np.random.default_rng(3)
    ratio_s = rng.uniform(0.2, 1.0, (30, 40, 2)).astype(np.float32)
    near = np.zeros((30, 40), bool)
    near[10:18, 12:25] = True
    full = upsample_ratio(ratio_s, near, 4, (120, 160))
    for x0, y0, x1, y1 in ((30, 20, 90, 100), (0, 0, 160, 120), (50, 60, 51, 61), (100, 35, 160, 90)):
        part = upsample_ratio(ratio_s, near, 4, (120, 160), window=(x0, y0, x1, y1))
        assert part.shape == (y1 - y0, x1 - x0, 2) and np.array_equal(part, full[y0:y1, x0:x1])
    assert (full[:, :40] == 1).all() and (full[40:72, 52:96] < 1).any()
    assert (upsample_ratio(ratio_s, near, 4, (120, 160), window=(0, 0, 30, 20)) == 1).all()


def test_stride_box_and_box_distance_against_their_definitions():
    """stride_box: the pixel box of every near sample's bilinear taps, from the near samples' extreme rows and
    columns, clipped to the frame (None without one); box_distance2: the squared distance of each map vertex to
    the objects' box, 0 inside, on maps of any shape (one row or column too)."""
    from types import SimpleNamespace

    from photoreg.render.composite import box_distance2, stride_box

    rng = np.random.default_rng(8)
    assert stride_box(np.zeros((5, 7), bool), 4, (20, 28)) is None
    for shape in ((1, 1), (1, 6), (6, 1), (30, 40)):
        near = rng.random(shape) < 0.2
        near.flat[rng.integers(near.size)] = True
        rows, cols = np.nonzero(near)
        expected = (max((cols.min() - 1) * 4, 0), max((rows.min() - 1) * 4, 0),
                    min((cols.max() + 1) * 4 + 1, shape[1] * 4), min((rows.max() + 1) * 4 + 1, shape[0] * 4))
        assert stride_box(near, 4, (shape[0] * 4, shape[1] * 4)) == expected
        vertex = rng.uniform(-1.0, 1.0, (*shape, 3)).astype(np.float32)
        bounds = np.array([[-0.2, -0.1, 0.0], [0.3, 0.2, 0.4]])
        nearest = np.clip(vertex, bounds[0], bounds[1])
        np.testing.assert_allclose(box_distance2(SimpleNamespace(vertex=vertex), bounds),
                                   ((vertex - nearest) ** 2).sum(axis=-1), rtol=1e-6, atol=1e-7)
    inside = SimpleNamespace(vertex=np.array([[[0.0, 0.0, 0.2]]], np.float32))
    assert box_distance2(inside, np.array([[-0.2, -0.1, 0.0], [0.3, 0.2, 0.4]]))[0, 0] == 0.0


@pytest.mark.parametrize("shadows", ["voxel", "none"])
def test_composite_blends_only_the_layers_region(tmp_path, shadows):
    """The render stage's layers say which box they change (Layers.region: the G-buffer's window and the reach of
    the shadow samples); outside it alpha is 0 and the ratio 1, and the composite, blended inside it alone, is
    the full-frame blend (1 - alpha) cam ratio + alpha colour bit for bit, the camera frame elsewhere."""
    from photoreg.config import Session
    from photoreg.render.stage import RenderStage

    s = Session()
    s.objects = [_cube(tmp_path, scale=0.12, position=[-0.2, 0.1, 0.0], albedo=[0.6, 0.5, 0.4])]
    s.lighting.stride, s.lighting.rays, s.lighting.ray_length = 2, 16, 0.3
    s.render.shadows = shadows
    stage = RenderStage(s, INTR, "cpu")
    floor = _floor_grid()
    maps = raycast_surface(floor, INTR, LOOK_DOWN, 0.1, 3.0, stride=2)
    low = np.array([[-0.8, 0.0, 0.6]])                              # a low light: the shadow reaches past the window
    F = np.outer([1.0, 0.9, 0.8], 2.0 * sh.sh_basis(low, 3)[0]) + np.outer([0.3, 0.3, 0.3], np.eye(9)[0])
    camera = np.random.default_rng(0).uniform(0.2, 0.8, (INTR.height, INTR.width, 3)).astype(np.float32)
    out = stage(camera, np.ones((INTR.height, INTR.width), np.float32), floor, maps, LOOK_DOWN, F)
    layers = stage.last
    x0, y0, x1, y1 = layers.region
    assert (x1 - x0) * (y1 - y0) < 0.6 * INTR.width * INTR.height
    inside = np.zeros((INTR.height, INTR.width), bool)
    inside[y0:y1, x0:x1] = True
    assert (layers.alpha[~inside] == 0).all() and (layers.ratio[~inside] == 1).all()
    assert (layers.alpha[inside] > 0).any()
    if shadows == "voxel":
        wx0, wy0, wx1, wy1 = stage.last_input.gbuffer.window
        beyond = inside.copy()
        beyond[wy0:wy1, wx0:wx1] = False
        assert (layers.ratio[beyond] < 1).any()
    a = layers.alpha[..., None]
    assert np.array_equal(out, (1.0 - a) * camera * layers.ratio + a * layers.colour)


def test_render_window_with_egl(tmp_path):
    """With EGL the G-buffer rasterises the window alone (its own viewport and principal point): the same
    G-buffer, in a process whose pyrender runs on EGL (Mesa's here, NVIDIA's on a GPU machine); and the draw's
    framebuffer is single-sample there too, so the faces' codes are not blended along their shared edges: EGL's
    G-buffer is the rays' (pyrender's 4x MSAA dropped the cube's top face and a quarter of TUM's bunny)."""
    import os
    import subprocess
    import sys

    code = (f"import sys, numpy as np; sys.path[:0] = [{str(REPO)!r}]; from tests import test_render as t; "
            "from pathlib import Path; from photoreg.config import Session; "
            "from photoreg.render.stage import RenderStage; "
            f"s = Session(); s.objects = [t._cube(Path({str(tmp_path)!r}), scale=0.2)]; s.lighting.stride = 4; "
            "st = RenderStage(s, t.INTR, 'cpu'); assert st.gbuffer.gl_windows; "
            "t._check_window_gbuffer(st, np.full((t.INTR.height, t.INTR.width), 0.9, np.float32), "
            f"st.window(t.LOOK_DOWN)); t.test_raycast_gbuffer_is_the_draws(Path({str(tmp_path)!r}), 'cpu'); "
            "print('ok')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       env={**os.environ, "PYOPENGL_PLATFORM": "egl"}, cwd=REPO)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-2000:]


def test_objects_out_of_every_view_are_warned_of(tmp_path, capsys):
    """An object placed where no frame sees it (here behind the demo's cameras; a tracked run's first-camera world
    taken for the recording's does it too): the run says so at its end, and summary.json counts no frame with an
    object in view."""
    import json

    from photoreg.cli import main

    demo = REPO / "data" / "demo"
    session = tmp_path / "s.toml"
    session.write_text((demo / "session.toml").read_text().replace('path = "."', f'path = "{demo.as_posix()}"')
                       .replace('mesh = "object.obj"', f'mesh = "{(demo / "object.obj").as_posix()}"')
                       .replace("position = [0.0, 0.0, 0.0]", "position = [0.0, 0.0, -40.0]"))
    assert main(["run", str(session), "--out", str(tmp_path / "o"), "--frames", "0:2", "--rays", "16", "--stride",
                 "8", "--quiet"]) == 0
    assert "warning: no composite shows an object: check the objects' positions" in capsys.readouterr().err
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["composites"] == 2 and summary["objects_in_view"] == 0


def test_textured_object_composites_its_texture(tmp_path):
    """A textured cube on the floor (its top face's texture coordinates its x and y): the composite of its top face,
    lit alike everywhere, is the texture's albedo times one shading, whatever the texel."""
    from PIL import Image

    box = trimesh.creation.box(extents=(1, 1, 1))
    texture = np.kron(np.random.default_rng(5).integers(30, 256, (4, 4, 3)), np.ones((4, 4, 1))).astype(np.uint8)
    box.visual = trimesh.visual.TextureVisuals(uv=box.vertices[:, :2] + 0.5, image=Image.fromarray(texture))
    box.export(tmp_path / "box.obj")
    obj = ObjectConfig(mesh=str(tmp_path / "box.obj"), position=[0.0, 0.0, 0.1], scale=0.2, albedo="texture")
    camera, out, layers, gb = _render_floor(tmp_path, "voxel", obj=obj)
    top = cv2.erode((gb.coverage == 1).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert top.sum() > 30 and np.ptp(gb.albedo[top], axis=0).min() > 0.2   # several texels of other colours
    shading = out[top] / gb.albedo[top]
    assert np.all(np.isfinite(out)) and np.ptp(shading, axis=0).max() < 0.02 * shading.mean(), np.ptp(shading, 0)


def test_an_obj_s_texture_16_bit_grey_or_missing(tmp_path):
    """A 16-bit grey texture (0x4000) gives its albedo (8-bit 64: linear 0.0513; was read as white, PIL's convert
    clipping it at 255); a texture image or material library the OBJ names but lacks is an error naming it (was the
    flat Kd colour, without a word)."""
    from PIL import Image

    from photoreg.io.images import srgb_to_linear
    from photoreg.render.scene import load_object

    box = trimesh.creation.box(extents=(1, 1, 1))
    box.visual = trimesh.visual.TextureVisuals(uv=box.vertices[:, :2] + 0.5,
                                               image=Image.fromarray(np.full((4, 4, 3), 200, np.uint8)))
    box.export(tmp_path / "box.obj")
    (image,) = tmp_path.glob("*.png")
    cv2.imwrite(str(image), np.full((4, 4), 0x4000, np.uint16))
    obj = ObjectConfig(mesh=str(tmp_path / "box.obj"), albedo="texture")
    np.testing.assert_allclose(load_object(obj).textures[0], srgb_to_linear(np.full((4, 4, 3), 64, np.uint8)))
    (mtl,) = tmp_path.glob("*.mtl")
    # the names read as trimesh reads them: the rest of the line (spaces kept), map_kd in any case, from the OBJ's
    # folder (a library in a folder of its own names its images from the OBJ's)
    spaced = image.with_name("my texture.png")
    image.rename(spaced)
    mtl.write_text(mtl.read_text().replace(f"map_Kd {image.name}", f"map_kd {spaced.name}"))
    np.testing.assert_allclose(load_object(obj).textures[0], srgb_to_linear(np.full((4, 4, 3), 64, np.uint8)))
    (tmp_path / "materials").mkdir()
    mtl.rename(tmp_path / "materials" / mtl.name)
    (tmp_path / "box.obj").write_text((tmp_path / "box.obj").read_text().replace(
        f"mtllib {mtl.name}", f"mtllib materials/{mtl.name}"))
    np.testing.assert_allclose(load_object(obj).textures[0], srgb_to_linear(np.full((4, 4, 3), 64, np.uint8)))
    spaced.unlink()
    with pytest.raises(FileNotFoundError, match=re.escape("its texture image (map_Kd) 'my texture.png' is missing")):
        load_object(obj)
    (tmp_path / "materials" / mtl.name).unlink()
    with pytest.raises(FileNotFoundError, match=re.escape(f"its material library 'materials/{mtl.name}' is missing")):
        load_object(obj)
    load_object(ObjectConfig(mesh=str(tmp_path / "box.obj")))   # one albedo: no texture needed


def test_none_renderer_leaves_real_pixels(tmp_path):
    camera, out, layers, gb = _render_floor(tmp_path, "none")
    real = gb.coverage == 0
    assert np.array_equal(out[real], camera[real]) and np.all(np.isfinite(out))


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """The demo session over frames 0-20 (insert frames 10 and 20 composited; every frame, as a run would),
    with the video of its composites."""
    from photoreg.config import load_session
    from photoreg.runner import run_session

    out = tmp_path_factory.mktemp("demo_run")
    s = load_session(REPO / "data" / "demo" / "session.toml")
    s.output.dir, s.frames, s.output.pictures_every, s.output.video = str(out), "0:21", 0, True
    run_session(s, quiet=True)
    return out


def test_demo_video_holds_every_composite(demo_run):
    """composite.mp4 has one frame per composite, at the recording's 30 frames/s, and its frame 20 is
    composite/000020.png up to the codec's loss."""
    import json

    summary = json.loads((demo_run / "summary.json").read_text())
    assert summary["video"] == {"file": "composite.mp4", "frames": 21, "fps": 30.0}
    assert summary["composites"] == summary["objects_in_view"] == 21
    cap = cv2.VideoCapture(str(demo_run / "composite.mp4"))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    assert len(frames) == 21 and cap.get(cv2.CAP_PROP_FPS) == pytest.approx(30.0)
    png = cv2.imread(str(demo_run / "composite" / "000020.png"))
    assert frames[20].shape == png.shape and np.abs(frames[20].astype(int) - png).mean() < 4
    assert not list(demo_run.glob("*.partial*"))


def test_demo_object_brightness_matches_path_tracer(demo_run):
    """F in absolute units (lighting.reference_albedo) plus the floor's bounce light the object as the path
    tracer does: its mean luminance within 10% (what this test guards: 20% too dark with F relative to
    albedo 1 and no bounce; 15-21% too bright per channel with the sun but no bounce term, which takes the
    floor's light on sun-facing faces for sunlight; 8-19% with albedo_step "joint") and every channel within
    20%. The colour balance is weaker: it rests on the max-RGB rule (the brightest region in each channel has
    reference_albedo), which on this scene by itself puts blue 6.7% low (the white box is 0.75 in blue, not
    0.8), and on the region albedos (frame 0: the floor comes out (1.07, 1.16, 1.34) x its true albedo, F's
    upward irradiance (1.10, 1.03, 0.87) x the true colour). Per channel it was 2-8% off before the floor's
    plane was split off its region (albedo.split_off_plane), because the box-in-floor region made the traced
    light too blue (frame 20: 3.02 against the true 2.31 in blue) and restarted the filter at frame 10; now
    0.98 / 0.94 / 0.85 at frame 10 and 1.04 / 1.03 / 0.94 at frame 20 (luminance 0.94 / 1.03), while the
    object's squared error against the path tracer fell on every insert frame (benchmarks/lighting_accuracy.md)."""
    from photoreg.io.images import read_exr
    from photoreg.lighting.sh import LUMINANCE

    assert (demo_run / "lightmap" / "000010.exr").is_file() and (demo_run / "composite" / "000020.png").is_file()
    for f in ("000010", "000020"):
        gt = read_exr(REPO / "data" / "demo" / "insert" / f"{f}.exr")
        est = read_exr(demo_run / "composite_linear" / f"{f}.exr")
        mask = cv2.imread(str(REPO / "data" / "demo" / "insert_mask" / f"{f}.png"), cv2.IMREAD_GRAYSCALE) > 0
        ratio = est[mask].mean(axis=0) / gt[mask].mean(axis=0)
        lum = float((est[mask] @ LUMINANCE).mean() / (gt[mask] @ LUMINANCE).mean())
        assert abs(lum - 1.0) < 0.10 and np.all(np.abs(ratio - 1.0) < 0.20), (f, lum, ratio)


def test_demo_no_dark_seam_around_the_object(demo_run):
    """The real pixels just outside the object (its mask dilated by one pixel) as bright as the path tracer's,
    within 5% in luminance: at frame 20 they were 8.6% too dark (0.914) while the lighting stride's samples
    hidden under the object were interpolated into them (composite.refine_seam: 0.975 at frame 20, 1.027 at 10)."""
    from photoreg.io.images import read_exr
    from photoreg.lighting.sh import LUMINANCE

    for f in ("000010", "000020"):
        gt = read_exr(REPO / "data" / "demo" / "insert" / f"{f}.exr")
        est = read_exr(demo_run / "composite_linear" / f"{f}.exr")
        mask = cv2.imread(str(REPO / "data" / "demo" / "insert_mask" / f"{f}.png"), cv2.IMREAD_GRAYSCALE) > 0
        ring = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~mask
        lum = float((est[ring] @ LUMINANCE).mean() / (gt[ring] @ LUMINANCE).mean())
        assert abs(lum - 1.0) < 0.05, (f, lum)


def test_demo_lighting_against_the_path_tracer(demo_run):
    """The run's lighting (frames 0-20) against the generator's environment (Mitsuba, an independent
    renderer): median irradiance si-RMSE over the upper hemisphere 0.069 with the samples of earlier views
    in the solve (lighting.history; 0.072 before the filter's new_view_share), 0.081 without; 0.109 without
    the normal bins counted per albedo region (lighting.region_weights: in one histogram the white box's top
    shares the floor's bin and weighs nothing). benchmarks/lighting_accuracy.py, ablations "no history" and
    "no region weights"."""
    from photoreg.bench.score import score

    m = score(demo_run, REPO / "data" / "demo")["lighting"]["metrics"]
    assert m["irradiance_si_rmse_upper"]["median"] < 0.077
    assert m["direction_deg"]["median"] < 15.0


@pytest.mark.xfail(reason="issue 5 open: the baseline pastes the path tracer's own object, its noise included; "
                          "frame 10 beats it (0.045 vs 0.078) but frame 20 does not (0.036 vs 0.020; with the "
                          "generator's true light 0.029, the object path-traced with other seeds 0.028)",
                   strict=False)
def test_demo_composite_beats_no_shadow_baseline(demo_run):
    from photoreg.bench.score import score_composites

    rows = [r for r in score_composites(demo_run, REPO / "data" / "demo")["per_frame"] if "si_rmse" in r]
    assert rows and all(r["si_rmse"] < r["baseline_si_rmse"] for r in rows)


@pytest.mark.data
@pytest.mark.parametrize("name", ["tum_fr1_rpy", "iclnuim_livingroom1"])
def test_real_recording_sessions_insert_the_object(name, data_dir, tmp_path, monkeypatch):
    """sessions/ has one session per shared real recording: it loads (paths through PHOTOREG_DATA) and a
    short run (few rays) writes composites where the object is in view and changes the frame."""
    from photoreg.config import load_session
    from photoreg.io.images import read_exr
    from photoreg.runner import run_session

    monkeypatch.setenv("PHOTOREG_DATA", str(data_dir))
    s = load_session(REPO / "sessions" / f"{name}.toml")
    s.output.dir, s.frames, s.output.pictures_every = str(tmp_path), "0:2", 0
    s.lighting.rays, s.lighting.stride = 16, 8
    run_session(s, quiet=True)
    ratio = read_exr(tmp_path / "lightmap" / "000001.exr")
    comp = cv2.imread(str(tmp_path / "composite" / "000001.png"))
    assert comp is not None and np.isfinite(ratio).all() and ratio.min() < 0.99   # a shadow or occlusion term


def test_voxel_traces_the_dominant_light_as_a_disc(tmp_path):
    """Under a sun plus a dim sky, 5 SH bands smear the sun over tens of degrees: the SH-only transfer
    (light_rays 0, the paper) leaves a weak shadow; tracing the fitted disc (light_rays 16) reaches the
    umbra, about 1 - opacity, beside the cube (lit from 30 deg off zenith toward +x)."""
    from photoreg.lighting.parametric import lobe_sh, parametric_light

    sun = np.array([math.sin(math.radians(30)), 0.0, math.cos(math.radians(30))])
    F = lobe_sh(np.array([8.0, 8.0, 8.0]), sun, math.radians(2.0), 5)
    F[:, 0] += 0.3 * math.sqrt(4 * math.pi)
    scene = load_scene([_cube(tmp_path, scale=0.2, position=[0.0, 0.0, 0.1], albedo=[0.5, 0.5, 0.5])])
    floor, virt = _floor_grid(), voxel_grid(scene, 0.02, "cpu")
    maps = raycast_surface(floor, INTR, LOOK_DOWN, 0.1, 3.0, stride=1)
    gb = GBufferRenderer(scene, INTR, 2).render(LOOK_DOWN, maps.depth)
    camera = np.full((48, 64, 3), 0.4, np.float32)
    mins = {}
    for rays in (0, 16):
        inp = RenderInput(camera, F, 1.0, floor, virt, maps, gb, scene.bounds,
                          lambda b: make_direction_set(32, b, seed=0), 0.03, 0.5, light_rays=rays)
        layers = get_renderer("voxel")(inp)
        assert np.all(np.isfinite(layers.ratio)) and np.all(np.isfinite(layers.colour))
        mins[rays] = float(layers.ratio[gb.coverage == 0].min())
    opacity = float(parametric_light(F, sun).opacity.mean())
    umbra = 1.0 - opacity                                          # 0.105 for this light
    assert abs(mins[16] - umbra) < 0.06 and mins[0] - umbra > 0.15, (mins, umbra)   # measured 0.154 / 0.318


def test_frames_holding_one_estimate_share_its_light():
    """RenderInput.light is fitted once per estimate: frames that hold the same F (and traced light) get the same
    ParametricLight, equal to a fit of their own; another F or another traced light gets its own."""
    from photoreg.lighting.parametric import parametric_light, traced_light

    F = np.zeros((3, 9))
    F[:, 0], F[:, 3] = [2.0, 1.8, 1.5], [0.9, 0.8, 0.7]   # ambient plus a lobe along +x (band 1: y, z, x)

    def light(F, sun=None):
        return RenderInput(None, F, 1.0, *([None] * 8), sun=sun).light

    held = light(F.copy())
    assert light(F.copy()) is held
    fresh = parametric_light(F, sh.dominant_direction(F))
    np.testing.assert_array_equal(held.residual, fresh.residual)
    assert held.direction @ fresh.direction == pytest.approx(1.0) and held.lobe_share > 0
    other = F.copy()
    other[:, 3] *= 0.5
    assert light(other) is not held and (light(other).colour < held.colour).all()
    sun = {"direction": [1.0, 0.0, 0.0], "irradiance": [0.5, 0.4, 0.3], "angle": 0.05}
    traced = light(F.copy(), sun)
    assert traced is not held and traced is light(F.copy(), dict(sun))
    np.testing.assert_array_equal(traced.residual, traced_light(F, np.array(sun["direction"]),
                                                                np.array(sun["irradiance"]), 0.05).residual)


@pytest.mark.parametrize("shadows", ["voxel", "shadowmap", "neural_soft", "neural_shadowmap"])
def test_region_holds_the_shadow_not_every_near_sample(tmp_path, shadows):
    """A renderer's region (what composite blends) is the box of what it changes: the object's window and the pixels
    interpolated from the samples it darkens (ratio below 1; composite.changed_box), not every sample within reach of
    the objects (the rest keep a ratio of exactly 1)."""
    camera, out, layers, gb = _render_floor(tmp_path, shadows, window=True)
    x0, y0, x1, y1 = layers.region
    changed = (layers.ratio < 1.0).any(axis=2) | (layers.alpha > 0)
    rows, cols = np.nonzero(changed)
    stride = 2
    assert x0 <= cols.min() and cols.max() < x1 and y0 <= rows.min() and rows.max() < y1
    assert x0 >= cols.min() - 2 * stride and x1 <= cols.max() + 2 * stride + 2          # the interpolation's reach
    assert y0 >= rows.min() - 2 * stride and y1 <= rows.max() + 2 * stride + 2
    outside = np.ones(changed.shape, bool)
    outside[y0:y1, x0:x1] = False
    assert np.array_equal(out[outside], camera[outside]) and np.all(layers.ratio[outside] == 1.0)
