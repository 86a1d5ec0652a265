"""Per-frame SH lighting solve (Gruber et al. 2012): weighted, Tikhonov-regularised least squares.

Model (DESIGN.md): the observed linear radiance of a surface sample is I(x) = rho * sum_i R(x)_i F_i
with R the transfer from the ray caster. One unknown global albedo is absorbed into F (rho = 1), so
the returned lighting is relative to the scene's albedo scale.

Samples are weighted so that the distribution of surface normals does not decide the answer: a
frame that is 95% floor would otherwise fit the floor's irradiance perfectly and extrapolate the
rest of the sphere from a handful of samples.
  * "bins" (the paper): normals are histogrammed on an equal-area spherical grid; with Q_c samples in
    bin c and P populated bins, every sample in c gets weight 1/(Q_c * P), so each populated bin
    carries the same total weight 1/P however many samples fell into it (over-represented bins are
    down-weighted, sparse ones up-weighted). Weights are rescaled to mean 1.
  * "density": inverse kernel density of normals on the sphere (von Mises-Fisher kernel of
    `density_bandwidth` radians) - the same idea without bin edges.
  * "none": every sample weighs the same.
With per-region albedo (photoreg.lighting.robust) the bins are counted per albedo region when
`region_weights` is on: each (region, bin) cell carries the same weight. A region's albedo is free, so
only the spread of normals within a region tells F's shape; with one histogram for all regions the
top of a box shares the floor's bin and weighs nothing, and the light's zenith-to-horizon colour is
left to the colour balance rule.

The system is solved through the SVD of the weighted design sqrt(W) A with Tikhonov filter factors
s / (s^2 + lambda), i.e. exactly the least-squares solution of the stacked system
[sqrt(W) A; sqrt(lambda) I] f = [sqrt(W) b; sqrt(lambda) f_prior]; the normal equations are never
formed or inverted. lambda = `regularization` * trace(A^T W A) / K, so it is relative to the data.

That is the paper's solver. The robust settings (loss, per-region albedo, order selection; see
photoreg.lighting.robust) switch solve_lighting over to photoreg.lighting.robust.solve.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..types import Lighting, SolveDiagnostics
from . import sh

WEIGHTINGS = ("bins", "density", "none")
MODES = ("rgb", "white")
LOSSES = ("none", "huber", "tukey")
ALBEDOS = ("single", "regions")
ALBEDO_REFERENCES = ("max", "largest", "mean")
ALBEDO_STEPS = ("alternate", "joint")
SELECTIONS = ("fixed", "gcv", "holdout", "aic", "bic")


@dataclass
class SolverConfig:
    """Settings of the per-frame lighting solve (see the module docstring for the weightings)."""

    bands: int = 3
    # "bins" | "density" | "none". bins won on 32 synthetic clustered-normal cases (8-band light, 3-band solve):
    # mean relative irradiance error 0.059 (bins) vs 0.060 (density) vs 0.094 (none), at a third of density's cost.
    weighting: str = "bins"
    grid_bins: int = 8                 # equal-area grid: grid_bins bands in z x 2*grid_bins in azimuth
    density_bandwidth: float = 0.2     # radians, kernel width for weighting="density"
    regularization: float = 1e-2       # Tikhonov lambda relative to trace(A^T W A) / K; best of 0..3e-2 measured
    min_visible: float = 0.05          # drop samples with less than this unoccluded fraction (paper: 95% blocked)
    mode: str = "rgb"                  # "rgb": three solves; "white": one luminance solve times mean chroma
    max_samples: int | None = 20000    # random subsample of the usable samples (fixed seed), None = all
    seed: int = 0
    saturation_level: float | None = 0.99  # drop samples with any channel >= this (None: keep all)
    black_level: float = 1e-3          # drop samples whose brightest channel is <= this
    min_samples_factor: float = 3.0    # fewer than factor * K usable samples -> weak
    max_condition: float = 1e4         # condition number of the weighted design above this -> weak
    rank_rtol: float = 1e-6            # singular values above rank_rtol * s_max count toward the rank
    # A bin holding fewer than this share of the samples gets proportionally less than a full bin's weight:
    # a few stray normals (TSDF edges) must not carry as much as the whole floor. 0 = the paper's rule.
    bin_min_fraction: float = 0.0

    # --- robust settings (photoreg.lighting.robust); the defaults here are the paper's solver ---
    loss: str = "none"                 # "none" | "huber" | "tukey": IRLS weights on luminance residuals
    loss_scale: float | None = None    # tuning constant in robust sigmas (None: 1.345 huber, 4.685 tukey)
    iterations: int = 12               # alternations of albedo, lighting and robust weights (at most) ...
    tolerance: float = 1e-2            # ... stopping once F moves less than this (relative) per alternation
    albedo: str = "single"             # "single" | "regions": one albedo, or one per region found in the data
    albedo_reference: str = "max"      # scale fix: "max" (per-channel max over regions), "largest", "mean"
    albedo_step: str = "alternate"     # "alternate" F and albedos, or a "joint" Gauss-Newton step (robust.py)
    reference_albedo: float = 1.0      # ... whose albedo is taken to be this (absolute scale of F)
    chroma_bandwidth: float = 0.08     # region clustering cell in log-chromaticity (best of 0.05/0.08/0.12)
    intensity_bandwidth: float = 0.5   # ... and in log albedo (second pass, shading removed)
    min_region_fraction: float = 0.005  # a region needs this share of the samples (small objects count)
    select: str = "fixed"              # order/regularisation choice: fixed | gcv | holdout | aic | bic
    max_bands: int = 5                 # largest band count tried by `select`
    lambdas: tuple = (1e-3, 3e-3, 1e-2, 3e-2, 1e-1)  # relative regularisations tried by `select`
    holdout_fraction: float = 0.0      # share of samples kept out of the fit to report a held-out residual
    region_weights: bool = False       # weighting "bins": normals counted per albedo region (module docstring)

    def __post_init__(self) -> None:
        if self.bands < 1:
            raise ValueError(f"bands must be >= 1, got {self.bands}")
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.grid_bins < 1 or self.density_bandwidth <= 0 or self.regularization < 0:
            raise ValueError("grid_bins >= 1, density_bandwidth > 0 and regularization >= 0 are required")
        for name, value, choices in (("loss", self.loss, LOSSES), ("albedo", self.albedo, ALBEDOS),
                                     ("albedo_reference", self.albedo_reference, ALBEDO_REFERENCES),
                                     ("albedo_step", self.albedo_step, ALBEDO_STEPS),
                                     ("select", self.select, SELECTIONS)):
            if value not in choices:
                raise ValueError(f"{name} must be one of {choices}, got {value!r}")
        if not 0 < self.reference_albedo <= 1:
            raise ValueError(f"reference_albedo must be in (0, 1], got {self.reference_albedo}")
        if not (0 <= self.bin_min_fraction < 1 and 0 <= self.holdout_fraction < 0.5 and self.iterations >= 1
                and self.max_bands >= 1 and self.lambdas and min(self.lambdas) >= 0):
            raise ValueError("need 0 <= bin_min_fraction < 1, 0 <= holdout_fraction < 0.5, iterations >= 1, "
                             "max_bands >= 1 and non-negative lambdas")

    @classmethod
    def from_lighting(cls, lc) -> "SolverConfig":
        """The solve settings of a session's [lighting] table (photoreg.config.LightingConfig)."""
        return cls(bands=lc.bands, weighting=lc.weighting, regularization=lc.regularization,
                   min_visible=lc.min_visible, mode=lc.mode, bin_min_fraction=lc.bin_min_fraction, loss=lc.loss,
                   albedo=lc.albedo, albedo_reference=lc.albedo_reference, albedo_step=lc.albedo_step,
                   reference_albedo=lc.reference_albedo, select=lc.select,
                   max_bands=lc.max_bands, max_samples=lc.max_samples, region_weights=lc.region_weights)

    @property
    def robust(self) -> bool:
        """Whether any robust setting is on (then solve_lighting runs photoreg.lighting.robust.solve)."""
        return (self.loss != "none" or self.albedo != "single" or self.select != "fixed"
                or self.holdout_fraction > 0)

    @property
    def fit_bands(self) -> int:
        """Band count of the transfer the solve needs: max_bands when selecting, else bands."""
        return self.max_bands if self.select != "fixed" else self.bands


