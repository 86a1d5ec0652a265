"""The virtual scene: the session's [[objects]] as world-space meshes, and their signed-distance grid.

world = R @ (scale * v) + position, R = Rotation.from_euler('xyz', rotation, degrees=True) (DESIGN.md).
Every object is checked when the scene loads (missing or unreadable file, empty mesh, non-finite
transform or albedo, albedo = "texture" on a mesh without one), so a bad object fails the run before any frame is
processed. The SDF grid
(voxel_grid) lets the transfer kernel test visibility rays against real and virtual geometry in one pass.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from photoreg.config import ALBEDO_TEXTURE, ObjectConfig
from photoreg.device import init_warp
from photoreg.io.images import srgb_to_linear
from photoreg.kernels.gbuffer import CORNER_COLOURS, NO_TEXTURE
from photoreg.kernels.grid import SDF_DTYPE, SDF_NUMPY, DenseGrid, update_empty_distance

wp = init_warp()

GRID_RESOLUTION = 64   # voxels along the scene's largest extent (capped at the TSDF voxel size)
GRID_CELL = 8          # voxels per empty-skipping cell
GRID_TRUNC_VOXELS = 4.0
GRID_MAX_VOXELS = 1 << 24   # the objects' SDF grid at most (64 MB of float32): coarser voxels for objects far apart
MAX_OBJECT_EXTENT = 50.0    # metres an object may span as placed: more is a unit or `scale` mistake


@dataclass
class VirtualObject:
    """One placed object: world-space triangles, its linear albedo (one colour, a texture or corner colours) and, if
    smooth, its vertex normals."""

    source: str                 # the mesh file, for messages
    vertices: np.ndarray        # (V, 3) float64 world positions
    faces: np.ndarray           # (F, 3) int64
    albedo: np.ndarray          # (3,) float32 linear RGB (varying: the mean of its parts' means, by area)
    transform: np.ndarray       # (4, 4) object-to-world (object_transform)
    # Where each face takes its albedo when it varies (objects.albedo = "texture"), (F,) int32: an index into
    # `textures`, or CORNER_COLOURS (`corners`); None: the one `albedo` everywhere.
    face_source: np.ndarray | None = None
    textures: list = field(default_factory=list)  # (H, W, 3) float32 linear RGB albedos, row 0 the image's top
    uv: np.ndarray | None = None       # (V, 2) float32 texture coordinates (origin at the image's bottom left)
    corners: np.ndarray | None = None  # (F, 3, 3) float32 linear RGB albedo at each face's corners (vertex colours)
    normals: np.ndarray | None = None  # (V, 3) float32 world unit vertex normals of a smooth object (objects.smooth)

    def local_vertices(self) -> np.ndarray:
        """(V, 3) vertices in the mesh file's own frame (the transform undone)."""
        T = self.transform
        return np.linalg.solve(T[:3, :3], (self.vertices - T[:3, 3]).T).T


@dataclass
class FaceAttributes:
    """What varies over each face of VirtualScene.triangles(): `source` (F,) where it takes its albedo (a texture's
    index, NO_TEXTURE: its object's one albedo, or CORNER_COLOURS), `smooth` (F,) whether its normal varies; its
    corners' texture coordinates (F, 3, 2), linear colours (F, 3, 3) and unit normals (F, 3, 3), zero where unused;
    the textures."""

    source: np.ndarray
    smooth: np.ndarray
    uv: np.ndarray
    corners: np.ndarray
    normals: np.ndarray
    textures: list[np.ndarray]

    def varies(self) -> np.ndarray:
        """(F,) whether a face's albedo or normal varies over it."""
        return (self.source != NO_TEXTURE) | self.smooth


