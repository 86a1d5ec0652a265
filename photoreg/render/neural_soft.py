"""`neural_soft` renderer (Sommer et al., WSCG 2023): each object's soft shadow on its ground plane comes
from a small MLP f(u, v, d) -> visibility trained on ray-traced textures (photoreg.train.neural_soft).

Per frame: the parametric light of F (photoreg.lighting.parametric) gives the light direction and the
shadow opacity. Each object stands on the side of its mesh whose plane holds the most real receivers near it
(support_axis: a recording's world has no up of its own); the receivers near the objects (at the lighting stride)
are taken into its standing frame (the mesh's frame turned so that that side's axis is +z:
neural_soft_weights.standing_rotation; the weights are made per side), and those within PLANE_TOLERANCE of its
ground plane are moved along the light direction onto
the plane, looked up in the object's texture square, and get ratio = 1 - opacity * (1 - visibility)
(visibilities of several objects multiply). Receivers off the plane keep ratio 1: the method models
ground-plane shadows only. Lights lower than the training range (theta > theta_max) are clamped to it.
The object itself is shaded as by `none` (unoccluded SH lighting). Numpy inference; no PyTorch.
Weights: user cache or committed data/weights, else trained once on first use (minutes, with progress).
"""
from __future__ import annotations

import math
import os

import numpy as np

from photoreg.lighting.parametric import receiver_opacity
from photoreg.render.composite import (Layers, RenderInput, box_distance2, changed_box, darkened, near_objects,
                                      refine_seam, upsample_ratio)
from photoreg.render.neural_soft_weights import (AXES, NeuralSoftSettings, axis_name, axis_vector, find_weights,
                                                 load_weights, standing_rotation, weights_key)
from photoreg.render.scene import VirtualObject
from photoreg.render.shadow_mlp import ShadowMLP, predict
from photoreg.render.shadow_texture import PLANE_SIDE, TextureFrame, texture_frame
from photoreg.render.voxel import render_none

PLANE_TOLERANCE = 0.05   # receivers within this share of the object's extent (+ the ray offset) of its plane
MIN_ELEVATION = 1e-3     # light direction's local z below this: the plane is unlit, no shadow to draw
SUPPORT_MIN = 16         # receivers a side's plane must hold to be the object's support (support_axis)
SUPPORT_COS = math.cos(math.radians(25.0))   # ... with their normals this close to the side's axis

_LOADED: dict[tuple, tuple[ShadowMLP, TextureFrame]] = {}   # per process: mesh file state -> net, frame


def _rotation_scale(obj: VirtualObject) -> tuple[np.ndarray, float]:
    """The object's rotation (3, 3, mesh to world) and uniform scale."""
    scale = float(np.cbrt(np.linalg.det(obj.transform[:3, :3])))
    return obj.transform[:3, :3] / scale, scale


def plane_tolerance(obj: VirtualObject, offset: float) -> float:
    """Metres from its ground plane within which a receiver counts as on it: PLANE_TOLERANCE of the object's extent
    plus the ray offset."""
    return PLANE_TOLERANCE * float((obj.vertices.max(0) - obj.vertices.min(0)).max()) + offset


def support_axis(obj: VirtualObject, points: np.ndarray, normals: np.ndarray, tolerance: float) -> np.ndarray | None:
    """The signed unit axis (3,) of the mesh's own frame that the object stands on: of its six sides, the one whose
    plane (through the mesh's lowest point along the axis turned into the world) holds the most of the real
    receivers (N, 3) within `tolerance` metres with their normals (N, 3) facing the object (within 25 degrees of
    that axis); None where no side holds SUPPORT_MIN of them."""
    rot, _ = _rotation_scale(obj)
    best, most = None, SUPPORT_MIN - 1
    for axis in map(axis_vector, AXES):
        w = rot @ axis
        on = np.abs(points @ w - (obj.vertices @ w).min()) <= tolerance
        count = np.count_nonzero(on & (normals @ w >= SUPPORT_COS))
        if count > most:
            best, most = axis, count
    return best


def object_net(obj: VirtualObject, up: np.ndarray, settings: NeuralSoftSettings = NeuralSoftSettings()
               ) -> tuple[ShadowMLP, TextureFrame]:
    """The net and texture frame of the object standing on its side `up` (support_axis): loaded once per process
    (keyed by the mesh file's path, size and mtime and the side), from the cache or the committed weights, else
    trained now and cached."""
    st = os.stat(obj.source)
    memo = (os.path.abspath(obj.source), st.st_size, st.st_mtime_ns, settings, tuple(up))
    if memo not in _LOADED:
        standing = obj.local_vertices() @ standing_rotation(up).T
        path = find_weights(weights_key(obj.source, settings, up))
        if path is None:
            from photoreg.train.neural_soft import stderr_progress, train_mesh

            stderr_progress(f"no weights for {obj.source} standing on its {axis_name(up)} side: training them now "
                            "(once; cached afterwards)")
            path = train_mesh(obj.source, standing, obj.faces, settings, up=up)
        _LOADED[memo] = (load_weights(path)[0], texture_frame(standing))
    return _LOADED[memo]


