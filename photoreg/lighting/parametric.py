"""A parametric light from SH lighting: one directional lobe (a uniform disc) plus a residual ambient.

Shadow renderers that work with one light (shadow maps, neural shadows) need a direction, a light
colour, an ambient colour and a shadow opacity; this module derives them from F (3, B*B) (DESIGN.md).

Model. A disc (spherical cap) of angular radius a and constant radiance around the unit direction d,
with integrated radiance c (radiance x solid angle, so c is the irradiance it delivers at normal
incidence up to the cap's cosine falloff; same units as F), has the SH coefficients
    F_lm = c g_l(a) Y_lm(d),   g_l(a) = (P_{l-1}(x) - P_{l+1}(x)) / ((2l + 1)(1 - x)),  x = cos a,
(addition theorem; g_0 = 1, g_1 = (1 + x)/2, g_l -> 1 as a -> 0: a delta). The fit works on bands
l >= l0 (l0 = fit_from(B): 1, or 2 when B >= 4), where a smooth sky carries little energy; a sky gradient
lies in band 1, and fitting it too made a sun under a linear sky 15% too bright and twice too wide:
  - direction d and radius a: maximise the luminance correlation sum_{l>=l0} g_l sum_m F_lm Y_lm(d), i.e.
    minimise the least-squares residual over those bands (sum_m Y_lm(d)^2 = (2l+1)/(4 pi) does not depend
    on d); a is chosen from the band energy falloff on a grid clamped to [ANGLE_MIN, ANGLE_MAX];
  - colour per channel k: c_k = sum_l g_l p_lk / sum_l g_l^2 (2l+1)/(4 pi), p_lk = sum_m F_k,lm Y_lm(d),
    clamped at 0 (least squares on bands >= l0);
  - the residual F - lobe is the ambient; `ambient` is its irradiance at the normal facing the light.
Opacity. A receiver facing the light gets E_lobe = c g_1(a) (the cap's exact irradiance) plus E_amb; fully
blocking the lobe leaves E_amb, so the ratio of shadowed to lit radiance is E_amb / (E_lobe + E_amb) and
    opacity o = E_lobe / (E_lobe + E_amb)   (ratio in full shadow = 1 - o).
This is the physical analogue of Sommer et al.'s o = 1 - tanh(E_amb / (0.05 E_light)): both are 1 with no
ambient and fall toward 0 as the ambient dominates, but ours follows from the same F the voxel renderer
uses (theirs saturates: o < 0.01 once E_amb > 0.13 E_light). `receiver_opacity` gives the same share for
any receiver normal.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.optimize import minimize
from scipy.special import eval_legendre

from photoreg.lighting import sh

ANGLE_MIN = math.radians(0.5)    # below this the bands cannot tell a disc from a point (B <= 8)
ANGLE_MAX = math.radians(30.0)   # broader lobes are ambient, not a light that casts a shadow
ANGLE_GRID = np.geomspace(ANGLE_MIN, ANGLE_MAX, 96)
ANGLE_DEFAULT = math.radians(2.0)  # used when the bands cannot measure the falloff (B < 3)
SEARCH_DIRS = 2048               # coarse direction search before the local refinement
MIN_LOBE_SHARE = 1e-6            # a lobe irradiance below this share of the total counts as no light


@dataclass
class ParametricLight:
    """One directional light plus ambient, derived from SH lighting (see the module docstring)."""

    direction: np.ndarray   # (3,) world unit vector towards the light
    colour: np.ndarray      # (3,) integrated radiance c of the lobe (irradiance at normal incidence), F's units
    ambient: np.ndarray     # (3,) irradiance of the residual at the normal facing the light, >= 0
    opacity: np.ndarray     # (3,) in [0, 1]: lobe share of the irradiance on a receiver facing the light
    angle: float            # light's angular radius in radians, in [ANGLE_MIN, ANGLE_MAX]
    residual: np.ndarray    # (3, B*B) SH of the ambient (F minus the lobe)
    lobe_share: float       # share of the luminance energy in the fitted bands that the lobe explains, [0, 1]
    notes: list[str] = field(default_factory=list)

    def lobe_irradiance(self) -> np.ndarray:
        """E_lobe (3,) on a receiver facing the light: c g_1(angle)."""
        return self.colour * band_attenuation(self.angle, 2)[1]

    def irradiance(self, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(E_lobe max(n.d, 0), E_residual(n) clamped at 0), each (N, 3), at unit normals (N, 3)."""
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        lobe = np.maximum(n @ self.direction, 0.0)[:, None] * self.lobe_irradiance()[None]
        amb = np.maximum(sh.irradiance(self.residual, n), 0.0) if len(n) else np.zeros((0, 3))
        return lobe, amb


def band_attenuation(angle: float, bands: int) -> np.ndarray:
    """g_l (bands,) of a uniform disc of angular radius `angle`, normalised so g_0 = 1."""
    x = math.cos(angle)
    g = np.ones(bands)
    if 1.0 - x < 1e-12:
        return g
    for l in range(1, bands):
        g[l] = (eval_legendre(l - 1, x) - eval_legendre(l + 1, x)) / ((2 * l + 1) * (1.0 - x))
    return g