@dataclass
class VirtualScene:
    objects: list[VirtualObject]

    @cached_property
    def boxes(self) -> np.ndarray:
        """(K, 2, 3) each object's world axis-aligned box, read-only (the objects are placed once and the boxes are
        read every frame: made once, 0.2 ms a time for the bunny on the H100's host)."""
        box = np.stack([np.stack([o.vertices.min(0), o.vertices.max(0)]) for o in self.objects])
        box.flags.writeable = False
        return box

    @cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) world axis-aligned box of every object, read-only."""
        box = np.stack([self.boxes[:, 0].min(0), self.boxes[:, 1].max(0)])
        box.flags.writeable = False
        return box

    def containing(self, point: np.ndarray) -> list[int]:
        """Indices of the objects that hold the world `point` (the camera inside an object sees it from within: the
        render stage says so): a box test, then the generalised winding number of the object's triangles about the
        point (solid angles summed, Van Oosterom-Strackee), |w| > 1/2, which open meshes (a teapot's rim) and
        overlapping parts hold too where ray parity does not."""
        point = np.asarray(point, np.float64)
        inside = []
        for k, o in enumerate(self.objects):
            if np.any(point < self.boxes[k, 0]) or np.any(point > self.boxes[k, 1]):
                continue
            a, b, c = (o.vertices[o.faces[:, j]] - point for j in range(3))
            la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
            det = np.einsum("ij,ij->i", a, np.cross(b, c))
            den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
                   + np.einsum("ij,ij->i", c, a) * lb)
            if abs(np.arctan2(det, den).sum() / (2 * np.pi)) > 0.5:
                inside.append(k)
        return inside

    def triangles(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All objects as one mesh: vertices (V, 3), faces (F, 3), per-face object index (F,)."""
        verts, faces, owner, base = [], [], [], 0
        for k, o in enumerate(self.objects):
            verts.append(o.vertices)
            faces.append(o.faces + base)
            owner.append(np.full(len(o.faces), k, np.int32))
            base += len(o.vertices)
        return np.concatenate(verts), np.concatenate(faces), np.concatenate(owner)

    def face_attributes(self) -> FaceAttributes:
        """What varies over each face, alongside triangles()."""
        source, smooth, uv, corners, normals, textures = [], [], [], [], [], []
        for o in self.objects:
            n = len(o.faces)
            if o.face_source is None:
                source.append(np.full(n, NO_TEXTURE, np.int32))
            else:   # the object's texture indices after those of the objects before it
                source.append(np.where(o.face_source >= 0, o.face_source + len(textures), o.face_source))
                textures.extend(o.textures)
            smooth.append(np.full(n, o.normals is not None))
            uv.append(o.uv[o.faces] if o.uv is not None else np.zeros((n, 3, 2), np.float32))
            corners.append(o.corners if o.corners is not None else np.zeros((n, 3, 3), np.float32))
            normals.append(o.normals[o.faces] if o.normals is not None else np.zeros((n, 3, 3), np.float32))
        return FaceAttributes(*(np.concatenate(a) for a in (source, smooth, uv, corners, normals)), textures)


def object_transform(obj: ObjectConfig) -> np.ndarray:
    """4x4 object-to-world matrix: world = R @ (scale * v) + position; ValueError when non-finite."""
    from scipy.spatial.transform import Rotation

    vals = np.array([*obj.position, *obj.rotation, obj.scale], dtype=np.float64)
    if vals.shape != (7,) or not np.all(np.isfinite(vals)) or not obj.scale > 0:
        raise ValueError(f"{obj.mesh}: object transform must be finite with scale > 0 "
                         f"(position {obj.position}, rotation {obj.rotation}, scale {obj.scale})")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", obj.rotation, degrees=True).as_matrix() * obj.scale
    T[:3, 3] = obj.position
    return T


def load_object(obj: ObjectConfig) -> VirtualObject:
    """Load and place one object (PLY/OBJ/OFF/GLB via trimesh); clear errors naming the file."""
    import trimesh

    path = Path(obj.mesh)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: virtual object mesh not found")
    T = object_transform(obj)
    textured = isinstance(obj.albedo, str)
    if textured and obj.albedo != ALBEDO_TEXTURE:
        raise ValueError(f"{path}: object albedo must be 3 numbers or {ALBEDO_TEXTURE!r}, got {obj.albedo!r}")
    if not textured:
        albedo = np.asarray(obj.albedo, dtype=np.float64)
        if albedo.shape != (3,) or not np.all(np.isfinite(albedo)) or np.any(albedo < 0):
            raise ValueError(f"{path}: object albedo must be 3 finite non-negative numbers, got {obj.albedo}")
    obj_file = path.suffix.lower() == ".obj"
    materials = obj_material_files(path) if textured and obj_file else []
    for name, file, what in materials:   # trimesh goes on without them: the flat Kd colour, or none
        if file is None:
            raise FileNotFoundError(f"{path}: its {what} {name!r} is missing (looked for in {path.parent})")
    try:   # the parts apart: each keeps its own material (mesh_parts)
        parts = mesh_parts(trimesh.load(str(path), process=True))
    except Exception as e:  # trimesh raises many types for unreadable files
        raise ValueError(f"{path}: cannot read mesh ({e})") from None
    if not all(isinstance(m, trimesh.Trimesh) for m in parts) or not any(len(m.faces) for m in parts):
        raise ValueError(f"{path}: mesh has no triangles (those with a non-finite vertex are dropped on reading)")
    local = np.concatenate([np.asarray(m.vertices, np.float64) for m in parts])
    if not np.all(np.isfinite(local)):
        raise ValueError(f"{path}: mesh has non-finite vertices")
    if not sum(m.area for m in parts) > 0:
        raise ValueError(f"{path}: mesh has no area (every triangle degenerate)")
    v = local @ T[:3, :3].T + T[:3, 3]
    extent = float(np.ptp(v, axis=0).max())
    if extent > MAX_OBJECT_EXTENT:
        raise ValueError(f"{path}: the object spans {extent:.4g} m as placed (scale {obj.scale}), more than "
                         f"{MAX_OBJECT_EXTENT:g} m: check the mesh's units and the object's scale")
    base = np.cumsum([0] + [len(m.vertices) for m in parts])
    faces = np.concatenate([np.asarray(m.faces, np.int64) + b for m, b in zip(parts, base)])
    normals = None
    if obj.smooth:   # the file's vertex normals, else trimesh's (the mean of the faces' round each vertex), turned
        normals = np.concatenate([np.asarray(m.vertex_normals, np.float64) for m in parts]) @ T[:3, :3].T
        normals = (normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)).astype(np.float32)
    if not textured:
        return VirtualObject(str(path), v, faces, albedo.astype(np.float32), T, normals=normals)
    varying = [part_albedo(m, path, obj_file and not materials) for m in parts]
    textures = [a.texture for a in varying if a.texture is not None]
    index = np.cumsum([0] + [a.texture is not None for a in varying])   # each part's texture, if it has one
    source = np.concatenate([np.full(len(m.faces), CORNER_COLOURS if a.texture is None else k, np.int32)
                             for m, a, k in zip(parts, varying, index)])
    area = np.array([m.area for m in parts])
    mean = np.average([a.mean for a in varying], axis=0, weights=area if area.sum() > 0 else None)
    return VirtualObject(str(path), v, faces, mean.astype(np.float32), T, source, textures,
                         np.concatenate([a.uv for a in varying]), np.concatenate([a.corners for a in varying]), normals)


