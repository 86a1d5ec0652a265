"""The dominant distant light ("sun") found from the shadows and shading it causes, by exact visibility.

A few SH bands cannot hold a small bright light: its hard shadows make the band-limited fit bend the low
bands (the estimate comes out flatter and its direction off). Where one light dominates, it is better
modelled apart: I = rho (R . F + e s(d)), s(d) = mean over the light's disc of V(x, w) max(n.w, 0) / pi,
with V traced through the fused volume (photoreg.lighting.robust solves F and e >= 0 together).

Search for d, given the frame's solve without it (its samples, albedo regions, weights):
  1. coarse: `candidates` spherical-Fibonacci directions (fixed in the world), one visibility ray each from
     a subsample of the fitted samples;
  2. each candidate is scored by how much adding its column lowers the weighted residual of a nearly
     unregularised fit (`search_regularization`: a column the SH can already represent, such as any light
     over a single plane, gains nothing; shadows can not be represented and do), summed over channels whose
     e comes out positive (closed form, by eliminating e: gain = (z - u^T H b)^2 / (v - u^T H u), one small
     eigen-decomposition per channel for all candidates). The samples keep their regions' albedos, except
     on the plane of the largest region (the floor or table: albedo.dominant_plane), where the samples of
     any region with fewer than PATCH_SHARE of the plane's samples of the largest region take that region's
     albedo: a shadow on the floor, tinted by the sky, often gets a colour region of its own, whose albedo
     then explains the shadow away (generated coloured scene, frame 0: the true direction 0.04% of the
     residual; in frames where the shadow stayed in the floor's region 24-29%). The samples keep their normal
     weights but not the fit's robust ones: the SH alone cannot hold a light's shadows, so the robust loss takes
     them for outliers and lowers their weight (generated tabletop under the HDR studio map: the key light's
     direction 2.6% of the residual with them, 9.6% without; found in frame 0 instead of frame 10). Large patches keep their
     own: given the white albedo, the black half of the generated black and white floor made the search
     claim a light (gain 0.07) in frames 0-4. A candidate that reaches fewer than `min_lit` of
     the samples scores nothing: a dominant light lights a part of the scene, not a few stray samples
     (measured on the generated tabletop at 640x480: the sun lights 90-95% of the samples; with 3 bands a
     direction from below the floor lighting 27 of 8000 samples, the underside of a small sphere, won the
     search with 8% of the residual and the frame's estimate went wrong);
  3. a distant light does not move: the coarse gains (as shares of the frame's residual) are accumulated
     over frames with a forgetting factor (`memory` coarse passes) and the best accumulated direction is refined
     in the frame by two cones of REFINE_DIRS directions, at the coarse spacing and a third of it. The
     coarse pass (most of the rays) runs every `coarse_every` frames; while a light is held the refinement
     runs every `refine_every` frames (the coarse passes refine too; every frame during the first
     `coarse_every` frames a light is held), from the same accumulated best coarse
     direction (not from the last refined one: refining a refinement drifts); the frames between hold the
     last refined light (they need no solve of the current view alone: the pipeline's solve then runs once),
     unless the joint fit with it is worse than usual (`stale`: its residual over STALE_FACTOR times the median
     of the last STALE_FRAMES joint fits; a light switched mid-recording), which refines it in that frame after
     all; with no light held nothing runs;
  4. a light is held from one coarse pass to the next when the accumulated mean gain of its direction is
     at least `min_gain` of the residual: evidence over frames, so that a light near the threshold does not
     blink on and off; otherwise none is claimed (a single plane or an overcast sky gives none).
Tracing is passed in as a function, so this module stays numpy-only and testable without a volume.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import sh
from .albedo import dominant_plane
from .parametric import ANGLE_DEFAULT, cone_directions, lobe_sh
from .robust import Solution, Term

REFINE_DIRS = 24     # directions per refinement cone
CHANGE_KEEP = 0.25   # share of a pass the accumulated votes keep where the lighting changed (lighting_changed)
PATCH_SHARE = 0.25   # search: a region with fewer samples on the floor's plane than this share of the floor region's
                     # own is scored there with the floor's albedo (module docstring, step 2)
REFINE_LEVELS = (1.0, 1.0 / 3.0)  # cone radii in units of the coarse spacing
STALE_FACTOR = 1.3   # a held light is refined after all where the joint fit's residual is over this times ...
STALE_FRAMES = 10    # ... the median of the last this many joint fits (module docstring, step 3)


@dataclass
class SunConfig:
    """Settings of the search (module docstring)."""

    candidates: int = 256        # coarse directions over the sphere (spacing about 12.7 degrees)
    samples: int = 1500          # fitted samples traced per candidate
    min_gain: float = 0.05       # hold a light whose mean gain (share of the residual) is at least this
    min_lit: float = 0.05        # share of the searched samples a candidate must light to score
    search_regularization: float = 1e-4  # relative Tikhonov strength of the scoring fit (step 2)
    memory: float = 10.0         # coarse passes over which their gains are accumulated
    coarse_every: int = 5        # frames between coarse passes (between them: refinement of a held light only)
    refine_every: int = 5        # frames between refinements of a held light (between them it is held as refined)
    rays: int = 8                # rays over the light's disc for its final transfer
    angle: float = ANGLE_DEFAULT  # the light's angular radius (not measured: shading cannot tell it)
    seed: int = 0

    def __post_init__(self) -> None:
        if not (self.candidates >= 8 and self.samples >= 10 and 0 <= self.min_gain < 1 and 0 <= self.min_lit < 1
                and self.rays >= 1
                and 0 < self.angle < math.pi / 2 and self.search_regularization >= 0 and self.memory >= 1
                and self.coarse_every >= 1 and self.refine_every >= 1):
            raise ValueError("sun: need candidates >= 8, samples >= 10, 0 <= min_gain < 1, 0 <= min_lit < 1, rays >= 1, "
                             "0 < angle < 90 degrees, search_regularization >= 0, memory >= 1, coarse_every >= 1, "
                             f"refine_every >= 1 (got {self})")


@dataclass
class Sun:
    """A found light: unit direction (world, towards the light), angular radius, and the share of the
    SH-only residual it explains (gain). The strength e comes from the joint solve."""

    direction: np.ndarray
    angle: float
    gain: float


def direct_transfer(visible: np.ndarray, normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N, D) V max(n.w, 0) / pi per sample and direction, from visibility (N, D) bool."""
    return visible * np.maximum(np.asarray(normals, np.float64) @ np.asarray(dirs, np.float64).T, 0.0) / math.pi


