"""Procedural scene kinds for the generator: diffuse objects on a floor at z = 0 (world z up, metres).

Every object's local frame has its base on z = 0, centred in x and y; `transform` (4x4, object to
world) places it. Sizes: plane (sx, sy), box (sx, sy, sz), sphere (r,), cylinder (r, h), mesh (extent,)
with a mesh file scaled so its largest side is `extent`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

SCENE_KINDS = ("tabletop", "corner", "plane", "split_albedo", "coloured")


def placement(position, yaw_deg: float = 0.0, rotation_xyz_deg=None) -> np.ndarray:
    """4x4 object-to-world: rotation (scipy 'xyz' Euler degrees, or a yaw about z) then translation."""
    angles = rotation_xyz_deg if rotation_xyz_deg is not None else (0.0, 0.0, yaw_deg)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
    T[:3, 3] = position
    return T


INSERT_TEXTURE_BLOCKS = 8   # the textured insert's texture: 8 x 8 blocks of 8 x 8 texels, one colour each


def insert_texture() -> np.ndarray:
    """The textured insert's base colour (`photoreg synth --insert-texture`): (64, 64, 3) uint8 sRGB, blocks of
    colours from a fixed seed (8-bit levels 40-230: linear albedo 0.02-0.79)."""
    blocks = np.random.default_rng(7).integers(40, 231, (INSERT_TEXTURE_BLOCKS, INSERT_TEXTURE_BLOCKS, 3))
    return np.kron(blocks, np.ones((8, 8, 1))).astype(np.uint8)


def textured_box(extents, image=None) -> trimesh.Trimesh:
    """A box (base on z = 0) whose every face carries the whole texture (`image`, PIL, for an export): its triangles'
    vertices unmerged, each vertex's texture coordinates its two coordinates across its face's normal, scaled to
    [0, 1] (v up, OBJ's convention; the image's row 0 at v = 1)."""
    box = trimesh.creation.box(extents=extents)
    box.apply_translation([0, 0, extents[2] / 2])
    vertices = box.vertices[box.faces].reshape(-1, 3)
    axis = np.repeat(np.abs(box.face_normals).argmax(axis=1), 3)
    across = np.array([[1, 2], [0, 2], [0, 1]])[axis]                  # the two axes in each face's plane
    lo, size = box.bounds[0], np.asarray(extents, np.float64)
    uv = (np.take_along_axis(vertices, across, 1) - lo[across]) / size[across]
    return trimesh.Trimesh(vertices, np.arange(len(vertices)).reshape(-1, 3), process=False,
                           visual=trimesh.visual.TextureVisuals(uv=uv, image=image))


@dataclass
class SceneObject:
    """One diffuse object: shape type, size, object-to-world transform, linear RGB albedo (or, on a box, an sRGB
    texture over every face: textured_box)."""

    name: str
    type: str
    size: tuple[float, ...]
    transform: np.ndarray
    albedo: tuple[float, float, float]
    source: str | None = None  # mesh file of a `mesh` object
    texture: np.ndarray | None = None  # (H, W, 3) uint8 sRGB base colour of a textured box

    def local_mesh(self) -> trimesh.Trimesh:
        """Triangle mesh in the object's local frame (base on z = 0); spheres as fine icospheres."""
        t = self.type
        if t == "plane":
            m = trimesh.Trimesh([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]],
                                [[0, 1, 2], [0, 2, 3]], process=False)
            m.apply_scale([self.size[0], self.size[1], 1.0])
            return m
        if t == "box" and self.texture is not None:
            return textured_box(self.size)
        if t == "box":
            m = trimesh.creation.box(extents=self.size)
            m.apply_translation([0, 0, self.size[2] / 2])
            return m
        if t == "sphere":
            m = trimesh.creation.icosphere(subdivisions=4, radius=self.size[0])
            m.apply_translation([0, 0, self.size[0]])
            return m
        if t == "cylinder":
            m = trimesh.creation.cylinder(radius=self.size[0], height=self.size[1], sections=48)
            m.apply_translation([0, 0, self.size[1] / 2])
            return m
        if t == "mesh":
            return load_mesh(self.source, self.size[0])
        raise ValueError(f"object {self.name!r}: unknown type {t!r}")

    def to_json(self) -> dict:
        d = {"name": self.name, "type": self.type, "size": list(map(float, self.size)),
             "transform": np.asarray(self.transform, dtype=float).tolist(), "albedo": list(map(float, self.albedo))}
        if self.source:
            d["source"] = self.source
        if self.texture is not None:
            d["texture"] = "insert_texture() (photoreg.synth.scenes), sRGB"
        return d


