"""Renderers of the registry: `voxel` (differential rendering with voxel visibility, Gruber et al. 2012)
and `none` (the object shaded by the unoccluded lighting, no shadows either way)."""
from __future__ import annotations

import numpy as np

from photoreg.kernels.transfer import any_blocked, shaded_pass
from photoreg.lighting import sh
from photoreg.lighting.parametric import ParametricLight, cone_directions
from photoreg.render.composite import (Layers, RenderInput, at_stride, bounce, box_distance2, changed_box, darkened,
                                      near_objects, seam_band, set_seam, shade, shadow_ratio, upsample_ratio)


CLOSE = 0.5  # the real surface within this share of the objects' size is what their blocked rays see


def _covered(inp: RenderInput) -> np.ndarray:
    """Which pixels of the G-buffer's window (GBuffer.box) show a virtual surface."""
    return inp.gbuffer.coverage[inp.gbuffer.box] > 0


def _object_colour(inp: RenderInput, shading: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """albedo * shading (camera units, no albedo), float32 (N, 3), at the `covered` pixels of the G-buffer's
    window (_covered)."""
    return (inp.gbuffer.window_albedo[covered] * np.maximum(shading, 0.0)).astype(np.float32)


def _virtual_colour(inp: RenderInput, values: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """The frame's colour layer: _object_colour's `values` at the `covered` pixels, zero elsewhere."""
    colour = np.zeros(inp.camera.shape, np.float32)
    colour[inp.gbuffer.box][covered] = values
    return colour


def pixels(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of a mask's pixels in row-major order: indexing with them gathers what the mask would, at a third
    of the time of a boolean mask over full-resolution maps (stride 1 at 640x480: 0.8 against 2.7 ms)."""
    return np.divmod(np.flatnonzero(mask), mask.shape[1])


def real_radiance(inp: RenderInput, rows: np.ndarray, cols: np.ndarray, ratio: np.ndarray | None = None) -> np.ndarray:
    """Mean camera radiance (3,) of the real surface at the stride pixels (rows, cols), times the shadow ratio
    (stride maps, (h, w, 3)) there when given: what a blocked ray sees (bounce)."""
    if len(rows) == 0:
        return np.zeros(3, np.float32)
    radiance = at_stride(inp.camera, inp.maps)[rows, cols]
    return (radiance if ratio is None else radiance * ratio[rows, cols]).mean(axis=0)


def _pass(inp: RenderInput, F: np.ndarray, light: ParametricLight | None, cone: np.ndarray | None,
          points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The ray pass at points (kernels.transfer.shaded_pass, (N, 8) rows): the shading by F's SH under R_TR and
    R_TRV, plus the light's disc (`cone`: its rays), gain * c/pi * mean over the disc's rays of V max(n.w, 0)
    (composite units), and the SH set's blocked shares. Every point's rays are its own: a pass over several point sets
    at once gives each set what its own pass would."""
    dirs, Y = inp.directions(sh.bands_of(F.shape[1]))
    weighted = np.full((len(dirs), 4), 4.0 / len(dirs))   # the SH set's dw / pi
    weighted[:, :3] *= inp.gain * (Y @ F.T)
    if light is not None:
        disc = np.zeros((len(cone), 4))
        disc[:, :3] = inp.gain * light.colour / (np.pi * len(cone))
        weighted, dirs = np.concatenate([weighted, disc]), np.concatenate([dirs, cone])
    return shaded_pass(inp.grid, inp.virtual, points, normals, dirs, weighted, inp.offset, inp.ray_length)


def render_voxel(inp: RenderInput) -> Layers:
    """R_TR / R_TRV in one ray pass at the real surface near the objects (lighting stride, interpolated
    back; at full resolution along the objects' silhouettes, composite.seam_band), and R_TRV at the
    virtual pixels with real geometry occluding (real shadows on the object); one ambient bounce each way
    (composite.bounce). With light_rays > 0 the dominant light is split out of F
    (photoreg.lighting.parametric) and traced as a disc of that many rays: sharp shadows that a few SH bands
    cannot hold; the residual SH keeps the rest."""
    maps, gb = inp.maps, inp.gbuffer
    F, light, notes = inp.F, None, []
    if inp.light_rays > 0:
        light = inp.light
        if light.lobe_share > 0:
            F = light.residual
        else:
            light = None
            notes.append("no directional light in F: SH transfer only")
    cone = None if light is None else cone_directions(light.direction, light.angle, inp.light_rays).astype(np.float32)
    distance2 = box_distance2(maps, inp.bounds)
    near = near_objects(maps, distance2, inp.ray_length)
    rows, cols = pixels(near)
    l_real = real_radiance(inp, rows, cols)
    covered = _covered(inp)
    band = seam_band(inp, near)
    # The real points whose shadow ratio is computed: the stride samples near the objects and the seam's pixels.
    # Only those with a ray the objects block can change (R_TRV = R_TR elsewhere, ratio exactly 1): a cheap
    # march of the small virtual grid along every ray of the passes finds them, and the real grid's march, the
    # expensive one, runs at those alone (TUM with the bunny: 864 of the 2090 stride samples near it).
    n_near = len(rows)
    points, normals = maps.vertex[rows, cols], maps.normal[rows, cols]
    if band is not None:
        points = np.concatenate([points, inp.surface.vertex[band]])
        normals = np.concatenate([normals, inp.surface.normal[band]])
    rays = inp.directions(sh.bands_of(F.shape[1]))[0]
    rays = rays if light is None else np.concatenate([rays, cone])
    hit = np.flatnonzero(any_blocked(inp.virtual, points, normals, rays, inp.offset, inp.ray_length))
    # One ray pass for the object's pixels and the shadowed real points (few launches: each costs host time)
    n_obj = int(covered.sum())
    passes = _pass(inp, F, light, cone, np.concatenate([gb.window_position[covered], points[hit]]),
                   np.concatenate([gb.window_normal[covered], normals[hit]]))
    on_object = passes[:n_obj]
    values = _object_colour(inp, bounce(on_object, l_real, l_real)[1], covered)
    l_virt = values.mean(axis=0) if n_obj else np.zeros(3, np.float32)

    # shadow_ratio's eps guard averages over the shadowed points of each set (stride samples, seam) apart
    ratio_pts = np.ones((len(points), 3), np.float32)
    split = int(np.searchsorted(hit, n_near))   # hit is sorted: the stride samples' rows come first
    for lo, hi in ((0, split), (split, len(hit))):
        if hi > lo:
            ratio_pts[hit[lo:hi]] = shadow_ratio(*bounce(passes[n_obj + lo:n_obj + hi], l_real, l_virt))
    ratio_s = np.ones(maps.vertex.shape, np.float32)
    ratio_s[rows, cols] = ratio_pts[:n_near]
    shadowed = darkened(ratio_s, near)
    ratio = upsample_ratio(ratio_s, shadowed, maps.stride, inp.camera.shape[:2])
    if band is not None:
        set_seam(ratio, inp, band, ratio_pts[n_near:])
    # What the object's blocked rays see is the real surface next to it, darkened by the object's own
    # shadow, not the mean of the whole neighbourhood: re-shade it with that (demo frames 10 and 20 against
    # the path tracer: the object's darkest third 24% -> 14% too bright at frame 10, the whole object at
    # most 10.9% -> 7.6% off per channel; composite si-RMSE, mean of the two frames, 0.071 -> 0.064).
    close = near_objects(maps, distance2, CLOSE * float(np.max(inp.bounds[1] - inp.bounds[0])))
    if close.any():
        l_close = real_radiance(inp, *pixels(close), ratio_s)
        values = _object_colour(inp, bounce(on_object, l_close, l_close)[1], covered)
    return Layers(_virtual_colour(inp, values, covered), gb.coverage, ratio, notes, changed_box(inp, shadowed))


def render_none(inp: RenderInput) -> Layers:
    """The object lit by the unoccluded lighting; real pixels unchanged (the 'no shadow' baseline)."""
    covered = _covered(inp)
    transfer = sh.unoccluded_transfer(inp.gbuffer.window_normal[covered], sh.bands_of(inp.F.shape[1]))
    return Layers(_virtual_colour(inp, _object_colour(inp, inp.gain * shade(inp.F, transfer), covered), covered),
                  inp.gbuffer.coverage,
                  np.ones(inp.camera.shape, np.float32), region=inp.gbuffer.window)
