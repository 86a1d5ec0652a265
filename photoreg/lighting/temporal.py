"""Temporal filter of the SH lighting: a Kalman filter in information form, with change detection.

State: F (3, K) at the filter's band count, per channel a precision matrix (K, K). Each frame:
  predict   P <- P + Q, Q = process_noise * (K / trace(J)) * I: a random walk whose step is a fixed
            share of the frame's measurement variance, so the smoothing does not depend on the data's
            scale (steady-state gain about sqrt(process_noise) in well-observed directions); on a frame
            that reaches a new view (`update(sol, new_view=True)`) the prior's precision is first scaled by
            new_view_share: with the history of samples (photoreg.lighting.history) the frame's solve
            already holds the earlier views' samples, so a prior built from those views' solves counts
            them twice and holds the estimate back while the views add up (generated 12-frame tabletop
            orbit: median direction error 12.6 -> 9.5 degrees at 0.3, benchmarks/lighting_accuracy.md);
  measure   the frame's solve (photoreg.lighting.robust.solve, regularised toward the prediction)
            gives z and its precision J = (G + lam I) / sigma^2 at the frame's band count; bands the
            frame did not fit get no information, so they keep the prediction; where the solve fell back to
            band 0 (too few resolved combinations), z is the prediction moved by the solve's resolution matrix
            toward the fit that J describes (Solution.measured), so what the frame does not resolve keeps the
            prediction;
  detect    ratio = SSE(prediction) / SSE(z) on the frame's own samples and weights: how much worse
            the predicted lighting explains this frame than its own fit (with a history of samples, on
            the current view's rows alone: Solution.current_system; over all rows two thirds of a switch
            frame's samples were lit by the old light and the ratio stayed at the threshold). Model
            misfit keeps this well above 1 on a static scene (1.3-4 measured on the synthetic
            recordings), so the test is relative: above (1 + change_threshold) * the median ratio of
            the last HISTORY frames the light changed (switched on or off): the filter forgets and
            restarts from z, so it follows within a frame or two instead of averaging the old light in;
  update    Lambda = Lambda_p + J, x = Lambda^-1 (Lambda_p x_p + J z).
Directions the data never observe (a single plane) stay at the prediction.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from . import sh
from .robust import Solution

HISTORY = 10  # frames of fit ratios behind the change test's baseline
# A traced light whose direction moves more than this from one frame to the next is another light: its irradiance
# filter starts again (two coarse spacings of the light search, photoreg.lighting.sun; a held light's refinements
# move it by at most about one and a third)
LIGHT_SWITCH_DEG = 25.0


@dataclass
class FilterConfig:
    """Settings of LightingFilter (module docstring)."""

    process_noise: float = 0.02
    change_threshold: float = 1.0
    new_view_share: float = 0.3

    def __post_init__(self) -> None:
        if not (self.process_noise >= 0 and self.change_threshold > 0 and 0 < self.new_view_share <= 1):
            raise ValueError("process_noise must be >= 0, change_threshold > 0 and new_view_share in (0, 1]")


def _embed(a: np.ndarray, k: int) -> np.ndarray:
    """(3, k') vector or (3, k', k') matrix zero-padded (or cut) to k coefficients."""
    a = np.asarray(a, dtype=np.float64)
    out = np.zeros((3,) + (k,) * (a.ndim - 1))
    kk = min(k, a.shape[1])
    if a.ndim == 2:
        out[:, :kk] = a[:, :kk]
    else:
        out[:, :kk, :kk] = a[:, :kk, :kk]
    return out


class LightingFilter:
    """Per-recording filter state; `prediction()` is the prior for the next solve, `update()` fuses it."""

    def __init__(self, bands: int, cfg: FilterConfig | None = None):
        self.cfg = cfg or FilterConfig()
        self.k = bands * bands
        self.x: np.ndarray | None = None          # (3, K)
        self.precision: np.ndarray | None = None  # (3, K, K)
        self.ratios: deque = deque(maxlen=HISTORY)  # fit ratios of recent frames without a change
        self.light: np.ndarray | None = None      # (3,) the traced light's filtered irradiance (irradiance())
        self.light_direction: np.ndarray | None = None   # (3,) that light's direction at the last frame

    def prediction(self) -> np.ndarray | None:
        """The current estimate (3, K), None before the first frame with samples."""
        return None if self.x is None else self.x.copy()

    def update(self, sol: Solution, new_view: bool = False) -> tuple[np.ndarray, bool]:
        """Fuse a frame's solution (seen from a new view: the prior counts new_view_share of its precision);
        returns the filtered lighting at the frame's band count and whether a lighting change was detected
        (the filter restarted)."""
        z = np.asarray(sol.lighting.sh, dtype=np.float64)
        k_frame = z.shape[1]
        system = sol.system
        if system is None:  # nothing measured: the estimate stands (or the solve's fallback)
            return (sh.truncate(self.x, sh.bands_of(k_frame)) if self.x is not None else z), False
        if sol.measured is not None and self.x is not None:
            # The solve fell back to band 0 (too few resolved combinations), which disagrees with the data wherever
            # they resolve more than one plane's irradiance (split_albedo with the depth filter and the normal
            # smoothing: the ambient jumped 2.5x between frames). The filter fuses what the frame resolves of the fit
            # that `system` describes: the prediction moved by the solve's resolution matrix (G + lam I)^-1 G,
            # so the directions it does not resolve keep the prediction (not the fallback's nor the fit's prior).
            k_sys = system.G.shape[1]
            x_p = _embed(self.x, k_sys)
            resolution = np.linalg.pinv(system.G + system.lam[:, None, None] * np.eye(k_sys)) @ system.G
            z = x_p + np.einsum("cij,cj->ci", resolution, _embed(sol.measured, k_sys) - x_p)
        J = _embed(system.precision(), self.k)
        z_full = _embed(z, self.k)
        if self.x is None:
            self.x, self.precision = z_full, J
            return z, False
        x_p = self.x
        if new_view:
            self.precision = self.precision * self.cfg.new_view_share
        eye = np.eye(self.k)
        tr = np.trace(J, axis1=1, axis2=2)
        q = self.cfg.process_noise * self.k / np.where(tr > 0, tr, 1.0)
        ridge = 1e-12 * np.trace(self.precision, axis1=1, axis2=2)[:, None, None] / self.k  # keeps inv() finite
        L_p = np.linalg.inv(np.linalg.inv(self.precision + ridge * eye) + q[:, None, None] * eye)
        check = sol.current_system if sol.current_system is not None else system
        floor = 1e-12 * max(float(check.c0.sum()), 1e-300)
        ratio = (check.sse(x_p) + floor) / (max(check.sse(z), 0.0) + floor)
        baseline = float(np.median(self.ratios)) if self.ratios else 1.0
        if ratio > (1.0 + self.cfg.change_threshold) * max(baseline, 1.0):
            self.x, self.precision = z_full, J
            self.ratios.clear()
            return z, True
        self.ratios.append(ratio)
        L = L_p + J
        rhs = np.einsum("cij,cj->ci", L_p, x_p) + np.einsum("cij,cj->ci", J, z_full)
        x = np.linalg.solve(L, rhs[..., None])[..., 0]
        if not np.isfinite(x).all():  # singular update (only with degenerate inputs): keep the frame's fit
            x, L = z_full, J
        self.x, self.precision = x, L
        return x[:, :k_frame].copy(), False

    def irradiance(self, e: np.ndarray | None, restart: bool, direction: np.ndarray | None = None) -> np.ndarray | None:
        """The traced light's irradiance (RGB) filtered across frames, from the frame's `e` (None: no light held,
        which forgets it) of the light at `direction` (unit, world): smoothed at the steady-state gain of a random
        walk whose step is process_noise of the measurement's variance, the SH's gain in well-observed directions
        (0.13 at the default 0.02); the frame's own value where no light was held before, the SH filter restarted
        (`restart`: a change) or the light is another (its direction moved by more than LIGHT_SWITCH_DEG). Each frame's
        solve splits the light between the traced light and the SH differently; the SH is filtered, so a renderer
        that drew the light's disc with the frame's own irradiance (its sharp shadows) and the rest from the
        filtered SH less that light made shadows that pulsed with the split (the demo: 2.46-2.92, jumps of 10%)."""
        if e is None:
            self.light = self.light_direction = None
            return None
        e = np.asarray(e, dtype=np.float64)
        moved = direction is not None and self.light_direction is not None and (
            float(np.dot(direction, self.light_direction)) < math.cos(math.radians(LIGHT_SWITCH_DEG)))
        if direction is not None:
            self.light_direction = np.asarray(direction, dtype=np.float64).copy()
        if self.light is None or restart or moved:
            self.light = e.copy()
        else:
            q = self.cfg.process_noise
            self.light = self.light + 0.5 * (math.sqrt(q * q + 4.0 * q) - q) * (e - self.light)
        return self.light.copy()