def load_mesh(path: str | None, extent: float) -> trimesh.Trimesh:
    """A mesh file as one Trimesh, centred in x/y, base on z = 0 (file's +y up turned to +z), largest side `extent`."""
    if not path or not Path(path).is_file():
        raise FileNotFoundError(f"mesh file {path!r} not found")
    try:
        m = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for unreadable files
        raise ValueError(f"{path}: not a readable mesh ({e})") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise ValueError(f"{path}: no triangles")
    if not (np.isfinite(m.vertices).all() and m.area > 0):
        raise ValueError(f"{path}: mesh has no area (every triangle degenerate) or non-finite vertices")
    m.apply_transform(placement([0, 0, 0], rotation_xyz_deg=(90, 0, 0)))  # OBJ convention +y up -> +z up
    lo, hi = m.bounds
    m.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    m.apply_scale(extent / float(np.max(hi - lo)))
    return m


@dataclass(frozen=True)
class OrbitRig:
    """Camera path parameters: orbit about `target` at horizontal `radius`, `height` above it,
    azimuth from `azimuth_deg` over `arc_deg`, height changing by +-`wobble` (slight elevation changes)."""

    target: tuple[float, float, float]
    radius: float = 1.0
    height: float = 0.6
    azimuth_deg: float = -60.0
    arc_deg: float = 180.0
    wobble: float = 0.08

    def to_json(self) -> dict:
        return {"target": list(self.target), "radius": self.radius, "height": self.height,
                "azimuth_deg": self.azimuth_deg, "arc_deg": self.arc_deg, "wobble": self.wobble}


INSERT_MESH_SCALE = 0.2   # largest side (m) of an inserted mesh (`photoreg synth --insert-mesh`)


@dataclass(frozen=True)
class VirtualObject:
    """The object added in insert frames: a unit cube (base on z = 0), or a mesh file's object scaled to a
    largest side of 1 as load_mesh makes it, placed as in DESIGN.md's [[objects]]:
    world = R @ (scale * v) + position, R = Rotation.from_euler('xyz', rotation_deg). Mitsuba renders a mesh
    with its vertex normals interpolated (the session's objects.smooth)."""

    position: tuple[float, float, float]
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 25.0)
    scale: float = 0.12
    albedo: tuple[float, float, float] = (0.7, 0.5, 0.3)
    textured: bool = False   # insert_texture() over every face instead of `albedo`
    mesh: str | None = None  # mesh file instead of the cube

    def local_mesh(self) -> trimesh.Trimesh:
        """The object in its own frame at scale 1; a textured cube with its texture coordinates and image (OBJ
        export)."""
        if self.mesh:
            return load_mesh(self.mesh, 1.0)
        if self.textured:
            from PIL import Image

            return textured_box((1.0, 1.0, 1.0), Image.fromarray(insert_texture()))
        m = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
        m.apply_translation([0, 0, 0.5])
        return m

    def scene_object(self) -> SceneObject:
        s, T = self.scale, placement(self.position, rotation_xyz_deg=self.rotation_deg)
        if self.mesh:
            return SceneObject("virtual_mesh", "mesh", (s,), T, self.albedo, source=self.mesh)
        return SceneObject("virtual_box", "box", (s, s, s), T, self.albedo,
                           texture=insert_texture() if self.textured else None)