@dataclass
class PartAlbedo:
    """One part's varying albedo, float32: its texture coordinates (V, 2), corner colours (F, 3, 3), mean linear RGB
    (3,) and texture (None: the corners')."""

    uv: np.ndarray
    corners: np.ndarray
    mean: np.ndarray
    texture: np.ndarray | None


def part_albedo(mesh, path: Path, bare_obj: bool) -> PartAlbedo:
    """Vertex or face colours (8-bit sRGB) at the corners, else the part's base-colour texture (base_colour_texture;
    `bare_obj`: the part of an OBJ without a material library) with zero corners."""
    kind = getattr(mesh.visual, "kind", None)
    if kind in ("vertex", "face"):   # colours at the vertices (or per face), 8-bit sRGB
        colours = mesh.visual.vertex_colors[mesh.faces] if kind == "vertex" else np.repeat(
            np.asarray(mesh.visual.face_colors)[:, None], 3, axis=1)
        corners = srgb_to_linear(np.ascontiguousarray(np.asarray(colours, np.uint8)[..., :3])).astype(np.float32)
        return PartAlbedo(np.zeros((len(mesh.vertices), 2), np.float32), corners, corners.mean(axis=(0, 1)), None)
    uv, texture = base_colour_texture(mesh, path, bare_obj)
    return PartAlbedo(uv, np.zeros((len(mesh.faces), 3, 3), np.float32), texture.mean(axis=(0, 1)), texture)