def score(A: np.ndarray, I: np.ndarray, w: np.ndarray, rho: np.ndarray, S: np.ndarray,
          lam_rel: float) -> tuple[np.ndarray, float]:
    """Residual reduction (D,) of adding each column of S (N, D) to the Tikhonov fit of I (N, 3) on A (N, K)
    with sample weights w (N,) and albedos rho (N, 3), summed over channels whose light comes out positive;
    and the weighted residual without any of them (module docstring, step 2)."""
    gain, base = np.zeros(S.shape[1]), 0.0
    k = A.shape[1]
    for c in range(3):
        wc = w * rho[:, c] ** 2
        G = (A * wc[:, None]).T @ A
        lam = lam_rel * float(np.trace(G)) / k
        ev, V = np.linalg.eigh(G)
        ev = np.maximum(ev, 0.0)
        keep = ev > max(float(ev.max()), 0.0) * k * 1e-13
        Hhalf = V[:, keep] / np.sqrt(ev[keep] + lam)      # H = Hhalf Hhalf^T
        y = w * rho[:, c] * I[:, c]
        b, U = A.T @ y, (A * wc[:, None]).T @ S           # (K,), (K, D)
        hb, hU = Hhalf.T @ b, Hhalf.T @ U
        base += max(float((w * I[:, c] ** 2).sum() - hb @ hb), 0.0)
        num = S.T @ y - hU.T @ hb
        den = (wc[:, None] * S * S).sum(axis=0) - (hU * hU).sum(axis=0)
        ok = (den > 1e-12 * np.maximum((wc[:, None] * S * S).sum(axis=0), 1e-300)) & (num > 0)
        gain += np.where(ok, num * num / np.where(ok, den, 1.0), 0.0)
    return gain, base