@dataclass
class SceneLayout:
    """A scene kind made concrete: its objects, the camera rig and the virtual object to insert."""

    kind: str
    objects: list[SceneObject]
    rig: OrbitRig
    insert: VirtualObject


def _floor(albedo=(0.5, 0.5, 0.5), size=3.0) -> SceneObject:
    return SceneObject("floor", "plane", (size, size), np.eye(4), albedo)


def build_scene(kind: str, mesh_file: str | None = None) -> SceneLayout:
    """Objects, camera rig and insert object of a scene kind (see SCENE_KINDS)."""
    target = (0.0, 0.0, 0.05)
    rig = OrbitRig(target)
    insert_at = (0.0, 0.0, 0.0)
    if kind == "tabletop":
        objs = [_floor((0.55, 0.45, 0.35)),
                SceneObject("box_flat", "box", (0.22, 0.16, 0.1), placement([0.28, 0.16, 0], 15), (0.8, 0.8, 0.75)),
                SceneObject("box_tall", "box", (0.1, 0.1, 0.26), placement([-0.22, 0.27, 0], -30), (0.3, 0.45, 0.7)),
                SceneObject("sphere_big", "sphere", (0.08,), placement([0.2, -0.25, 0]), (0.75, 0.3, 0.25)),
                SceneObject("sphere_small", "sphere", (0.05,), placement([-0.32, -0.08, 0]), (0.85, 0.85, 0.85))]
        if mesh_file:
            objs.append(SceneObject("mesh", "mesh", (0.2,), placement([-0.08, -0.32, 0], 40), (0.6, 0.6, 0.55),
                                    source=str(Path(mesh_file).resolve())))
        else:
            objs.append(SceneObject("cylinder", "cylinder", (0.06, 0.14), placement([-0.08, -0.32, 0]), (0.35, 0.6, 0.35)))
    elif kind == "corner":
        wall = (0.7, 0.7, 0.68)
        objs = [_floor((0.5, 0.5, 0.5)),
                SceneObject("wall_x", "plane", (1.2, 2.0), placement([-0.6, 0.4, 0.6], rotation_xyz_deg=(0, 90, 0)), wall),
                SceneObject("wall_y", "plane", (2.0, 1.2), placement([0.4, -0.6, 0.6], rotation_xyz_deg=(-90, 0, 0)), wall)]
        rig = OrbitRig((-0.3, -0.3, 0.3), radius=1.7, height=0.5, azimuth_deg=20.0, arc_deg=50.0)
        insert_at = (0.05, 0.05, 0.0)
    elif kind == "plane":
        objs = [_floor((0.6, 0.6, 0.6))]
    elif kind == "split_albedo":
        objs = [SceneObject("floor_black", "plane", (1.5, 3.0), placement([-0.75, 0, 0]), (0.04, 0.04, 0.04)),
                SceneObject("floor_white", "plane", (1.5, 3.0), placement([0.75, 0, 0]), (0.8, 0.8, 0.8))]
        insert_at = (0.25, 0.0, 0.0)
    elif kind == "coloured":
        objs = [_floor((0.5, 0.5, 0.5)),
                SceneObject("red_box", "box", (0.16, 0.16, 0.16), placement([0.25, 0.2, 0], 20), (0.8, 0.1, 0.1)),
                SceneObject("green_sphere", "sphere", (0.08,), placement([-0.25, 0.2, 0]), (0.1, 0.7, 0.15)),
                SceneObject("blue_cylinder", "cylinder", (0.07, 0.2), placement([-0.2, -0.25, 0]), (0.1, 0.2, 0.8)),
                SceneObject("yellow_box", "box", (0.2, 0.1, 0.08), placement([0.25, -0.22, 0], -35), (0.85, 0.75, 0.1))]
    else:
        raise ValueError(f"unknown scene kind {kind!r}; choose one of {', '.join(SCENE_KINDS)}")
    return SceneLayout(kind, objs, rig, VirtualObject(insert_at))