def bin_weights(normals: np.ndarray, grid_bins: int, min_fraction: float = 0.0,
                groups: np.ndarray | None = None) -> np.ndarray:
    """Per-sample weights 1/(Q_c * P) on an equal-area grid of normals, rescaled to mean 1.

    Bins are equal-area: `grid_bins` bands uniform in z = cos(theta) times 2*grid_bins uniform in
    azimuth, so an even spread of normals gives even counts. With min_fraction > 0 a bin holding
    Q_c < min_fraction * N samples carries only Q_c / (min_fraction * N) of a full bin's weight, so
    that a handful of stray normals cannot outweigh a well-sampled surface. With `groups` (N,) integer
    labels (albedo regions) the bins are counted per group: c runs over (group, bin) cells.
    """
    n = np.asarray(normals, dtype=np.float64)
    if n.shape[0] == 0:
        return np.zeros(0)
    iz = np.clip(((n[:, 2] + 1.0) * 0.5 * grid_bins).astype(np.int64), 0, grid_bins - 1)
    phi = np.arctan2(n[:, 1], n[:, 0])  # [-pi, pi]
    ip = np.clip(((phi + np.pi) / (2 * np.pi) * 2 * grid_bins).astype(np.int64), 0, 2 * grid_bins - 1)
    cell = iz * (2 * grid_bins) + ip
    if groups is not None:
        g = np.asarray(groups, dtype=np.int64)
        cell = cell + (g - g.min()) * (2 * grid_bins * grid_bins)
    counts = np.bincount(cell)[cell]   # each sample's bin count (bins are small integers: no sort needed)
    share = np.minimum(1.0, counts / (min_fraction * n.shape[0])) if min_fraction > 0 else 1.0
    w = share / counts
    return w * (len(w) / w.sum())


