"""Mitsuba 3 rendering for the generator (the only module importing Mitsuba; it is an optional extra).

Conventions checked by tests/test_synth.py:
- Mitsuba's camera looks down local +z with +y up and +x to the LEFT, so an OpenCV camera-to-world
  C becomes to_world = C @ diag(-1, -1, 1, 1). A centred principal point cx = (W-1)/2 (OpenCV pixel
  centres) is Mitsuba's default; fov_x = 2 atan(W / (2 fx)).
- Geometry comes from a 1-spp pass with a non-jittered stratified sampler (rays through exact pixel
  centres) and a box filter (no blending), as world positions converted to camera z. Mitsuba's
  `depth` AOV is used only as the hit mask: it is the ray distance minus the sensor's near clip.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from ..types import Intrinsics
from .scenes import SceneObject

_MI = None


def mitsuba():
    """Import Mitsuba and set its variant once: llvm_ad_rgb, else scalar_rgb with a warning."""
    global _MI
    if _MI is None:
        try:
            import mitsuba as mi
        except ImportError as e:
            raise RuntimeError("photoreg synth needs Mitsuba 3: pip install 'photoreg[synth]'") from e
        try:
            mi.set_variant("llvm_ad_rgb")
            import drjit as dr

            dr.eval(mi.Float(1.0) + 1.0)  # fails here when the LLVM backend cannot start
        except Exception as e:  # drjit/mitsuba raise plain Exceptions for a missing LLVM
            warnings.warn(f"Mitsuba llvm_ad_rgb unavailable ({e}); falling back to scalar_rgb (much slower)")
            mi.set_variant("scalar_rgb")
        _MI = mi
    return _MI


def _bsdf(albedo) -> dict:
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(map(float, albedo))}}}


def _textured_bsdf(texture: np.ndarray):
    """Mitsuba diffuse BSDF (loaded) whose reflectance is an 8-bit sRGB texture (Mitsuba decodes it to linear: raw =
    false), bilinear, repeating; read from a PNG written for it."""
    import tempfile
    from pathlib import Path

    from PIL import Image

    with tempfile.TemporaryDirectory() as folder:   # Mitsuba reads the image when the dictionary is loaded
        png = str(Path(folder) / "texture.png")
        Image.fromarray(np.asarray(texture, np.uint8)).save(png)
        return mitsuba().load_dict({"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
            "type": "bitmap", "filename": png, "raw": False, "filter_type": "bilinear", "wrap_mode": "repeat"}}})


def _shape(obj: SceneObject):
    """Mitsuba shape of an object: spheres analytic, everything else its triangle mesh (flat normals,
    smooth ones for `mesh` objects)."""
    mi = mitsuba()
    if obj.type == "sphere":
        r = float(obj.size[0])
        to_world = np.asarray(obj.transform) @ np.array([[r, 0, 0, 0], [0, r, 0, 0], [0, 0, r, r], [0, 0, 0, 1.0]])
        return {"type": "sphere", "to_world": mi.ScalarTransform4f(to_world.tolist()), "bsdf": _bsdf(obj.albedo)}
    tm = obj.local_mesh()
    tm.apply_transform(obj.transform)
    smooth = obj.type == "mesh"
    textured = obj.texture is not None
    props = mi.Properties()
    props["bsdf"] = _textured_bsdf(obj.texture) if textured else mi.load_dict(_bsdf(obj.albedo))
    mesh = mi.Mesh(obj.name, len(tm.vertices), len(tm.faces), props=props, has_vertex_normals=smooth,
                   has_vertex_texcoords=textured)
    params = mi.traverse(mesh)
    floats, ints = type(params["vertex_positions"]), type(params["faces"])
    params["vertex_positions"] = floats(np.asarray(tm.vertices, dtype=np.float32).ravel())
    params["faces"] = ints(np.asarray(tm.faces, dtype=np.uint32).ravel())
    if smooth:
        params["vertex_normals"] = floats(np.asarray(tm.vertex_normals, dtype=np.float32).ravel())
    if textured:   # Mitsuba's bitmap puts the image's row 0 at v = 0, OBJ's (the mesh's) at v = 1
        uv = np.asarray(tm.visual.uv, np.float32)
        params["vertex_texcoords"] = floats(np.stack([uv[:, 0], 1.0 - uv[:, 1]], 1).ravel())
    params.update()
    return mesh


def _to_world(pose: np.ndarray):
    return mitsuba().ScalarTransform4f((np.asarray(pose, dtype=np.float64) @ np.diag([-1.0, -1.0, 1.0, 1.0])).tolist())


class MitsubaScene:
    """Objects under an environment map, rendered from OpenCV camera poses with fixed intrinsics.

    render(): linear RGB radiance (path tracer, `max_depth` 2 = direct light only);
    geometry(): camera z in metres per pixel centre, 0 where the ray escapes.
    """

    def __init__(self, objects: list[SceneObject], env_image: np.ndarray, env_rotation: np.ndarray,
                 intrinsics: Intrinsics, max_depth: int = 6):
        mi = mitsuba()
        K = intrinsics
        if abs(K.fx - K.fy) > 1e-6 * K.fx or abs(K.cx - (K.width - 1) / 2) > 1e-6 or abs(K.cy - (K.height - 1) / 2) > 1e-6:
            raise ValueError("synth cameras need fx == fy and a centred principal point (cx=(W-1)/2, cy=(H-1)/2)")
        self.K = K
        to_env = np.eye(4)
        to_env[:3, :3] = env_rotation
        film = {"type": "hdrfilm", "width": K.width, "height": K.height, "rfilter": {"type": "box"}, "pixel_format": "rgb"}
        fov = math.degrees(2.0 * math.atan(K.width / (2.0 * K.fx)))
        cam = {"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": _to_world(np.eye(4)), "film": film}
        scene = {"type": "scene",
                 "env": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(env_image, dtype=np.float32)),
                         "to_world": mi.ScalarTransform4f(to_env.tolist())},
                 "colour_cam": {**cam, "sampler": {"type": "independent"}},
                 "geometry_cam": {**cam, "sampler": {"type": "stratified", "sample_count": 1, "jitter": False}}}
        for i, obj in enumerate(objects):
            scene[f"obj{i}_{obj.name}"] = _shape(obj)
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)
        self.colour_cam, self.geometry_cam = self.scene.sensors()
        self.path = mi.load_dict({"type": "path", "max_depth": int(max_depth)})
        self.aov = mi.load_dict({"type": "aov", "aovs": "hit:depth,pos:position"})

    def _place(self, pose: np.ndarray) -> None:
        self.params["colour_cam.to_world"] = _to_world(pose)
        self.params["geometry_cam.to_world"] = _to_world(pose)
        self.params.update()

    def render(self, pose: np.ndarray, spp: int, seed: int = 0) -> np.ndarray:
        """Linear RGB radiance (H, W, 3) float32 seen from camera-to-world `pose`."""
        mi = mitsuba()
        self._place(pose)
        img = mi.render(self.scene, sensor=self.colour_cam, integrator=self.path, spp=int(spp), seed=int(seed))
        return np.array(img, dtype=np.float32)[..., :3]

    def geometry(self, pose: np.ndarray) -> np.ndarray:
        """Camera z (H, W) float32 metres at exact pixel centres; 0 where nothing is hit."""
        mi = mitsuba()
        self._place(pose)
        img = np.array(mi.render(self.scene, sensor=self.geometry_cam, integrator=self.aov, spp=1, seed=0))
        hit = img[..., 0] > 0
        pose = np.asarray(pose, dtype=np.float64)
        z = (img[..., 1:4] - pose[:3, 3]) @ pose[:3, 2]
        return np.where(hit, z, 0.0).astype(np.float32)