def plane_visibility(obj: VirtualObject, points: np.ndarray, light_dir: np.ndarray, tolerance: float, up: np.ndarray,
                     settings: NeuralSoftSettings = NeuralSoftSettings()) -> tuple[np.ndarray, list[str]]:
    """Visibility (N,) in [0, 1] of the light at world points (N, 3) under `obj`'s shadow, the object standing on
    its side `up` (1 where the texture does not reach: off its plane by more than `tolerance` metres, or outside
    the square)."""
    net, frame = object_net(obj, up, settings)
    rot, scale = _rotation_scale(obj)
    rot = rot @ standing_rotation(up).T                          # standing frame to world
    d = rot.T @ np.asarray(light_dir, np.float64)
    vis = np.ones(len(points), np.float32)
    notes: list[str] = []
    if d[2] < MIN_ELEVATION:
        return vis, [f"{obj.source}: light at or below its ground plane: no plane shadow"]
    theta_max = math.radians(settings.theta_max_deg)
    if math.acos(min(d[2], 1.0)) > theta_max:
        phi = math.atan2(d[1], d[0])
        d = np.array([math.sin(theta_max) * math.cos(phi), math.sin(theta_max) * math.sin(phi), math.cos(theta_max)])
        notes.append(f"{obj.source}: light lower than the trained {settings.theta_max_deg:g} deg from zenith: clamped")
    local = (np.asarray(points, np.float64) - obj.transform[:3, 3]) @ rot / scale
    h = local[:, 2] - frame.z0
    on_plane = np.abs(h) <= tolerance / scale
    plane = local - (h / d[2])[:, None] * d                      # along the light onto the plane
    uv = frame.uv(plane)
    use = on_plane & np.all((uv >= 0.0) & (uv <= 1.0), axis=1)
    vis[use] = predict(net, uv[use], d)
    return vis, notes


def render_neural_soft(inp: RenderInput) -> Layers:
    """Object as `none`; real pixels near the objects darkened by the MLP shadow textures (module doc)."""
    if inp.scene is None:
        raise ValueError("neural_soft: RenderInput.scene is missing (the renderer works per object)")
    base = render_none(inp)
    light = inp.light
    notes = list(light.notes)
    if float(light.opacity.max()) <= 0.0:   # nothing to shadow: no net to load or train
        base.notes += notes + ["neural_soft: no directional light in F, no shadows"]
        return base
    maps = inp.maps
    extent = float((inp.bounds[1] - inp.bounds[0]).max())
    near = near_objects(maps, box_distance2(maps, inp.bounds), PLANE_SIDE * extent)
    standing = []   # (object, its plane's tolerance, the side it stands on)
    for k, obj in enumerate(inp.scene.objects):
        tol = plane_tolerance(obj, inp.offset)
        up = support_axis(obj, maps.vertex[near], maps.normal[near], tol)
        if up is None:
            notes.append(f"neural_soft: object {k} ({obj.source}): no real surface seen along a side of it to stand on "
                         "(within 25 degrees of a side's axis): no plane shadow")
        else:
            standing.append((obj, tol, up))
            notes.append(f"neural_soft: object {k} ({obj.source}) stands on its {axis_name(up)} side")

    def ratio_at(pts: np.ndarray, normals: np.ndarray) -> np.ndarray:
        vis = np.ones(len(pts), np.float32)
        for obj, tol, up in standing:
            v, n = plane_visibility(obj, pts, light.direction, tol, up)
            vis *= v
            notes.extend(x for x in n if x not in notes)
        return 1.0 - receiver_opacity(light, normals) * (1.0 - vis)[:, None]

    ratio_s = np.ones(maps.vertex.shape, np.float32)
    ratio_s[near] = ratio_at(maps.vertex[near], maps.normal[near])
    shadowed = darkened(ratio_s, near)
    ratio = upsample_ratio(ratio_s, shadowed, maps.stride, inp.camera.shape[:2])
    refine_seam(ratio, inp, near, ratio_at)   # inside inp.surface's window, which changed_box holds
    return Layers(base.colour, base.alpha, ratio, base.notes + notes, changed_box(inp, shadowed))