def density_weights(normals: np.ndarray, bandwidth: float, seed: int = 0, n_ref: int = 2048) -> np.ndarray:
    """Inverse kernel density of normals (von Mises-Fisher kernel, kappa = 1/bandwidth^2), mean 1.

    The density counts the sample itself plus its neighbours, estimated from at most `n_ref`
    random reference normals (scaled up to all N), so it is never below 1 and the cost is O(N n_ref).
    """
    n = np.asarray(normals, dtype=np.float64)
    count = n.shape[0]
    if count == 0:
        return np.zeros(0)
    kappa = 1.0 / bandwidth ** 2
    ref_idx = np.arange(count)
    if count > n_ref:
        ref_idx = np.random.default_rng(seed).choice(count, n_ref, replace=False)
    in_ref = np.zeros(count)
    in_ref[ref_idx] = 1.0
    ref = n[ref_idx]
    near = np.empty(count)
    for s in range(0, count, 4096):
        near[s:s + 4096] = np.exp(kappa * (np.clip(n[s:s + 4096] @ ref.T, -1.0, 1.0) - 1.0)).sum(axis=1)
    others = np.maximum(near - in_ref, 0.0)  # drop the self-term of reference samples
    dens = 1.0 + others * (count - 1) / np.maximum(len(ref_idx) - in_ref, 1.0)
    w = 1.0 / dens
    return w * (count / w.sum())


