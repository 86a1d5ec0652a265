"""Planar soft-shadow textures of one object on its ground plane (Sommer et al., WSCG 2023).

The texture is a square in the object's local frame: local +z is up and the object stands on the
plane z = min z of its mesh; the square has side 3x the object's largest extent and is centred under
the object's box. Texel (i, j) (row i along local +y, column j along local +x) covers the point
u = (j + 0.5) / res, v = (i + 0.5) / res of the square. A texel's value is the visible share of an
area light of `cone_angle` opening angle seen from the plane point: 1 = fully lit, 0 = fully shadowed.
Visibility is ray-traced against the mesh (Open3D RaycastingScene, Embree) with a fixed number of
stratified cone rays per texel; the light directions here are in the object's local frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PLANE_SIDE = 3.0  # texture side in units of the object's largest extent


@dataclass(frozen=True)
class TextureFrame:
    """Where a shadow texture lies in the object's local frame."""

    origin: np.ndarray   # (2,) local (x, y) of the square's corner u = v = 0
    side: float          # side length, local units
    z0: float            # ground-plane height (min z of the mesh)

    def uv(self, local: np.ndarray) -> np.ndarray:
        """(N, 2) texture coordinates of local points (N, 3) projected straight down on the plane."""
        return (local[:, :2] - self.origin) / self.side

    def points(self, res: int) -> np.ndarray:
        """(res*res, 3) local plane points at the texel centres, row-major (i, j)."""
        c = (np.arange(res) + 0.5) / res
        v, u = np.meshgrid(c, c, indexing="ij")
        xy = self.origin + self.side * np.stack([u.ravel(), v.ravel()], -1)
        return np.c_[xy, np.full(len(xy), self.z0)]


def texture_frame(vertices: np.ndarray) -> TextureFrame:
    """The texture square of a mesh given by its local vertices (V, 3); ValueError for a flat-less mesh."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    extent = float((hi - lo).max())
    if not np.isfinite(extent) or extent <= 0:
        raise ValueError(f"texture_frame: mesh has no extent (box {lo} .. {hi})")
    side = PLANE_SIDE * extent
    centre = 0.5 * (lo[:2] + hi[:2])
    return TextureFrame(centre - 0.5 * side, side, float(lo[2]))


def light_grid(theta_max_deg: float, theta_step_deg: float, phi_step_deg: float) -> np.ndarray:
    """(K, 3) local unit directions to the light: theta = 0 once, then every theta step up to theta_max
    at every phi step (45 / 4.5 / 12 degrees give 1 + 10 * 30 = 301)."""
    thetas = np.arange(1, int(round(theta_max_deg / theta_step_deg)) + 1) * np.radians(theta_step_deg)
    phis = np.arange(int(round(360.0 / phi_step_deg))) * np.radians(phi_step_deg)
    t, p = np.meshgrid(thetas, phis, indexing="ij")
    t, p = np.r_[0.0, t.ravel()], np.r_[0.0, p.ravel()]
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)


def _tangents(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing d to an orthonormal frame."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = np.cross(d, a)
    t1 /= np.linalg.norm(t1)
    return t1, np.cross(d, t1)


def cone_rays(axis: np.ndarray, count: int, rays: int, cone_angle: float, rng: np.random.Generator) -> np.ndarray:
    """(count, rays, 3) directions uniform in solid angle inside a cone of full opening `cone_angle`
    (radians) around unit `axis`: `count` sets of `rays`, each stratified on a sqrt(rays)^2 grid of
    (cos theta, phi) with its own jitter."""
    m = int(round(np.sqrt(rays)))
    if m * m != rays or rays < 1:
        raise ValueError(f"cone_rays: rays per texel must be a square number (1, 4, 9, 16, ...), got {rays}")
    a, b = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    u1 = (a.ravel() + rng.random((count, rays))) / m
    u2 = (b.ravel() + rng.random((count, rays))) / m
    cos_t = 1.0 - u1 * (1.0 - np.cos(0.5 * cone_angle))
    sin_t = np.sqrt(np.maximum(1.0 - cos_t ** 2, 0.0))
    t1, t2 = _tangents(axis)
    phi = 2.0 * np.pi * u2
    return cos_t[..., None] * axis + sin_t[..., None] * (np.cos(phi)[..., None] * t1 + np.sin(phi)[..., None] * t2)


class ShadowTracer:
    """Ray-traces shadow textures of one mesh (local frame) with Open3D's RaycastingScene."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import open3d as o3d

        self.o3d = o3d
        self.vertices = np.asarray(vertices, np.float64)
        self.frame = texture_frame(self.vertices)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                 o3d.core.Tensor(np.asarray(faces).astype(np.uint32)))
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        self.centre, self.radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))

    def texture(self, direction: np.ndarray, res: int, rays: int, cone_angle: float, seed: int = 0) -> np.ndarray:
        """(res, res) float32 visibility of a light of full opening `cone_angle` (radians) around the
        local unit `direction`. Texels whose light cone cannot reach the mesh's bounding sphere are 1
        without tracing; the rest trace `rays` stratified rays each, jittered per texel."""
        d = np.asarray(direction, np.float64)
        d = d / np.linalg.norm(d)
        pts = self.frame.points(res)
        to_c = self.centre - pts
        dist = np.linalg.norm(to_c, axis=1)
        ang = np.arccos(np.clip(to_c @ d / np.maximum(dist, 1e-12), -1.0, 1.0))
        reach = 0.5 * cone_angle + np.arcsin(np.clip(self.radius / np.maximum(dist, 1e-12), 0.0, 1.0))
        cand = np.nonzero(ang <= reach + 1e-6)[0]
        vis = np.ones(res * res, np.float32)
        if len(cand):
            dirs = cone_rays(d, len(cand), rays, cone_angle, np.random.default_rng(seed))
            origin = np.broadcast_to(pts[cand][:, None, :], dirs.shape)
            ray = np.concatenate([origin, dirs], -1).reshape(-1, 6).astype(np.float32)
            tnear = 1e-5 * self.frame.side
            hit = self.scene.test_occlusions(self.o3d.core.Tensor(ray), tnear=tnear).numpy()
            vis[cand] = 1.0 - hit.reshape(len(cand), rays).mean(1)
        return vis.reshape(res, res)
