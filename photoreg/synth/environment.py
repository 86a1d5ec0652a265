"""Environment lighting for the generator: HDR or procedural lat-long maps, the emitter rotation, GT SH.

Mitsuba's `envmap` (checked against renders, see tests/test_synth.py) maps a world direction w to
local v = R^T w (R the emitter's to_world), u = atan2(v.x, -v.z) / (2 pi), t = acos(v.y) / pi, and
interpolates bilinearly between texel nodes at u = (j + 0.5) / W and t = i / (H - 1): rows sit on the
poles, not at pixel centres. The ground-truth SH integrate exactly that function, so they describe
the light Mitsuba renders with.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..io.images import read_hdr
from ..lighting.sh import project

# Emitter-local +y (the map's "up") -> world +z; local +z -> world -y; local +x stays +x.
UP_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def emitter_rotation(yaw_deg: float) -> np.ndarray:
    """to_world rotation of the envmap: map up to world +z, then `yaw_deg` about world +z."""
    return Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix() @ UP_TO_Z


def node_directions(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Emitter-local unit directions of the texel nodes (H, W, 3) and per-row solid-angle weights (H,).

    Weights integrate Mitsuba's bilinear reconstruction exactly for the integral of radiance: in phi a
    periodic trapezoid (2 pi / W), in theta the integral of each row's hat function times sin(theta).
    """
    theta = np.pi * np.arange(height) / (height - 1)
    phi = 2.0 * np.pi * (np.arange(width) + 0.5) / width
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    d = np.stack([st * np.sin(phi), np.broadcast_to(ct, (height, width)), -st * np.cos(phi)], axis=-1)
    step = np.pi / (height - 1)
    w_theta = np.sin(theta) * 2.0 * (1.0 - math.cos(step)) / step
    w_theta[[0, -1]] = 1.0 - math.sin(step) / step
    return d, w_theta * (2.0 * np.pi / width)


def environment_sh(image: np.ndarray, rotation: np.ndarray, bands: int = 8, rows_per_chunk: int = 32) -> np.ndarray:
    """SH (3, bands^2) of the lat-long `image` as the envmap with to_world `rotation` lights world directions."""
    h, w, _ = image.shape
    dirs, weights = node_directions(h, w)
    sh = np.zeros((3, bands * bands))
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        world = dirs[r0:r1].reshape(-1, 3) @ rotation.T
        wts = np.repeat(weights[r0:r1], w)
        sh += project(world, image[r0:r1].reshape(-1, 3), wts, bands)
    return sh


@dataclass(frozen=True)
class Sun:
    """A sun disc: direction (elevation above the horizon, azimuth from +x towards +y, before yaw),
    angular diameter, irradiance at normal incidence and colour (linear RGB multiplier)."""

    elevation_deg: float = 45.0
    azimuth_deg: float = 30.0
    diameter_deg: float = 4.0
    irradiance: float = 4.0
    colour: tuple[float, float, float] = (1.0, 0.92, 0.8)

    def direction(self) -> np.ndarray:
        el, az = math.radians(self.elevation_deg), math.radians(self.azimuth_deg)
        return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


@dataclass(frozen=True)
class ProceduralSky:
    """Sky gradient (zenith to horizon), uniform ground below a soft horizon, and sun discs.

    Defined in the map's upright frame (z up); `emitter_rotation(yaw)` turns it into the world.
    """

    zenith: tuple[float, float, float] = (0.25, 0.45, 0.9)
    horizon: tuple[float, float, float] = (0.75, 0.8, 0.9)
    ground: tuple[float, float, float] = (0.3, 0.27, 0.24)
    suns: tuple[Sun, ...] = field(default_factory=lambda: (Sun(),))
    width: int = 1024
    height: int = 512

    def to_json(self) -> dict:
        return asdict(self)

    def bake(self) -> np.ndarray:
        """The lat-long float32 image (height, width, 3) Mitsuba uses, sampled at its texel nodes."""
        local, _ = node_directions(self.height, self.width)
        d = local @ UP_TO_Z.T  # upright-frame directions (z up)
        z = d[..., 2:3]
        sky = np.asarray(self.horizon) + (np.asarray(self.zenith) - np.asarray(self.horizon)) * np.sqrt(np.clip(z, 0, 1))
        s = np.clip((z + 0.03) / 0.06, 0.0, 1.0)
        blend = s * s * (3.0 - 2.0 * s)  # smoothstep over about +-2 degrees around the horizon
        img = blend * sky + (1.0 - blend) * np.asarray(self.ground)
        texel = math.pi / (self.height - 1)
        for sun in self.suns:
            radius = math.radians(sun.diameter_deg) / 2.0
            solid_angle = 2.0 * math.pi * (1.0 - math.cos(radius))
            angle = np.arccos(np.clip(d @ sun.direction(), -1.0, 1.0))
            coverage = np.clip((radius - angle) / texel + 0.5, 0.0, 1.0)  # one-texel soft edge
            img = img + coverage[..., None] * (sun.irradiance / solid_angle) * np.asarray(sun.colour)
        return img.astype(np.float32)


def load_environment(env: str, sky: ProceduralSky | None = None) -> tuple[np.ndarray, dict]:
    """('procedural' | path to .hdr/.exr) -> (lat-long float32 image, description for scene.json)."""
    if env == "procedural":
        sky = sky or ProceduralSky()
        return sky.bake(), {"type": "procedural", **sky.to_json()}
    path = Path(env)
    if not path.is_file():
        raise FileNotFoundError(f"--env {env}: no such HDR file (give a .hdr/.exr path or 'procedural')")
    img = read_hdr(path)
    if img.ndim != 3 or img.shape[0] < 3 or img.shape[1] < 2 or not np.all(np.isfinite(img)):
        raise ValueError(f"--env {env}: not a finite lat-long RGB image (shape {img.shape})")
    return np.maximum(img, 0.0), {"type": "hdr", "path": str(path.resolve()), "width": img.shape[1], "height": img.shape[0]}