def mesh_parts(loaded) -> list:
    """A loaded mesh file as its meshes, one per material (a GLB's geometries, an OBJ's materials), placed by the
    file's scene graph. Apart, each keeps its own texture and colour: trimesh's merged mesh packs them into one atlas
    image whose padding the bilinear lookup blends into the faces along its tiles' edges (Kenney's chairDesk.glb,
    three colours: a tenth of its pixels off by more than 0.01)."""
    import trimesh

    if isinstance(loaded, trimesh.Scene):
        return [m for m in loaded.dump(concatenate=False) if isinstance(m, trimesh.Trimesh) and len(m.faces)]
    return [loaded]


def base_colour_texture(mesh, path: Path, bare_obj: bool) -> tuple[np.ndarray, np.ndarray]:
    """(uv (V, 2) float32, linear RGB albedo (H, W, 3) float32) of a trimesh mesh's base colour: its texture image
    decoded from sRGB, times the material's baseColorFactor where it has one (glTF's PBR materials; OBJ's and PLY's
    images alone), or that factor alone (a 1 x 1 texture) where a glTF material has no image (an OBJ's: its Kd).
    ValueError naming the file when there is neither, or an image without texture coordinates."""
    material = getattr(mesh.visual, "material", None)
    if bare_obj:
        material = None   # trimesh gives an OBJ with texture coordinates and no material a grey stand-in image
    image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
    factor = getattr(material, "baseColorFactor", None)
    if image is None and factor is None and path.suffix.lower() == ".obj":
        factor = getattr(material, "diffuse", None)   # an OBJ material without an image: its Kd (linear)
    if image is None and factor is None:
        raise ValueError(f"{path}: albedo = {ALBEDO_TEXTURE!r} but the mesh has no texture image, base colour or "
                         "vertex colours")
    scale = np.ones(3, np.float32)
    if factor is not None:
        scale = np.asarray(factor, np.float32)[:3] / (255.0 if np.asarray(factor).dtype == np.uint8 else 1.0)
    if image is None:
        return np.zeros((len(mesh.vertices), 2), np.float32), scale.reshape(1, 1, 3)
    uv = getattr(mesh.visual, "uv", None)
    if uv is None or len(uv) != len(mesh.vertices) or not np.all(np.isfinite(uv)):
        raise ValueError(f"{path}: albedo = {ALBEDO_TEXTURE!r} but the mesh has no (finite) texture coordinates")
    texture = srgb_to_linear(np.ascontiguousarray(_rgb8(image)))
    return np.asarray(uv, np.float32), np.ascontiguousarray(texture * scale, np.float32)


def _rgb8(image) -> np.ndarray:
    """A PIL image as HxWx3 uint8: 16-bit grey (PIL's modes "I;16*" and "I" for a 16-bit grey PNG) scaled to 8 bits,
    since convert("RGB") clips its values at 255 (white); every other mode through convert."""
    if image.mode.startswith("I"):
        grey = np.clip(np.round(np.asarray(image, np.float64) / 257.0), 0, 255).astype(np.uint8)
        return np.repeat(grey[..., None], 3, axis=2)
    return np.asarray(image.convert("RGB"), np.uint8)


def _found_by_trimesh(folder: Path, name: str) -> Path | None:
    """The file trimesh's resolver reads for `name`, asked by a file in `folder`: the name as written (a leading /
    dropped), else its base name, inside the folder; None where it finds none."""
    root = folder.resolve()
    for candidate in (name.strip(), name.strip().lstrip("/"), Path(name.strip()).name):
        file = (root / candidate).resolve()
        if candidate and file.is_relative_to(root) and file.is_file():
            return file
    return None