def regularized_lstsq(design: np.ndarray, rhs: np.ndarray, lam: float, prior: np.ndarray | None = None,
                      relative: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """argmin_x ||design x - rhs||^2 + lam ||x - prior||^2 via the SVD of `design`.

    design (n, K), rhs (n,) or (n, C), prior like the solution (K,) or (K, C) or None (= 0).
    relative=True takes lam in units of trace(design^T design) / K. Returns (x, singular values).
    Directions with zero singular value keep the prior's value (the pseudo-inverse when lam = 0).
    Design and rhs are scaled to unit maximum first, so tiny or huge data neither under- nor overflow.
    """
    a = np.asarray(design, dtype=np.float64)
    b = np.asarray(rhs, dtype=np.float64)
    k = a.shape[1]
    x0 = np.zeros((k,) + b.shape[1:]) if prior is None else np.asarray(prior, dtype=np.float64)
    if a.shape[0] == 0:
        return x0.copy(), np.zeros(0)
    ca = float(np.abs(a).max()) or 1.0
    cb = float(np.abs(b).max()) or 1.0
    u, s, vt = np.linalg.svd(a / ca, full_matrices=False)
    lam_s = lam * float((s * s).sum()) / k if relative else lam / (ca * ca)
    tiny = (s.max() if s.size else 0.0) * max(a.shape) * np.finfo(np.float64).eps
    denom = s * s + lam_s
    filt = np.divide(s, denom, out=np.zeros_like(s), where=(s > tiny) & (denom > 0))
    x0_s = x0 * (ca / cb)
    r = b / cb - (a / ca) @ x0_s
    x_s = x0_s + vt.T @ (filt.reshape((-1,) + (1,) * (b.ndim - 1)) * (u.T @ r))
    with np.errstate(over="ignore"):
        return x_s * (cb / ca), s * ca


def _norms(v: np.ndarray) -> np.ndarray:
    """Lengths of the rows of v (N, 3), as np.linalg.norm(v, axis=1) (which reduces along the short axis
    several times slower)."""
    return np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])


def normal_weights(normals: np.ndarray, cfg: SolverConfig, groups: np.ndarray | None = None) -> np.ndarray:
    """Sample weights (mean 1) from the distribution of the (non-zero) normals, by cfg.weighting; "bins"
    counts them per group (albedo region) when groups are given and cfg.region_weights is on."""
    nrm = normals / _norms(normals)[:, None]
    if cfg.weighting == "bins":
        return bin_weights(nrm, cfg.grid_bins, cfg.bin_min_fraction, groups if cfg.region_weights else None)
    if cfg.weighting == "density":
        return density_weights(nrm, cfg.density_bandwidth, cfg.seed)
    return np.ones(nrm.shape[0])


def _all_columns(b: np.ndarray) -> np.ndarray:
    """b (N, d) boolean: rows that are all True, column by column (numpy reduces along a short last axis
    several times slower)."""
    ok = b[:, 0].copy()
    for j in range(1, b.shape[1]):
        ok &= b[:, j]
    return ok


def _usable(radiance, transfer, normals, visible, mask, cfg, clipped=None) -> tuple[np.ndarray, list[str]]:
    """Boolean mask of samples fit to enter the solve, with notes on what was dropped and why; `clipped` samples
    (censored: robust.solve) are not dropped as saturated."""
    notes: list[str] = []
    keep = np.ones(radiance.shape[0], dtype=bool) if mask is None else np.asarray(mask, dtype=bool).copy()
    finite_rad, finite_nrm = np.isfinite(radiance), np.isfinite(normals)
    finite = _all_columns(finite_rad) & _all_columns(np.isfinite(transfer)) & _all_columns(finite_nrm)
    finite &= np.isfinite(visible)
    nrm = np.where(finite_nrm, normals, 0.0)
    finite &= _norms(nrm) > 1e-6
    rad = np.where(finite_rad, radiance, 0.0)
    peak = np.maximum(np.maximum(rad[:, 0], rad[:, 1]), rad[:, 2])
    tests = [("non-finite or zero-normal", finite),
             ("occluded (visible < min_visible)", np.where(np.isfinite(visible), visible, -1.0) >= cfg.min_visible),
             ("black", peak > cfg.black_level)]
    if cfg.saturation_level is not None:
        bright = peak < cfg.saturation_level
        tests.append(("saturated", bright if clipped is None else bright | clipped))
    for name, ok in tests:
        dropped = int((keep & ~ok).sum())
        if dropped:
            notes.append(f"dropped {dropped} {name} samples")
        keep &= ok
    return keep, notes


