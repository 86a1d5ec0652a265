"""`shadowmap` renderer: one directional light from the SH lighting (photoreg.lighting.parametric), an
orthographic shadow map of the virtual objects fitted to them, PCSS-filtered lookups at the real surface
and at the virtual surface (self-shadowing), and real shadows protected (Jacobs et al.).

Real pixels. With o the lobe's share of the irradiance at the receiver (receiver_opacity), s the mapped
shadow and v the share of the light's disc the real geometry leaves open, the camera shows
E_amb + E_lobe v; the object removes E_lobe v s, so
    ratio = 1 - s o v / ((1 - o) + o v)      (= 1 - o s when the light is open; 1 under a real shadow).
The strength o is measured where the frame shows it (measured_opacity: per material, shadowed against lit
real radiance where the real geometry blocks the light), else the parametric lobe share.
Receivers are the real surface at the lighting stride inside the map's footprint (widened by the largest
filter radius), not only those within ray_length: a low light casts shadows farther than the voxel rays reach.
Virtual pixels: albedo * gain / pi * (E_residual(n) + E_lobe max(n.d, 0) (1 - s_self) v), the units of
voxel.py's albedo * F.R * gain (F.R = E / pi for an open point).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from photoreg.kernels.shadowmap import ShadowMap, depth_map, real_light_visibility, shadow_lookup
from photoreg.lighting import albedo as alb
from photoreg.lighting.solver import SolverConfig
from photoreg.lighting.parametric import ParametricLight, light_basis, receiver_opacity
from photoreg.render.composite import (Layers, RenderInput, at_stride, changed_box, darkened, refine_seam,
                                      upsample_ratio)

RESOLUTION = 512        # shadow-map texels per side
PAD_TEXELS = 2          # empty border around the objects' footprint
MAX_RADIUS = RESOLUTION / 4  # largest blocker-search / filter radius, texels: a 30 deg light's penumbra from
                             # blockers up to 0.44 map sides high (the tap count, not the radius, sets the cost)
REAL_SAMPLES = 8        # rays over the light's disc for the real geometry's visibility
MEASURE_MIN = 12        # shadowed and lit samples a material needs for a measured shadow strength
SELF_OFFSET_TEXELS = 2.0  # normal offset of virtual receivers' lookups (the real surface is not in the map:
                          # no offset, which would shift its shadow toward the object by offset * tan(theta))


def fit_shadow_map(vertices: np.ndarray, faces: np.ndarray, d: np.ndarray, device: str,
                   resolution: int = RESOLUTION) -> ShadowMap:
    """Shadow map of the triangles from direction d, its square footprint fitted to their projection."""
    u, v = light_basis(d)
    pu, pv, pd = vertices @ u, vertices @ v, vertices @ d
    side = max(pu.max() - pu.min(), pv.max() - pv.min(), 1e-6)
    texel = side / (resolution - 2 * PAD_TEXELS)
    lift = 0.05 * (pd.max() - pd.min()) + texel          # the light plane sits just above the objects
    corner = (u * (0.5 * (pu.max() + pu.min()) - 0.5 * resolution * texel)
              + v * (0.5 * (pv.max() + pv.min()) - 0.5 * resolution * texel) + d * (pd.max() + lift))
    max_t = pd.max() - pd.min() + 2 * lift
    return depth_map(vertices, faces, corner, u, v, d, texel, resolution, max_t, device)


def in_footprint(smap: ShadowMap, points: np.ndarray, resolution: int, reach_texels: float) -> np.ndarray:
    """Points (..., 3) whose lookups can meet a blocker: inside the map widened by reach_texels, below z_min."""
    rel = points - smap.corner
    x, y, z = rel @ smap.u / smap.texel, rel @ smap.v / smap.texel, -(rel @ smap.d)
    lo, hi = -reach_texels, resolution + reach_texels
    return (x >= lo) & (x <= hi) & (y >= lo) & (y <= hi) & (z > smap.z_min)


def protected_ratio(shadow: np.ndarray, opacity: np.ndarray, real_vis: np.ndarray) -> np.ndarray:
    """1 - s o v / ((1 - o) + o v) per channel: shadow (N,), opacity (N, 3), real visibility (N,)."""
    ov = opacity * real_vis[:, None]
    lost = shadow[:, None] * ov / np.maximum((1.0 - opacity) + ov, 1e-12)
    return np.clip(1.0 - lost, 0.0, 1.0).astype(np.float32)


def measured_opacity(colour: np.ndarray, points: np.ndarray, normals: np.ndarray, light: ParametricLight,
                     real_vis: np.ndarray, min_count: int = MEASURE_MIN) -> tuple[np.ndarray, list[str]]:
    """Shadow strength (N, 3) per material, measured in the frame (Jacobs et al.): real surface points
    facing the light (n.d > 0.3) are grouped by chromaticity (photoreg.lighting.albedo.cluster), the shadowed part
    of the largest plane, which the sky tints to a group of its own, joined to it (albedo.join_shadows: else the
    plane kept only a few shadowed points it misgrouped, and its strength, measured on those where a fine stride
    gave min_count of them, came out 0.54 at render stride 1, 0.33 at 3 and the parametric one at 4); in each
    group 1 - median(shadowed) / median(lit) of their radiance divided by the parametric light's
    unshadowed shading, shadowed = the real geometry blocks the light (real_vis < 0.1), lit = real_vis >
    0.9. Groups with fewer than `min_count` of either keep the parametric opacity (receiver_opacity);
    returns the strengths for all N points and notes saying which groups were measured."""
    opacity = receiver_opacity(light, normals)
    facing = (normals @ light.direction) > 0.3
    if np.count_nonzero(facing & (real_vis < 0.1)) < min_count:
        return opacity, []
    expected = sum(light.irradiance(normals))
    reflect = colour / np.maximum(expected, 1e-12)                       # albedo-like, per channel
    labels = alb.cluster(alb.colour_features(colour, with_intensity=False), SolverConfig.chroma_bandwidth,
                         min_count)
    labels = alb.join_shadows(labels, real_vis > 0.5, points, normals)
    notes = []
    for g in range(int(labels.max()) + 1 if labels.size else 0):
        mine = labels == g
        sh_ = mine & facing & (real_vis < 0.1)
        lit = mine & facing & (real_vis > 0.9)
        if sh_.sum() < min_count or lit.sum() < min_count:
            continue
        strength = 1.0 - np.median(reflect[sh_], axis=0) / np.maximum(np.median(reflect[lit], axis=0), 1e-12)
        opacity[mine] = np.clip(strength, 0.0, 1.0)
        notes.append(f"shadowmap: material {g} shadow strength measured {np.round(np.clip(strength, 0, 1), 2).tolist()} "
                     f"({int(sh_.sum())} shadowed / {int(lit.sum())} lit samples)")
    return opacity, notes


def _virtual_colour(inp: RenderInput, light: ParametricLight, lobe_vis: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """albedo * gain / pi * (E_residual(n) + E_lobe max(n.d, 0) lobe_vis) at covered pixels, zero elsewhere."""
    lobe, amb = light.irradiance(inp.gbuffer.normal[covered])
    e = amb + lobe * lobe_vis[:, None]
    colour = np.zeros(inp.camera.shape, np.float32)
    colour[covered] = inp.gbuffer.albedo[covered] * e / math.pi * inp.gain
    return colour


def render_shadowmap(inp: RenderInput) -> Layers:
    """Layers from one PCSS shadow map of the virtual objects lit by the SH lighting's dominant light."""
    if inp.scene is None:
        raise ValueError("shadowmap renderer: RenderInput.scene (the virtual objects' triangles) is missing")
    light = inp.light
    notes = list(light.notes)
    gb, maps = inp.gbuffer, inp.maps
    covered = gb.coverage > 0
    ratio = np.ones(inp.camera.shape, np.float32)
    if float(light.opacity.max()) <= 0.0:
        notes.append("shadowmap: no directional light in F, no shadows")
        return Layers(_virtual_colour(inp, light, np.ones(int(covered.sum())), covered), gb.coverage, ratio, notes)
    vertices, faces, _ = inp.scene.triangles()
    device = inp.grid.device
    smap = fit_shadow_map(np.asarray(vertices, np.float64), faces, light.direction, device)
    tan_a = math.tan(light.angle)
    notes.append(f"shadowmap: light {np.round(light.direction, 3).tolist()}, angle {math.degrees(light.angle):.1f} deg, "
                 f"opacity {np.round(light.opacity, 3).tolist()}, texel {smap.texel * 1000:.1f} mm")

    valid = maps.valid
    all_vis = np.zeros(valid.shape, np.float32)
    all_vis[valid] = real_light_visibility(inp.grid, maps.vertex[valid], maps.normal[valid], smap.d, smap.u, smap.v,
                                           tan_a, inp.offset, inp.ray_length, samples=REAL_SAMPLES)
    strength = np.zeros(valid.shape + (3,), np.float32)
    strength[valid], measured = measured_opacity(at_stride(inp.camera, maps)[valid], maps.vertex[valid],
                                                 maps.normal[valid], light, all_vis[valid])
    notes += measured
    sel = valid & in_footprint(smap, maps.vertex, RESOLUTION, MAX_RADIUS)

    def ratio_of(pts: np.ndarray, nrm: np.ndarray, strength_pts: np.ndarray, vis: np.ndarray) -> np.ndarray:
        return protected_ratio(shadow_lookup(smap, pts, nrm, tan_a, 0.0, max_radius=MAX_RADIUS)[0], strength_pts, vis)

    def ratio_at(pts: np.ndarray, nrm: np.ndarray) -> np.ndarray:
        """At new points (the seam): the shadow strength of the nearest stride sample (its material's)."""
        nearest = cKDTree(maps.vertex[valid]).query(pts)[1]
        return ratio_of(pts, nrm, strength[valid][nearest],
                        real_light_visibility(inp.grid, pts, nrm, smap.d, smap.u, smap.v, tan_a, inp.offset,
                                              inp.ray_length, samples=REAL_SAMPLES))

    ratio_s = np.ones(maps.vertex.shape, np.float32)
    ratio_s[sel] = ratio_of(maps.vertex[sel], maps.normal[sel], strength[sel], all_vis[sel])
    shadowed = darkened(ratio_s, sel)
    ratio = upsample_ratio(ratio_s, shadowed, maps.stride, inp.camera.shape[:2])
    refine_seam(ratio, inp, sel, ratio_at)   # inside inp.surface's window, which changed_box holds

    vpts, vnrm = gb.position[covered], gb.normal[covered]
    self_shadow, _ = shadow_lookup(smap, vpts, vnrm, tan_a, SELF_OFFSET_TEXELS * smap.texel, max_radius=MAX_RADIUS)
    vreal = real_light_visibility(inp.grid, vpts, vnrm, smap.d, smap.u, smap.v, tan_a, inp.offset, inp.ray_length,
                                  samples=REAL_SAMPLES)
    colour = _virtual_colour(inp, light, (1.0 - self_shadow) * vreal, covered)
    return Layers(colour, gb.coverage, ratio, notes, changed_box(inp, shadowed))