class SunSearch:
    """The search with its state across frames (the accumulated coarse gains; module docstring)."""

    def __init__(self, cfg: SunConfig):
        self.cfg = cfg
        self.coarse = sh.fibonacci_sphere(cfg.candidates)
        self.votes = np.zeros(cfg.candidates)  # forgetting sums of the coarse passes' gain shares ...
        self.weight = 0.0                      # ... and of the passes themselves: votes / weight = mean share
        self.held: np.ndarray | None = None    # the accumulated best coarse direction while a light is held
        self.held_since: int | None = None     # the frame from which a light has been held
        self.last: Sun | None = None           # the latest refined light, held between refinements
        self.residuals: deque = deque(maxlen=STALE_FRAMES)  # residual rms of the latest joint fits
        self.forced = False                    # the frame is searched again (recheck)
        self.coarse_next = False               # the next search is a coarse pass (lighting_changed)
        self.frames = 0

    def due(self) -> bool:
        """Whether the next frame is searched (a coarse pass, or a held light refined); if not, the call may
        pass no solution (the pipeline then skips the current view's own solve)."""
        cfg = self.cfg
        # a light held for less than coarse_every frames is refined every frame: its first refinements rest on
        # few views (generated coloured orbit: frame 0's 10.6 degrees off, frames 1-4's 6.3-3.3)
        young = self.held_since is not None and self.frames - self.held_since < cfg.coarse_every
        refine = self.held is not None and (young or self.frames % cfg.refine_every == 0)
        return self.forced or refine or self.coarse_next or self.frames % cfg.coarse_every == 0

    def stale(self, residual_rms: float) -> bool:
        """Record the residual rms of a joint fit with the light; whether it is over STALE_FACTOR times the median
        of the previous ones (at least 3): the held light no longer fits as it did."""
        worse = len(self.residuals) >= 3 and residual_rms > STALE_FACTOR * float(np.median(self.residuals))
        self.residuals.append(residual_rms)
        return worse

    def lighting_changed(self) -> None:
        """The temporal filter saw the lighting change (a light switched or moved): the accumulated votes count as
        CHANGE_KEEP of a pass and the next frame runs a coarse pass, so a light that moved is found there; the
        refinements search only round the held direction, and the old votes outweighed the new ones for up to
        `memory` coarse passes (a static camera's sun moved 120 degrees: 25 frames). A light that stayed keeps its
        mean vote (numerator and weight scale alike)."""
        self.votes *= CHANGE_KEEP
        self.weight *= CHANGE_KEEP
        self.coarse_next = True

    def recheck(self) -> None:
        """Search the frame just searched again, as a refinement of the held light (its joint fit was stale)."""
        self.frames -= 1
        self.forced = True

    def __call__(self, trace: Callable[[np.ndarray, np.ndarray], np.ndarray], sol: Solution | None,
                 radiance: np.ndarray, design: Callable[[np.ndarray], np.ndarray], normals: np.ndarray,
                 points: np.ndarray) -> Sun | None:
        """The frame's dominant light from the solution `sol` without it (on radiance (N, 3), normals (N, 3)
        and world points (N, 3)), or None when none is held. design(idx) gives the rows (len(idx), K') of its
        design (the SH transfer and any other extra terms' columns); trace(idx, dirs) the visibility
        (len(idx), D) bool of directions dirs (D, 3) from the samples idx."""
        cfg = self.cfg
        if not self.due():   # between searches: the held light as last refined (None when none is held)
            self.frames += 1
            return self.last if self.held is not None else None
        if sol is None or sol.samples is None or sol.system is None or int((sol.weights > 0).sum()) < 10:
            # too little to search in (a black or covered frame): the held light as last refined, searched next frame
            return self.last if self.held is not None else None
        coarse = self.coarse_next or self.frames % cfg.coarse_every == 0
        self.frames += 1
        self.forced = self.coarse_next = False
        A, I, w, rho, nrm, idx = _search_inputs(sol, radiance, design, normals, points, cfg)
        lam = cfg.search_regularization

        def gains(dirs):
            S = direct_transfer(trace(idx, dirs), nrm, dirs)
            g, base = score(A, I, w, rho, S, lam)
            g[(S > 0).mean(axis=0) < cfg.min_lit] = 0.0
            return g / base if base > 0 else np.zeros(len(dirs))

        if coarse:
            keep = 1.0 - 1.0 / cfg.memory
            self.votes = self.votes * keep + gains(self.coarse)
            self.weight = self.weight * keep + 1.0
            j = int(np.argmax(self.votes))
            self.held = self.coarse[j] if self.votes[j] >= cfg.min_gain * self.weight else None
        if self.held is None:
            self.last = self.held_since = None
            return None
        if self.held_since is None:
            self.held_since = self.frames - 1
        best, best_gain = self.held, -math.inf   # the first cone holds the start direction itself
        spacing = math.sqrt(4 * math.pi / cfg.candidates)
        for level in REFINE_LEVELS:
            dirs = np.vstack([best, cone_directions(best, level * spacing, REFINE_DIRS)])
            g = gains(dirs)
            j = int(np.argmax(g))
            if g[j] > best_gain:
                best, best_gain = dirs[j] / np.linalg.norm(dirs[j]), float(g[j])
        self.last = Sun(direction=best, angle=cfg.angle, gain=best_gain)
        return self.last


