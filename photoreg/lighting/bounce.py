"""The one-bounce terms from observed radiance: what the real surface that blocks a direction sends back.

A direction that real geometry blocks within the ray length does not see the distant light but the surface it
hits, and that surface has usually been seen by the camera: its fused luminance is in the exposure tracker's
map (photoreg.lighting.exposure; gain-corrected, like the samples). With lighting.bounce_observed the bounce
is split in two columns per sample (robust.py's extra terms, I = rho (R.F + e_obs b_obs + e_b b_unk)):
  b_obs(x) = (1/pi) sum over blocked directions whose hit point the map holds of L(hit) max(n.w, 0) dw,
  b_unk(x) = (1/pi) sum over the other blocked directions of max(n.w, 0) dw,
with the transfer's quadrature (dw = 4 pi / D over the direction set). e_obs (RGB, 0..OBSERVED_GAIN_MAX) gives
the bounce light the colour that the luminance map lacks; e_b is robust.bounce_term's one fitted radiance,
now only for the directions whose hit no sample has seen (all of them in a recording's first frame).
One radiance for every blocked direction took the light a bright wall throws for sky light and a dark one's
shadow for none; over the benchmark recordings (benchmarks/lighting_accuracy.md, rows "no observed bounce")
the observed radiance lowered the irradiance error on the generated variants, under the HDR maps and the
held-out residual on ICL-NUIM.
"""
from __future__ import annotations

import numpy as np

from ..kernels.transfer import TransferResult, observed_bounce
from .exposure import ExposureTracker
from .robust import Term, bounce_term

# Largest e_obs per channel: the observed luminance is the incident radiance, only its colour is free. Tried with
# a first version (every solve's samples traced again through the current volume and map) on the generated
# tabletop / corner / 640x480 tabletop: 1.0 gave si-RMSE 0.086 / 0.209 / 0.081, 1.2 0.084 / 0.227 / 0.077, 1.5
# 0.086 / 0.246 / 0.076, unbounded 0.096 / 0.247 (the corner, whose walls beyond the rays read as sky, takes more
# than the observed light: capped at 1 it loses least).
OBSERVED_GAIN_MAX = 1.0


def bounce_columns(tr: TransferResult, points: np.ndarray, normals: np.ndarray, dirs: np.ndarray, offset: float,
                   surface: ExposureTracker) -> np.ndarray:
    """(N, 2) columns b_obs, b_unk (module docstring) of the N samples of a transfer pass with hit distances
    (kernels.transfer.radiance_transfer(..., hit_distances=True)) along `dirs` from points + normals * offset,
    the luminance of what the rays hit taken from `surface`'s map."""
    keys, lum, _ = surface.map
    return observed_bounce(tr, points, normals, dirs, offset, surface.cell, keys, lum)


def observed_bounce_terms(columns: np.ndarray, transfer: np.ndarray, radiance: np.ndarray) -> list[Term]:
    """The solve's two bounce terms from bounce_columns' (N, 2) columns: the fitted radiance of the unseen
    blocked directions (robust.bounce_term's, bounded by the median radiance of the samples) and the observed
    radiance's colour gain e_obs in [0, OBSERVED_GAIN_MAX]."""
    return [bounce_term(transfer, radiance, blocked=columns[:, 1]),
            Term("bounce_observed", columns[:, 0], upper=np.full(3, OBSERVED_GAIN_MAX))]