@lru_cache(maxsize=None)
def _grid_attenuation(bands: int) -> np.ndarray:
    """band_attenuation at every ANGLE_GRID angle, (len(ANGLE_GRID), bands), read-only: computed once per band
    count instead of at every fit (96 Legendre evaluations took most of a 5 ms fit)."""
    g = np.stack([band_attenuation(a, bands) for a in ANGLE_GRID])
    g.setflags(write=False)
    return g


def lobe_sh(colour: np.ndarray, direction: np.ndarray, angle: float, bands: int) -> np.ndarray:
    """SH (3, B*B) of the disc lobe: c_k g_l Y_lm(d)."""
    per_coeff = np.repeat(band_attenuation(angle, bands), [2 * l + 1 for l in range(bands)])
    return np.outer(colour, per_coeff * sh.sh_basis(direction[None], bands)[0])


def fit_from(bands: int) -> int:
    """First band of the lobe fit: 2 when at least two higher bands remain (a smooth sky's gradient lives
    in band 1 and would pass for a broader, brighter lobe), else 1."""
    return 2 if bands >= 4 else 1


def _band_sums(F: np.ndarray, d: np.ndarray, bands: int) -> np.ndarray:
    """p_l = sum_m F_lm Y_lm(d) for the fitted bands l >= fit_from(bands): (C, bands - fit_from)."""
    prod = np.atleast_2d(F) * sh.sh_basis(d[None], bands)[0]
    return np.stack([prod[:, l * l:(l + 1) * (l + 1)].sum(axis=1) for l in range(fit_from(bands), bands)], axis=1)


def _best_direction(lum: np.ndarray, g: np.ndarray, bands: int) -> np.ndarray:
    """argmax over unit d of sum_{fitted l} g_l p_l(d): coarse Fibonacci search, then a local refinement."""
    lo = fit_from(bands)
    weights = np.repeat(np.concatenate([np.zeros(lo), g[lo:]]), [2 * l + 1 for l in range(bands)])
    filt = lum * weights
    dirs = sh.fibonacci_sphere(SEARCH_DIRS)
    d0 = dirs[np.argmax(sh.sh_basis(dirs, bands) @ filt)]

    def neg(v):
        n = np.linalg.norm(v)
        return -(sh.sh_basis(v[None] / max(n, 1e-12), bands)[0] @ filt)

    res = minimize(neg, d0, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-12, "maxiter": 400})
    d = res.x / max(np.linalg.norm(res.x), 1e-12)
    return d if neg(d) <= neg(d0) else d0


