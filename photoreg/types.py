"""Typed values passed between pipeline stages (plain dataclasses around numpy arrays).

Conventions (docs/conventions.md): metres, OpenCV camera frame, 4x4 float64 camera-to-world poses,
colour images RGB-ordered 8-bit sRGB, depth float32 metres with 0/NaN invalid.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels (OpenCV: pixel centres at integer coordinates)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = 1000.0  # depth-image units per metre (TUM: 5000)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the image resized by `factor` (pixel-centre convention kept)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        return Intrinsics(w, h, self.fx * factor, self.fy * factor,
                          (self.cx + 0.5) * factor - 0.5, (self.cy + 0.5) * factor - 0.5, self.depth_scale)

    def cropped(self, x0: int, y0: int, x1: int, y1: int) -> "Intrinsics":
        """Intrinsics of the sub-image of pixel columns x0..x1-1 and rows y0..y1-1."""
        return Intrinsics(x1 - x0, y1 - y0, self.fx, self.fy, self.cx - x0, self.cy - y0, self.depth_scale)

    def check(self, where: str) -> "Intrinsics":
        """self, or a ValueError naming `where` when the size or focal lengths are not positive."""
        if self.width <= 0 or self.height <= 0 or not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"{where}: invalid intrinsics {self}")
        return self

    def to_json(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "depth_scale": self.depth_scale}


@dataclass
class Frame:
    """One RGB-D frame as read from a recording."""

    index: int                      # 0-based position in the recording's frame order
    timestamp: float                # seconds
    color: np.ndarray               # HxWx3 uint8, sRGB, RGB order
    depth: np.ndarray               # HxW float32 metres, 0 or NaN = invalid
    intrinsics: Intrinsics
    pose: np.ndarray | None = None  # 4x4 float64 camera-to-world, None when unknown
    source: str = ""                # file the colour came from, for error messages
    # the depth at its own resolution (float32 metres) where it is registered to the colour at a lower one (a
    # phone's LiDAR; io.images.registered_depth scaled it up into `depth`), None where it is at the colour's: what
    # `photoreg stream` sends, the server scaling it up the same way
    depth_native: np.ndarray | None = None
    shutter: float | None = None    # seconds the shutter was open, where the camera says (the recording's
                                    # calibration, a streamed frame's `shutter`): the objects' motion blur


@dataclass
class Lighting:
    """SH coefficients of distant incident radiance, shape (3, B*B), world frame."""

    sh: np.ndarray

    @property
    def bands(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1])))


@dataclass
class SolveDiagnostics:
    """How much the per-frame lighting solve can be trusted."""

    n_samples: int = 0
    condition_number: float = float("inf")
    effective_rank: int = 0
    residual_rms: float = 0.0
    weak: bool = True
    notes: list[str] = field(default_factory=list)
    # Robust solve (photoreg.lighting.robust) and temporal filter; defaults = not computed.
    bands: int = 0                           # band count chosen for this frame (0: not reported)
    regularization: float | None = None      # relative Tikhonov strength chosen for this frame
    albedo: list = field(default_factory=list)       # per-region linear RGB albedo (scale-fixed), largest first
    inlier_fraction: float | None = None     # share of the robust weight kept after IRLS
    unobserved: list[str] = field(default_factory=list)  # axis directions whose irradiance the data leave open
    observed_fraction: float | None = None   # share of the sphere's normals whose irradiance the data determine
    heldout_residual: float | None = None    # median |relative residual| on samples kept out of the fit
    exposure_gain: float = 1.0               # frame gain removed before the solve (against the fused model)
    change_detected: bool = False            # the temporal filter saw a lighting change and restarted
    # The dominant light traced apart (photoreg.lighting.sun): direction (world, towards it), angle (radius,
    # radians), irradiance (its e per channel, F's units) and gain (share of the SH-only residual it explains).
    sun: dict | None = None
    bounce_radiance: list | None = None      # (3,) radiance the blocked directions see (the one-bounce term)
    bounce_observed: list | None = None      # (3,) colour gain on the observed radiance they see (bounce_observed)
    estimated_frame: int | None = None       # the frame whose samples gave this lighting (earlier when held)

    def to_json(self) -> dict:
        cond = self.condition_number
        out = {"n_samples": int(self.n_samples),
               "condition_number": float(cond) if np.isfinite(cond) else None,
               "effective_rank": int(self.effective_rank),
               "residual_rms": float(self.residual_rms), "weak": bool(self.weak),
               "notes": list(self.notes),
               "estimated_frame": None if self.estimated_frame is None else int(self.estimated_frame)}
        if self.bands:
            out.update({"bands": int(self.bands), "regularization": self.regularization,
                        "albedo": [[round(float(x), 5) for x in row] for row in self.albedo],
                        "inlier_fraction": self.inlier_fraction, "unobserved": list(self.unobserved),
                        "observed_fraction": self.observed_fraction, "heldout_residual": self.heldout_residual,
                        "exposure_gain": float(self.exposure_gain), "change_detected": bool(self.change_detected),
                        "sun": self.sun, "bounce_radiance": self.bounce_radiance,
                        "bounce_observed": self.bounce_observed})
        return out


@dataclass
class FrameResult:
    """Everything the pipeline produced for one frame."""

    index: int
    timestamp: float
    lighting: Lighting
    diagnostics: SolveDiagnostics
    dominant_direction: np.ndarray
    timings_ms: dict[str, float] = field(default_factory=dict)
    composite: np.ndarray | None = None  # HxWx3 linear float32, when virtual objects were inserted
    # box (x0, y0, x1, y1) outside which the composite is the frame's own colour, linearised (exactly: its 8-bit
    # sRGB comes back); None: any pixel may differ
    composite_region: tuple[int, int, int, int] | None = None
    # (4, 4) camera-to-world the frame was fused and lit from: the recording's, or the tracked one (recording.use_poses
    # false: the world is then the first frame's camera); None where it had none (not fused)
    pose: np.ndarray | None = None
    objects_in_view: bool | None = None   # whether a pixel of the composite shows an object; None: no composite