def select_samples(radiance, transfer, normals, visible, cfg: SolverConfig, bands: int, prior=None, mask=None,
                   clipped=None):
    """Checked float64 inputs, transfer cut to `bands`, the indices of the usable (subsampled) samples,
    the prior cut to `bands` (None when absent or unusable) and notes on what was dropped; `clipped` (N,) bool
    marks censored samples (robust.solve), kept whatever their level.

    Shapes that do not match raise ValueError; bad data only drops samples."""
    radiance = np.asarray(radiance, dtype=np.float64).reshape(-1, 3)
    transfer = np.asarray(transfer, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    visible = np.asarray(visible, dtype=np.float64).reshape(-1)
    k = bands * bands
    n_all = radiance.shape[0]
    if transfer.ndim != 2 or transfer.shape[1] < k:
        raise ValueError(f"transfer must be (N, >= {k}) for {bands} bands, got {transfer.shape}")
    if not (transfer.shape[0] == normals.shape[0] == visible.shape[0] == n_all):
        raise ValueError(f"sample counts differ: radiance {n_all}, transfer {transfer.shape[0]}, "
                         f"normals {normals.shape[0]}, visible {visible.shape[0]}")
    if mask is not None and np.shape(mask) != (n_all,):
        raise ValueError(f"mask shape {np.shape(mask)} does not match {n_all} samples")
    if clipped is not None:
        if np.shape(clipped) != (n_all,):
            raise ValueError(f"clipped shape {np.shape(clipped)} does not match {n_all} samples")
        clipped = np.asarray(clipped, dtype=bool)
    transfer = transfer[:, :k]
    notes: list[str] = []
    if prior is not None:
        prior = sh.truncate(np.asarray(prior, dtype=np.float64), bands)
        if prior.shape[0] != 3 or not np.isfinite(prior).all():
            notes.append("prior ignored (not a finite 3-channel SH)")
            prior = None
    keep, drop_notes = _usable(radiance, transfer, normals, visible, mask, cfg, clipped)
    notes += drop_notes
    idx = np.flatnonzero(keep)
    if cfg.max_samples is not None and idx.size > cfg.max_samples:
        idx = np.sort(np.random.default_rng(cfg.seed).choice(idx, cfg.max_samples, replace=False))
    return radiance, transfer, normals, idx, prior, notes


def conditioning(s: np.ndarray, n: int, k: int, cfg: SolverConfig, notes: list[str]) -> tuple[int, float, bool]:
    """Effective rank, condition number and 'too few samples' from the singular values s of a
    design with n samples and k unknowns; appends the matching diagnostic notes."""
    s_max = float(s[0]) if s.size else 0.0
    rank = int((s > cfg.rank_rtol * s_max).sum()) if s_max > 0 else 0
    cond = float(s_max / s[-1]) if s.size == k and s[-1] > 0 else float("inf")
    too_few = n < cfg.min_samples_factor * k
    if too_few:
        notes.append(f"only {n} usable samples for {k} unknowns")
    if rank < k:
        notes.append(f"rank deficient: effective rank {rank} of {k}")
    elif cond > cfg.max_condition:
        notes.append(f"ill-conditioned: condition number {cond:.3g}")
    return rank, cond, too_few


def solve_lighting(radiance: np.ndarray, transfer: np.ndarray, normals: np.ndarray, visible: np.ndarray,
                   cfg: SolverConfig | None = None, prior: np.ndarray | None = None,
                   mask: np.ndarray | None = None) -> tuple[Lighting, SolveDiagnostics]:
    """Solve SH lighting F (3, cfg.bands^2) from per-sample radiance (N, 3) and transfer (N, B*B).

    normals (N, 3) world and visible (N,) unoccluded fraction feed the sample weights and the
    occlusion filter; `mask` (N,) optionally restricts the samples; `prior` (3, B'*B') is a previous
    lighting to regularise toward (instead of toward zero) and to fall back on. Shapes that do not
    match raise ValueError; data problems never raise: they give a finite, weak result with notes.
    A config with robust settings (SolverConfig.robust) is solved by photoreg.lighting.robust.solve.
    """
    cfg = cfg or SolverConfig()
    if cfg.robust:
        from .robust import solve
        sol = solve(radiance, transfer, normals, visible, cfg, prior=prior, mask=mask)
        return sol.lighting, sol.diagnostics
    k = cfg.bands * cfg.bands
    radiance, transfer, normals, idx, prior, notes = select_samples(radiance, transfer, normals, visible, cfg,
                                                                    cfg.bands, prior, mask)
    fallback = prior if prior is not None else np.zeros((3, k))
    n = idx.size
    if n == 0:
        notes.append("no usable samples: returning the " + ("prior" if prior is not None else "zero lighting"))
        return Lighting(fallback.copy()), SolveDiagnostics(n_samples=0, weak=True, notes=notes)

    a, obs, nrm = transfer[idx], radiance[idx] / cfg.reference_albedo, normals[idx]  # every albedo = reference
    w = normal_weights(nrm, cfg)
    sw = np.sqrt(w)[:, None]

    if cfg.mode == "white":
        rhs = obs @ sh.LUMINANCE
        mean_rgb = (w[:, None] * obs).sum(axis=0) / w.sum()
        chroma = mean_rgb / max(float(sh.LUMINANCE @ mean_rgb), 1e-12)
        prior_x = None if prior is None else sh.luminance(prior)
    else:
        rhs = obs
        prior_x = None if prior is None else prior.T

    aw = sw * a
    rhs_w = sw * rhs if rhs.ndim == 2 else sw[:, 0] * rhs
    x, s = regularized_lstsq(aw, rhs_w, cfg.regularization, prior_x, relative=True)
    rank, cond, too_few = conditioning(s, n, k, cfg, notes)

    solve_cols = k
    if prior is None and k > 1 and (n < k or rank < k):
        # Not enough information for the higher bands and nothing to regularise toward: claim no
        # direction, fit the ambient (band 0) term only.
        notes.append("band-0-only fallback")
        solve_cols = 1
        x, _ = regularized_lstsq(aw[:, :1], rhs_w, cfg.regularization, relative=True)

    f = np.zeros((3, k))
    if cfg.mode == "white":
        f[:, :solve_cols] = chroma[:, None] * x[None, :]
    else:
        f[:, :solve_cols] = x.T
    if not np.isfinite(f).all():  # only reachable with overflowing inputs
        notes.append("solution overflowed: returning the " + ("prior" if prior is not None else "zero lighting"))
        f = fallback.copy()

    c = float(np.abs(obs).max()) or 1.0  # residual in units of the data: no under/overflow
    with np.errstate(over="ignore", invalid="ignore"):
        resid = (a @ f.T - obs) / c
        mean_obs = float(np.abs(obs / c).mean())
        rms = float(np.sqrt(np.mean(resid * resid)) / mean_obs) if mean_obs > 0 else 0.0
    diag = SolveDiagnostics(n_samples=n, condition_number=cond, effective_rank=rank,
                            residual_rms=float(np.nan_to_num(rms, nan=0.0, posinf=np.finfo(np.float64).max)),
                            weak=bool(too_few or rank < k or cond > cfg.max_condition or solve_cols < k),
                            notes=notes)
    return Lighting(f), diag