def _lobe_fit(p: np.ndarray, g: np.ndarray, n_l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares lobe amplitude c per row of p (C, fitted bands) and the energy it explains."""
    gg = g[len(g) - p.shape[1]:]
    c = p @ gg / np.sum(gg * gg * n_l)
    return c, 2 * c * (p @ gg) - c * c * np.sum(gg * gg * n_l)


def _no_light(F: np.ndarray, direction: np.ndarray, note: str) -> ParametricLight:
    """Finite light with opacity 0: all of F is ambient."""
    amb = np.maximum(sh.irradiance(F, direction[None])[0], 0.0)
    return ParametricLight(direction=direction, colour=np.zeros(3), ambient=amb, opacity=np.zeros(3),
                           angle=ANGLE_MAX, residual=F.copy(), lobe_share=0.0, notes=[note])


def parametric_light(F: np.ndarray, direction: np.ndarray | None = None) -> ParametricLight:
    """Directional disc lobe plus residual ambient fitted to F (3, B*B), DESIGN.md basis (module docstring).
    `direction` fixes the lobe's direction instead of fitting it (an estimate's band 1 is its best observed
    band; its higher bands may pull the fitted direction off)."""
    F = np.asarray(F, dtype=np.float64)
    if F.ndim != 2 or F.shape[0] != 3:
        raise ValueError(f"parametric_light: F must be (3, B*B), got {F.shape}")
    bands = sh.bands_of(F.shape[1])
    up = np.array([0.0, 0.0, 1.0])
    if not np.all(np.isfinite(F)):
        return _no_light(np.zeros_like(F), up, "lighting has non-finite coefficients: no light, no ambient")
    if bands < 2:
        return _no_light(F, up, "lighting has band 0 only: no direction, all ambient")
    lum = sh.luminance(F)
    lo = fit_from(bands)
    energy = float(np.sum(lum[lo * lo:] ** 2))
    if energy <= 1e-24 * max(float(lum[0] ** 2), 1e-300):
        return _no_light(F, sh.dominant_direction(F), f"lighting has no energy in bands >= {lo}: all ambient")
    n_l = np.array([(2 * l + 1) / (4 * math.pi) for l in range(lo, bands)])
    notes: list[str] = []
    # direction for a point light first, then the radius from the band falloff, then the direction again
    fixed = direction is not None
    d = np.asarray(direction, np.float64) / max(np.linalg.norm(direction), 1e-12) if fixed else \
        _best_direction(lum, np.ones(bands), bands)
    angle = ANGLE_DEFAULT
    for _ in range(1 if fixed else 2):
        if bands >= 3:
            p = _band_sums(lum, d, bands)[0]
            gg = _grid_attenuation(bands)[:, bands - p.shape[0]:]
            explained = (gg @ p) ** 2 / ((gg * gg) @ n_l)   # _lobe_fit's energy at every angle of the grid
            angle = float(ANGLE_GRID[int(np.argmax(explained))])
        if not fixed:
            d = _best_direction(lum, band_attenuation(angle, bands), bands)
    if bands < 3:
        notes.append(f"{bands} bands cannot measure the lobe's falloff: angle set to {math.degrees(angle):.1f} deg")
    if float(sh.LUMINANCE @ sh.irradiance(F, d[None])[0]) <= 0:
        return _no_light(F, d, "irradiance at the light's normal is not positive: no light")
    g = band_attenuation(angle, bands)
    c_lum, explained = _lobe_fit(_band_sums(lum, d, bands), g, n_l)
    colour = np.maximum(_lobe_fit(_band_sums(F, d, bands), g, n_l)[0], 0.0)
    residual, ambient, opacity = _split(F, colour, d, angle)
    if np.any(ambient < 0):
        notes.append("residual irradiance at the light's normal is negative in some channel: clamped to 0")
    if c_lum[0] <= 0 or float(np.max(opacity)) < MIN_LOBE_SHARE:
        return _no_light(F, d, f"no positive directional lobe in bands >= {lo}: all ambient")
    return ParametricLight(direction=d, colour=colour, ambient=np.maximum(ambient, 0.0), opacity=opacity,
                           angle=angle, residual=residual,
                           lobe_share=float(np.clip(explained[0] / energy, 0.0, 1.0)), notes=notes)


def _split(F: np.ndarray, colour: np.ndarray, d: np.ndarray, angle: float):
    """(residual F - the disc's SH, the residual's irradiance at the normal facing the light (unclamped),
    opacity E_lobe / (E_lobe + max(that, 0)) in [0, 1]) of a disc lobe of integrated radiance colour (3,)."""
    residual = F - lobe_sh(colour, d, angle, sh.bands_of(F.shape[1]))
    ambient = sh.irradiance(residual, d[None])[0]
    e_lobe = colour * band_attenuation(angle, 2)[1]
    total = e_lobe + np.maximum(ambient, 0.0)
    return residual, ambient, np.clip(np.where(total > 0, e_lobe / np.maximum(total, 1e-300), 0.0), 0.0, 1.0)


def traced_light(F: np.ndarray, direction: np.ndarray, colour: np.ndarray, angle: float) -> ParametricLight:
    """The light found by tracing its shadows (photoreg.lighting.sun): a disc of integrated radiance `colour`
    (3,) around unit `direction` with radius `angle`, whose SH F (3, B*B) includes; residual = F - its lobe."""
    F = np.asarray(F, dtype=np.float64)
    d = np.asarray(direction, np.float64) / max(float(np.linalg.norm(direction)), 1e-12)
    colour = np.maximum(np.asarray(colour, np.float64), 0.0)
    residual, ambient, opacity = _split(F, colour, d, angle)
    lum, lobe_lum = sh.luminance(F)[1:], sh.luminance(F - residual)[1:]
    share = float(np.clip(lobe_lum @ lum / max(float(lum @ lum), 1e-300), 0.0, 1.0)) if colour.any() else 0.0
    return ParametricLight(direction=d, colour=colour, ambient=np.maximum(ambient, 0.0), opacity=opacity,
                           angle=angle, residual=residual, lobe_share=share, notes=["light traced from its shadows"])


def receiver_opacity(light: ParametricLight, normals: np.ndarray) -> np.ndarray:
    """Lobe share (N, 3) of the irradiance at receivers with unit normals (N, 3): the strength a full
    shadow of the lobe has there (E_lobe max(n.d, 0) / (E_lobe max(n.d, 0) + E_residual(n)), in [0, 1])."""
    lobe, amb = light.irradiance(normals)
    total = lobe + amb
    return np.clip(np.where(total > 0, lobe / np.maximum(total, 1e-300), 0.0), 0.0, 1.0)


def cone_directions(direction: np.ndarray, angle: float, n: int) -> np.ndarray:
    """n unit directions (n, 3) spread uniformly in solid angle over the cap of radius `angle` around
    `direction` (a Fibonacci spiral on the cap): the light's disc, for soft-shadow visibility rays."""
    if n < 1:
        raise ValueError(f"cone_directions: n must be >= 1, got {n}")
    local = sh.fibonacci_cap(n, math.cos(angle))
    d = np.asarray(direction, dtype=np.float64) / max(float(np.linalg.norm(direction)), 1e-12)
    return local @ np.stack([*light_basis(d), d])


def light_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit u, v with (u, v, d) orthonormal (d a unit vector)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(a, d)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)