def obj_material_files(path: Path) -> list[tuple[str, Path | None, str]]:
    """What an OBJ's look depends on besides itself, read as trimesh reads it (5.x: the rest of its first mtllib
    line; in that library the rest of each map_Kd line, in any case; both looked up from the OBJ's folder): (the
    name as written, the file trimesh reads for it or None where it finds none, what it is)."""
    text = path.read_text(errors="replace")
    at = text.find("mtllib")
    if at < 0:
        return []
    end = text.find("\n", at)
    name = text[at + len("mtllib"):len(text) if end < 0 else end].strip()
    library = _found_by_trimesh(path.parent, name)
    files = [(name, library, "material library")]
    if library is not None:
        for line in library.read_text(errors="replace").splitlines():
            if line.strip().lower().startswith("map_kd") and len(line.split()) > 1:
                image = line[line.lower().index("map_kd") + len("map_kd"):].strip()
                files.append((image, _found_by_trimesh(path.parent, image), "texture image (map_Kd)"))
    return files


def load_scene(objects: list[ObjectConfig]) -> VirtualScene:
    """Every object of a session, placed in the world; ValueError when there are none."""
    if not objects:
        raise ValueError("load_scene: the session has no [[objects]]")
    return VirtualScene([load_object(o) for o in objects])


def voxel_grid(scene: VirtualScene, max_voxel: float, device: str) -> DenseGrid:
    """Signed-distance DenseGrid of the whole virtual scene (Open3D RaycastingScene, negative inside),
    voxel = min(largest extent / GRID_RESOLUTION, max_voxel), coarser where the grid would hold more than
    GRID_MAX_VOXELS (large objects, or objects far apart); built once per run."""
    import open3d as o3d

    verts, faces, _ = scene.triangles()
    lo, hi = scene.bounds
    voxel = float(min(max((hi - lo).max() / GRID_RESOLUTION, 1e-4), max_voxel))
    while True:
        trunc = GRID_TRUNC_VOXELS * voxel
        pad = trunc + 2 * voxel
        origin = lo - pad
        dims = np.ceil((hi + pad - origin) / voxel).astype(np.int64) + 1
        dims = (-(-dims // GRID_CELL) * GRID_CELL).astype(np.int64)
        if np.prod(dims.astype(float)) <= GRID_MAX_VOXELS:
            break
        voxel *= 1.05 * (np.prod(dims.astype(float)) / GRID_MAX_VOXELS) ** (1 / 3)
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    axes = [(origin[k] + np.arange(d) * voxel).astype(np.float32) for k, d in enumerate(dims)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    sdf = rs.compute_signed_distance(o3d.core.Tensor(pts)).numpy().reshape(*dims).astype(np.float32)
    return sdf_grid(sdf, origin, voxel, trunc, device)


def sdf_grid(sdf: np.ndarray, origin, voxel: float, trunc: float, device: str) -> DenseGrid:
    """DenseGrid from a numpy SDF (nx, ny, nz; each a multiple of GRID_CELL), clamped to +-trunc, with
    its empty-space distance field."""
    sdf = np.clip(np.asarray(sdf, np.float32), -trunc, trunc)
    if sdf.ndim != 3 or any(d % GRID_CELL for d in sdf.shape):
        raise ValueError(f"sdf_grid: shape {sdf.shape} must be 3-D with sides multiple of {GRID_CELL}")
    c = [d // GRID_CELL for d in sdf.shape]
    occupied = (sdf.reshape(c[0], GRID_CELL, c[1], GRID_CELL, c[2], GRID_CELL).min(axis=(1, 3, 5))
                < trunc).astype(np.uint8)
    occ_wp = wp.array(occupied, dtype=wp.uint8, device=device)
    empty = wp.empty_like(occ_wp)
    update_empty_distance(occ_wp, empty)
    return DenseGrid(sdf=wp.array(sdf.astype(SDF_NUMPY), dtype=SDF_DTYPE, device=device),
                     origin=np.asarray(origin, np.float64), voxel_size=float(voxel), trunc=float(trunc),
                     shape=tuple(int(d) for d in sdf.shape), empty=empty, cell=GRID_CELL)
