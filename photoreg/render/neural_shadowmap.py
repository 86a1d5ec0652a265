"""`neural_shadowmap` renderer (Datta et al., SIGGRAPH 2022): a compact U-Net maps shadow-map buffers to the
visibility of the SH lighting's dominant light, run through OpenCV's dnn module (no PyTorch at run time).

Per frame: the parametric light of F (photoreg.lighting.parametric, in the direction of F's band 1 as
render_voxel takes it), the orthographic shadow map of the
virtual objects from its direction (photoreg.render.shadowmap.fit_shadow_map), the buffers at the lighting
stride (photoreg.render.shadow_buffers), the network's visibility v in [0, 1], kept where the shadow map puts a
virtual blocker between the receiver and the light and 1 elsewhere (the network's v strays below 1 far from any
blocker: TUM's whole desk darkened by up to 12%; a mask dilated by 1-6 stride samples scored worse on the demo). Real
pixels get
    ratio = 1 - o(n) (1 - v)      (o: the light's share of the irradiance at the receiver, receiver_opacity),
interpolated to full resolution like the voxel renderer's ratio; virtual pixels get render_none's colour
(albedo * gain * F.R unoccluded) times the same factor (self-shadowing). The network was trained on
exactly this formula against the voxel renderer (photoreg.train.shadow_train; data/neural_shadowmap/README.md).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from photoreg.lighting import sh
from photoreg.lighting.parametric import receiver_opacity
from photoreg.render.composite import Layers, RenderInput, changed_box, shade, upsample_ratio
from photoreg.render.shadow_buffers import SM_RESOLUTION, shadow_buffers
from photoreg.render.shadowmap import fit_shadow_map

WEIGHTS = Path(__file__).resolve().parents[2] / "data" / "neural_shadowmap" / "shadow_unet.onnx"
MULTIPLE = 32   # the network's input sides must be multiples of this (space-to-depth, 4 poolings)
UNCHANGED = 1e-3  # ratios above 1 - this are left at 1 (no interpolation box needed there)
FILL_RADIUS = 2   # stride samples: reach of the real ratio into samples hidden by the objects
BLOCKED_GAP = 1e-3   # metres: a receiver whose emitter lies nearer the light than itself by more is blocked

_nets: dict[str, cv2.dnn.Net] = {}


def load_net(path: str | Path = WEIGHTS) -> cv2.dnn.Net:
    """The ONNX network through cv2.dnn, loaded once per path; FileNotFoundError naming a missing file."""
    key = str(Path(path).resolve())
    if key not in _nets:
        if not Path(path).is_file():
            raise FileNotFoundError(f"{path}: neural shadow-map weights not found (train them: "
                                    f"data/neural_shadowmap/README.md)")
        net = cv2.dnn.readNetFromONNX(key)
        net.setPreferableBackend(cv2.dnn.DNN_BACKEND_OPENCV)
        net.setPreferableTarget(cv2.dnn.DNN_TARGET_CPU)
        _nets[key] = net
    return _nets[key]


def predict_visibility(data: np.ndarray, net: cv2.dnn.Net | None = None) -> np.ndarray:
    """Visibility (h, w) float32 in [0, 1] of buffers (C, h, w); zero-padded (no receiver) to MULTIPLE."""
    net = load_net() if net is None else net
    c, h, w = data.shape
    H, W = -(-h // MULTIPLE) * MULTIPLE, -(-w // MULTIPLE) * MULTIPLE
    x = np.zeros((1, c, H, W), np.float32)
    x[0, :, :h, :w] = np.nan_to_num(data, nan=0.0, posinf=0.0, neginf=0.0)
    net.setInput(x)
    return np.clip(net.forward()[0, 0, :h, :w], 0.0, 1.0).astype(np.float32)


def _fill_from_real(ratio_s: np.ndarray, real: np.ndarray, behind: np.ndarray) -> np.ndarray:
    """Ratio at stride samples where the virtual surface hides the real one (`behind` & ~real): the mean of
    the real samples within FILL_RADIUS, so that interpolation at object edges (partly covered pixels)
    sees the shadow beside the object rather than 1. The voxel renderer has the hidden real surface's
    own ratio there; the network only sees the virtual surface."""
    hidden = behind & ~real
    if not hidden.any():
        return ratio_s.astype(np.float32)
    k = (2 * FILL_RADIUS + 1,) * 2
    w = cv2.boxFilter(real.astype(np.float32), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    acc = cv2.boxFilter(np.where(real[..., None], ratio_s, 0.0).astype(np.float32), -1, k, normalize=False,
                        borderType=cv2.BORDER_CONSTANT)
    out = ratio_s.astype(np.float32).copy()
    fill = hidden & (w > 0)
    out[fill] = acc[fill] / w[fill, None]
    return out


def render_neural_shadowmap(inp: RenderInput) -> Layers:
    """Layers from the network's visibility of the dominant light (module docstring)."""
    if inp.scene is None:
        raise ValueError("neural_shadowmap renderer: RenderInput.scene (the virtual objects) is missing")
    gb, maps, s = inp.gbuffer, inp.maps, inp.maps.stride
    H, W = inp.camera.shape[:2]
    covered = gb.coverage > 0
    colour = np.zeros(inp.camera.shape, np.float32)
    unshadowed = sh.unoccluded_transfer(gb.normal[covered], sh.bands_of(inp.F.shape[1]))
    colour[covered] = gb.albedo[covered] * np.maximum(shade(inp.F, unshadowed), 0.0) * inp.gain
    light = inp.light
    notes = list(light.notes)
    if float(light.opacity.max()) <= 0.0:
        notes.append("neural_shadowmap: no directional light in F, no shadows")
        return Layers(colour, gb.coverage, np.ones(inp.camera.shape, np.float32), notes, gb.window)
    verts, faces, _ = inp.scene.triangles()
    smap = fit_shadow_map(verts, faces, light.direction, inp.grid.device, SM_RESOLUTION)
    buf = shadow_buffers(maps, gb, light, smap)
    vis = predict_visibility(buf.data)
    vis[~(buf.valid & (buf.data[5] - buf.data[4] > BLOCKED_GAP))] = 1.0   # the network's v only where a blocker is
    h, w = vis.shape
    factor = np.ones((h, w, 3), np.float32)
    factor[buf.valid] = 1.0 - receiver_opacity(light, buf.normal[buf.valid]) * (1.0 - vis[buf.valid, None])
    real = buf.valid & ~buf.virtual
    ratio_s = _fill_from_real(np.where(real[..., None], factor, 1.0), real, maps.valid)
    shadowed = maps.valid & (ratio_s.min(-1) < 1.0 - UNCHANGED)
    ratio = upsample_ratio(ratio_s, shadowed, s, (H, W))
    if covered.any():
        full = upsample_ratio(factor, buf.valid, s, (H, W))
        colour[covered] *= full[covered]
    return Layers(colour, gb.coverage, ratio, notes, changed_box(inp, shadowed))   # the composite blends that box