def _search_inputs(sol: Solution, radiance, design, normals, points, cfg: SunConfig):
    """(A, I, w, rho, normals, idx) of a subsample of at most cfg.samples of the fitted samples; w their normal
    weights without the robust ones, rho (n, 3) their regions' albedos, the largest region's for small patches on
    its plane (module docstring, step 2)."""
    live = sol.weights > 0
    w = (sol.setup.w0 if sol.setup is not None else sol.weights)[live]
    idx, labels = sol.samples[live], sol.labels[live]
    if idx.size > cfg.samples:
        pick = np.sort(np.random.default_rng(cfg.seed).choice(idx.size, cfg.samples, replace=False))
        idx, labels, w = idx[pick], labels[pick], w[pick]
    nrm, pts = np.asarray(normals, np.float64)[idx], np.asarray(points, np.float64)[idx]
    labels = np.maximum(labels, 0)   # fitted samples all have a region (weight 0 otherwise)
    rho = sol.albedo[labels]
    plane = dominant_plane(pts[labels == 0], nrm[labels == 0])
    if plane is not None:
        on = plane.on(pts, nrm)
        count = np.bincount(labels[on], minlength=len(sol.albedo))
        rho[on & (count[labels] < PATCH_SHARE * count[0])] = sol.albedo[0]
    return np.asarray(design(idx), np.float64), np.asarray(radiance, np.float64)[idx], w, rho, nrm, idx


def sun_term(sun: Sun, visible: np.ndarray, normals: np.ndarray, disc: np.ndarray, bands: int) -> Term:
    """The solve's term of a found sun from the visibility (N, R) of its disc's rays `disc` (R, 3)."""
    s = direct_transfer(visible, normals, disc).mean(axis=1)
    return Term("sun", s, lobe_sh(np.ones(1), sun.direction, sun.angle, bands)[0])


def disc_rays(sun: Sun, n: int) -> np.ndarray:
    """n directions (n, 3) over the sun's disc (the centre alone when n = 1)."""
    return sun.direction[None] if n == 1 else cone_directions(sun.direction, sun.angle, n)
