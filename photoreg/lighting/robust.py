"""Robust per-frame lighting solve: IRLS, per-region albedo by alternation, model order selection.

Model: I_i = rho_{r(i)} * (R_i . F) per channel, with r(i) the albedo region of sample i
(photoreg.lighting.albedo; one region when cfg.albedo = "single", which is the paper's model).
The fit alternates, at most cfg.iterations times and until F moves less than cfg.tolerance (relative):
  1. F given albedos and weights: per channel the weighted Tikhonov system
     (G_c + lam_c I) f = g_c + lam_c f_prior, G_c = sum_i w_i rho_ic^2 R_i R_i^T, g_c = sum_i w_i rho_ic I_ic R_i,
     lam_c = regularization * trace(G_c) / K (relative, as in the paper's solver); with cfg.albedo_step
     "joint" taken as a joint Gauss-Newton step in F and the albedos of all regions but the largest
     (_with_albedo_columns): alternating F and albedos alone creeps along the direction in which brighter
     albedos trade against more light;
  2. albedos given F, in closed form per region and channel: rho = sum w I S / sum w S^2 (S = R.F),
     then the scale fix (albedo.reference_scale) moves the common factor into F; regions whose
     albedos the data cannot tell apart are merged. At the third alternation the regions are
     found again on the albedo estimates I / S (shading divided out; albedo.py), a region whose residual
     says it mixes surfaces of different albedo is split by geometry (_split_mixed), and with a traced light
     the floor's colour regions that lie in its shadow join the floor (albedo.join_shadows);
  3. robust weights from the luminance residuals e_i scaled by 1.4826 * MAD (cfg.loss: Huber or
     Tukey's biweight): specular highlights, unexplained shadows, colour-depth misalignment and stray
     normals stop pulling the estimate.
Sample weights are the normal-distribution weights (solver.normal_weights, counted per first-pass colour
region with cfg.region_weights) times the robust weights.

Extra terms (Term): known per-sample columns t_j with one unregularised coefficient e_j >= 0 per channel,
I_i = rho * (R_i . F + sum_j e_j t_ij); the SH part keeps the Tikhonov term. Two are used:
  * the dominant light traced exactly (photoreg.lighting.sun): t = mean over its disc of V max(n.w, 0) / pi,
    e its integrated radiance. Hard shadows that a few SH bands cannot hold are then explained by e, not by
    bending the low bands; its SH (the disc's) is added to the returned lighting, which stays one SH;
  * one bounce (interreflection): t = (1/pi) integral (1 - V) max(n.w, 0) dw, the share of the hemisphere
    that real geometry blocks, e the radiance those blocked directions see. Without it the light a floor
    throws onto the sides of objects (+20-110% on the generated tabletop's vertical faces, measured with the
    true lighting and albedos) is taken for sunlight or distant light from the horizon. It is local, so it
    adds no SH. One e for every blocked direction, at most the median radiance of the frame's samples
    (what the surfaces around show; unbounded it took 0.9 on the generated corner, whose median is 0.6,
    and cost accuracy there: si-RMSE 0.26 against 0.20 bounded). With lighting.bounce_observed the directions
    whose hit point the camera has seen get the observed radiance instead (photoreg.lighting.bounce: a third
    term), and this one keeps the rest.

Order selection (cfg.select): the band count B in 1..cfg.max_bands and the regularisation in
cfg.lambdas are chosen per frame on the converged weights and albedos by GCV, K-fold held-out
residual (spatial folds when points are given), AIC or BIC. The systems for fewer bands are leading
blocks of G, so every candidate costs one small eigen-decomposition.

K x K normal equations (not the SVD of the solver module): the design changes every iteration and
the temporal filter needs G anyway; conditioning is checked (diagnostics) and directions with no
information keep the prior exactly (eigenvalue cut-off), as in solver.regularized_lstsq.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg.lapack import dpotrf as _potrf, dpotrs as _potrs
from scipy.spatial import cKDTree

from ..types import Lighting, SolveDiagnostics
from . import albedo as alb
from . import sh
from .solver import SolverConfig, conditioning, normal_weights, select_samples

TUNING = {"huber": 1.345, "tukey": 4.685}  # 95% efficiency at Gaussian noise
MERGE_LOG_TOLERANCE = 0.1   # regions whose albedos differ by < ~10% in every channel are one region
SECOND_PASS = 2             # iteration at which regions are found again on albedo estimates
FOLDS = 5                   # K-fold count of select = "holdout"
FOLD_CELL = 0.1             # metres: spatial fold cells, so held-out samples are not neighbours of fitted ones
AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
OBSERVED = 0.5              # a normal's irradiance counts as observed when the data resolve this share of it
COVERAGE_NORMALS = sh.fibonacci_sphere(256)
MIXED_FACTOR = 2.0          # a region is mixed (_split_mixed) when its median relative residual is over this
MIXED_MIN = 0.1             # ... times the frame's median and over this
MIN_DOF = 2.0               # fewer resolved combinations (one plane resolves ~1): band-0 fallback


def loss_weights(u: np.ndarray, loss: str, c: float) -> np.ndarray:
    """IRLS weights psi(u)/u of scaled residuals u: 1 (none), Huber min(1, c/|u|), Tukey (1-(u/c)^2)^2."""
    a = np.abs(u)
    if not np.isfinite(a).all():  # NaN counts as infinitely far, an infinite residual as the largest float
        a = np.where(np.isnan(a), np.inf, np.minimum(a, np.finfo(np.float64).max))
    if loss == "huber":  # min(1, c / a) is 1 for a <= c (also a = 0) and c / a above
        with np.errstate(divide="ignore", over="ignore"):
            return np.minimum(1.0, c / a)
    if loss == "tukey":
        return np.where(a < c, (1.0 - (a / c) ** 2) ** 2, 0.0)
    return np.ones_like(a)


def robust_scale(r: np.ndarray, w: np.ndarray) -> float:
    """1.4826 * median |r| over samples with weight > 0 (the RMS when the median is 0, tiny if all are 0)."""
    a = np.abs(r[w > 0])
    if a.size == 0:
        return 1.0
    s = 1.4826 * alb.median(a)
    return s if s > 0 else float(np.sqrt(np.mean(a * a))) or 1e-300


@dataclass
class NormalEquations:
    """A frame's weighted least-squares system per channel c at `bands`:
    SSE_c(f) = f^T G_c f - 2 g_c^T f + c0_c, with `lam` (3,) the absolute Tikhonov strength used and
    `sigma2` the residual variance of the fit, so that (G + lam I) / sigma2 is the estimate's precision."""

    G: np.ndarray      # (3, K, K)
    g: np.ndarray      # (3, K)
    c0: np.ndarray     # (3,)
    lam: np.ndarray    # (3,)
    sigma2: float
    n: int

    @property
    def bands(self) -> int:
        return sh.bands_of(self.G.shape[1])

    def sse(self, F: np.ndarray) -> float:
        """Weighted sum of squared residuals of lighting F (3, >= K) on this frame's samples."""
        f = np.asarray(F, dtype=np.float64)[:, :self.G.shape[1]]
        return float(sum(f[c] @ self.G[c] @ f[c] - 2 * self.g[c] @ f[c] + self.c0[c] for c in range(3)))

    def precision(self) -> np.ndarray:
        """(3, K, K) inverse covariance of the frame's estimate, data plus its Tikhonov term."""
        eye = np.eye(self.G.shape[1])
        return (self.G + self.lam[:, None, None] * eye) / max(self.sigma2, 1e-300)

    def noise_free_fit(self, L: np.ndarray, lam_scale: float = 1.0) -> np.ndarray:
        """(3, K) the Tikhonov solution (G + s lam I)^-1 G L of this system (its samples, weights and albedos)
        for data that lighting L (3, >= K) explains exactly, with the strength scaled by s = lam_scale: what
        the fit can recover at best, since directions the samples do not observe stay at the prior (zero)."""
        k = self.G.shape[1]
        L = np.asarray(L, dtype=np.float64)[:, :k]
        eye = np.eye(k)
        return np.stack([np.linalg.lstsq(self.G[c] + lam_scale * self.lam[c] * eye, self.G[c] @ L[c], rcond=None)[0]
                         for c in range(3)])


@dataclass
class Solution:
    """A frame's lighting, its diagnostics, the system for the temporal filter (None without samples)
    and the per-region albedos (largest region first)."""

    lighting: Lighting
    diagnostics: SolveDiagnostics
    system: NormalEquations | None
    albedo: np.ndarray
    terms: dict = field(default_factory=dict)   # name -> (3,) e of each extra term
    samples: np.ndarray | None = None           # indices of the fitted samples in the inputs ...
    labels: np.ndarray | None = None            # ... their albedo regions (-1: none) ...
    weights: np.ndarray | None = None           # ... and final weights (normal x robust), for the sun search
    current_system: NormalEquations | None = None  # `system` over the current view's rows alone (solve's `current`)
    setup: "_Setup | None" = None               # what a later solve on the same samples reuses (solve's `start`)
    # where the band-0 fallback replaced the fit in `lighting`: the regularised fit of every band that `system`
    # describes (the temporal filter fuses it once it holds an estimate: the fallback's band 0 alone disagrees
    # with the data wherever they resolve more than the plane's irradiance)
    measured: np.ndarray | None = None


@dataclass
class _Setup:
    """The parts of a solve that depend only on its samples and on settings that the joint solve with a traced
    light does not change: the normal-distribution weights and the first-pass (colour) albedo regions."""

    key: tuple           # the settings they were computed with (_setup_key)
    samples: np.ndarray  # indices of the fitted samples
    w0: np.ndarray       # normal_weights of the samples, per first-pass region (before any hold-out)
    labels: np.ndarray | None  # the first-pass regions (None: one albedo)
    clipped: np.ndarray        # which of the samples are clipped (solve's `clipped`)


def _setup_key(cfg: SolverConfig, min_count: int) -> tuple:
    return (cfg.weighting, cfg.grid_bins, cfg.density_bandwidth, cfg.bin_min_fraction, cfg.seed, cfg.albedo,
            cfg.chroma_bandwidth, min_count, cfg.region_weights)


@dataclass
class Term:
    """An extra term of the model (module docstring): its per-sample column (N,) and, for a distant light,
    its SH (B*B,) per unit of e (added to the returned lighting); None for a local term."""

    name: str
    transfer: np.ndarray
    sh: np.ndarray | None = None
    upper: np.ndarray | None = None   # (3,) largest e per channel (None: unbounded)


def bounce_term(transfer: np.ndarray, radiance: np.ndarray, blocked: np.ndarray | None = None) -> Term:
    """The one-bounce term, its column the share of the hemisphere that real geometry blocks (from the
    transfer's band 0, sh.blocked_share; or `blocked` (N,) where given: photoreg.lighting.bounce's directions
    whose hit no sample has seen), its radiance bounded by the median of the observed sample radiance (N, 3)
    (module docstring)."""
    rad = np.asarray(radiance, dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(rad).all(axis=1)
    upper = np.array([alb.median(c) for c in rad[ok].T]) if ok.any() else np.zeros(3)
    column = sh.blocked_share(transfer)[:, 0] if blocked is None else np.asarray(blocked, dtype=np.float64)
    return Term("bounce", column, upper=upper)


def _factor(G: np.ndarray, lam_rel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigen-factors of the Tikhonov systems G + lam I (G (..., K, K), one per channel), lam = lam_rel *
    trace(G) / K: (V, 1 / (e + lam) with 0 for zero-information directions, lam (...)). One factor serves
    every right-hand side of a channel."""
    k = G.shape[-1]
    lam = lam_rel * np.trace(G, axis1=-2, axis2=-1) / k
    e, V = np.linalg.eigh(G)
    e = np.maximum(e, 0.0)
    tiny = np.maximum(e.max(axis=-1, keepdims=True), 0.0) * k * 1e-13
    denom = e + lam[..., None]
    inv = np.divide(1.0, denom, out=np.zeros_like(denom), where=(e > tiny) & (denom > 0))
    return V, inv, lam


def _tikhonov(G: np.ndarray, lam_rel: float):
    """(H, lam): H(rhs) = (G_c + lam_c I)^+ rhs_c per channel c for rhs (3, K, j), with _factor's eigenvalue
    cut-off, and lam (3,). When every G_c - t I is positive definite (t = K * 1e-13 * trace(G_c), at least
    _factor's cut-off) nothing is cut and Cholesky factors give the same solution (up to rounding) about ten
    times faster than the eigen-decomposition; otherwise _factor's."""
    k = G.shape[-1]
    lam = lam_rel * np.trace(G, axis1=-2, axis2=-1) / k
    eye = np.eye(k)
    factors = []
    if np.isfinite(G).all() and np.all(lam > 0):
        for c in range(G.shape[0]):
            t = k * 1e-13 * float(np.trace(G[c]))
            if _potrf(G[c] - t * eye, lower=1, clean=0)[1] != 0:
                break
            L, info = _potrf(G[c] + lam[c] * eye, lower=1, clean=0)
            if info != 0:
                break
            factors.append(L)
    if len(factors) == G.shape[0]:
        def solve_chol(rhs):
            return np.stack([_potrs(L, rhs[c], lower=1)[0] for c, L in enumerate(factors)])
        return solve_chol, lam
    V, inv, lam = _factor(G, lam_rel)

    def solve_eig(rhs):
        return V @ (inv[..., None] * (np.swapaxes(V, 1, 2) @ rhs))
    return solve_eig, lam


@dataclass
class _Regions:
    """The samples sorted by albedo region (labels -1 left out), so that the per-region sums of the IRLS
    iterations are contiguous slices; built once per label assignment, then grams(w) for each new weighting.
    With `base` weights (the normal weights: robust weights only lower them) the sums at the base weights are
    kept and grams(w) subtracts those of the rows whose weight fell (the outliers; Huber leaves most at 1)."""

    A: np.ndarray        # (n, K') sorted rows of the design
    I: np.ndarray        # (n, 3) their radiance
    idx: np.ndarray      # (n,) their indices in the unsorted samples
    bounds: np.ndarray   # (m + 1,) region r is rows bounds[r]:bounds[r + 1]
    I2: np.ndarray | None = None   # (n, 3) I * I (c0's summands; filled in by of())
    base: tuple | None = None      # (sorted base weights, their sums (G, h, c0))

    @classmethod
    def of(cls, A: np.ndarray, I: np.ndarray, labels: np.ndarray, m: int, base=None) -> "_Regions":
        idx = np.flatnonzero(labels >= 0)
        idx = idx[np.argsort(labels[idx], kind="stable")]
        Is = np.take(I, idx, axis=0)  # take: several times faster than fancy indexing of rows
        reg = cls(np.take(A, idx, axis=0), Is, idx, np.searchsorted(labels[idx], np.arange(m + 1)), Is * Is)
        if base is not None:
            ws = np.take(base, idx)
            reg.base = (ws, reg._sums(ws, np.arange(idx.size), reg.bounds))
        return reg

    def _sums(self, ws: np.ndarray, rows: np.ndarray, bounds: np.ndarray):
        """Per-region sums over the sorted `rows` (ascending; region r is rows[bounds[r]:bounds[r + 1]]) with
        their weights ws (len(rows),)."""
        m, k = len(bounds) - 1, self.A.shape[1]
        full = rows.size == self.idx.size
        A = self.A if full else np.take(self.A, rows, axis=0)
        I = self.I if full else np.take(self.I, rows, axis=0)
        I2 = self.I2 if full else np.take(self.I2, rows, axis=0)
        Aw = A * ws[:, None]
        G, h = np.empty((m, k, k)), np.empty((m, 3, k))
        for r in range(m):
            a, b = bounds[r], bounds[r + 1]
            np.matmul(Aw[a:b].T, A[a:b], out=G[r])
            np.matmul(I[a:b].T, Aw[a:b], out=h[r])
        return G, h, ws @ I2

    def grams(self, w: np.ndarray):
        """Per-region sums G_m = sum w R R^T (m, K, K), h_m = sum w I R (m, 3, K) and c0 = sum w I^2 (3,)
        for sample weights w (unsorted, (N,))."""
        ws = np.take(w, self.idx)
        if self.base is not None:
            wb, (Gb, hb, cb) = self.base
            d = wb - ws
            rows = np.flatnonzero(d)
            if 2 * rows.size < ws.size:   # fewer rows changed than not: subtract theirs from the base sums
                Gd, hd, cd = self._sums(np.take(d, rows), rows, np.searchsorted(rows, self.bounds))
                return Gb - Gd, hb - hd, cb - cd
        return self._sums(ws, np.arange(self.idx.size), self.bounds)


def _grams(A: np.ndarray, I: np.ndarray, w: np.ndarray, labels: np.ndarray, m: int):
    """Per-region sums of _Regions.grams for one weighting."""
    return _Regions.of(A, I, labels, m).grams(w)


def _counts(labels: np.ndarray, w: np.ndarray, m: int) -> np.ndarray:
    """Total weight of each of the m regions (labels -1 count for none)."""
    return np.bincount(labels + 1, weights=w, minlength=m + 1)[1:]   # -1 counted in the dropped bin 0


def _channel_systems(Gm, hm, c0, rho):
    """Per-channel G_c = sum_m rho_mc^2 G_m, g_c = sum_m rho_mc h_mc: (3, K, K), (3, K), c0."""
    G = np.einsum("mc,mij->cij", rho * rho, Gm)
    g = np.einsum("mc,mci->ci", rho, hm)
    return G, g, c0


def _with_albedo_columns(G, g, Gm, hm, rho, F):
    """The F step's system (3, K', K'), (3, K') augmented for a joint Gauss-Newton step in F and the albedos of
    regions 1..m-1 around (F, rho) (region 0, the largest, keeps its albedo: it fixes the scale). Linearised,
    rho_r (a.F) ~ rho_r0 (a.F) + (rho_r - rho_r0) s with s = a.F0: the albedo columns are s, with target
    I + rho_r0 s (without it F still moved 1% per alternation after 12 on the generated tabletop). Returns
    the augmented (G, g); the new columns are unregularised extra terms with rho >= 0."""
    GF = np.einsum("mij,cj->mci", Gm[1:], F)          # (m-1, 3, K'): sum_r w a s
    D = np.einsum("mci,ci->cm", GF, F)                 # (3, m-1): sum_r w s^2
    r1 = rho[1:].T                                     # (3, m-1)
    U = np.transpose(GF, (1, 2, 0)) * r1[:, None, :]   # (3, K', m-1)
    n, q = G.shape[1], rho.shape[0] - 1
    Ga = np.zeros((3, n + q, n + q))
    Ga[:, :n, :n], Ga[:, :n, n:], Ga[:, n:, :n] = G, U, np.transpose(U, (0, 2, 1))
    Ga[:, n + np.arange(q), n + np.arange(q)] = D
    ga = np.concatenate([g + np.einsum("cim,cm->ci", U, r1), np.einsum("mci,ci->cm", hm[1:], F) + r1 * D], axis=1)
    return Ga, ga


def _solve_channels(G, g, lam_rel, prior, n_extra: int = 0, upper=None):
    """Per-channel Tikhonov solutions (3, K) and absolute lambdas (3,). The system's last n_extra columns are
    extra terms: unregularised, 0 <= e <= upper (n_extra, 3) (active set: a negative e leaves, one above its
    bound is fixed there), the SH part f = f0 - H U e eliminated exactly (f0 the SH-only solution, H the
    regularised inverse, U the coupling); returned as F's last n_extra coefficients."""
    k = G.shape[1] - n_extra
    Gs = G[:, :k, :k]
    regularised_inverse, lams = _tikhonov(Gs, lam_rel)
    f0 = prior + regularised_inverse((g[:, :k] - np.einsum("cij,cj->ci", Gs, prior))[..., None])[..., 0]
    if not n_extra:
        return f0, lams
    U = G[:, :k, k:]                                                   # (3, k, p) coupling
    HU = regularised_inverse(U)
    M = G[:, k:, k:] - np.swapaxes(U, 1, 2) @ HU                       # (3, p, p) Schur complements
    r = g[:, k:] - (np.swapaxes(U, 1, 2) @ f0[..., None])[..., 0]     # (3, p)
    diag = np.diagonal(M, axis1=1, axis2=2)
    active = diag > 1e-12 * np.maximum(np.diagonal(G[:, k:, k:], axis1=1, axis2=2), 1e-300)
    ub = np.full((3, n_extra), np.inf) if upper is None else np.asarray(upper, dtype=np.float64).T
    if n_extra == 1:  # the active set in closed form: e = r / M within [0, ub], 0 when inactive
        e = np.where(active, np.minimum(np.maximum(r / np.where(active, M[:, :, 0], 1.0), 0.0), ub), 0.0)
    else:
        e = np.array([_active_set(M[c], r[c], active[c], ub[c]) for c in range(3)])
    e = np.clip(e, 0.0, ub)
    F = np.concatenate([f0 - (HU @ e[..., None])[..., 0], e], axis=1)
    return F, lams


def _active_set(M: np.ndarray, r: np.ndarray, active: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Extra-term coefficients e (p,) of one channel minimising e^T M e - 2 r^T e with 0 <= e <= ub over the
    `active` terms (others 0): a negative e leaves the active set, the one most above its bound is fixed there.
    On Python floats (p is 2 or 3: numpy's per-call overhead was most of the solve's time here)."""
    p = len(r)
    Ml, rl, ubl, act = M.tolist(), r.tolist(), ub.tolist(), active.tolist()
    e, fixed = [0.0] * p, [False] * p
    while any(act):
        free = [i for i in range(p) if act[i] and not fixed[i]]
        e = [e[i] if fixed[i] else 0.0 for i in range(p)]
        if free:
            rr = [rl[i] - sum(Ml[i][j] * e[j] for j in range(p) if fixed[j]) for i in free]
            for i, v in zip(free, _small_lstsq([[Ml[i][j] for j in free] for i in free], rr)):
                e[i] = v
        if any(e[i] < 0 for i in free):
            act[min(free, key=lambda i: e[i])] = False   # the first smallest, as argmin
            continue
        over = [i for i in free if e[i] > ubl[i]]
        if not over:
            break
        j = max(over, key=lambda i: e[i] - ubl[i])       # the first largest, as argmax
        fixed[j], e[j] = True, ubl[j]
    return np.array(e)


def _small_lstsq(M: list, r: list) -> list:
    """lstsq(M, r) of a tiny system: 1 x 1 and well-conditioned 2 x 2 in closed form, else numpy's."""
    if len(r) == 1:
        return [r[0] / M[0][0] if M[0][0] != 0 else 0.0]
    if len(r) == 2:
        (a, b), (c, d) = M
        det = a * d - b * c
        if abs(det) > 1e-8 * max(abs(a), abs(b), abs(c), abs(d)) ** 2:
            return [(d * r[0] - b * r[1]) / det, (a * r[1] - c * r[0]) / det]
    return np.linalg.lstsq(np.array(M), np.array(r), rcond=None)[0].tolist()


def _prior_scale(F: np.ndarray, prior: np.ndarray, G: np.ndarray) -> np.ndarray | None:
    """Per-channel s minimising |s F_c - prior_c| in the data metric G_c: keeps the albedo scale (and so
    the colour balance) of the previous frames; None when the prior has no observed component."""
    s = np.ones(3)
    for c in range(3):
        ff, fp = F[c] @ G[c] @ F[c], F[c] @ G[c] @ prior[c]
        if not (ff > 0 and fp > 0):
            return None
        s[c] = fp / ff
    return s


def _region_albedos(Gm, hm, F) -> np.ndarray:
    """Closed-form albedo (m, 3) of each region given F from the per-region sums of _Regions.grams:
    rho = sum w I S / sum w S^2 with S = A.F, i.e. h.F / F^T G F; NaN where undefined."""
    return _albedo_ratio(np.einsum("mci,ci->mc", hm, F), np.einsum("ci,mij,cj->mc", F, Gm, F))


def _albedo_ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """Albedos num / den (sum w I S / sum w S^2), NaN where undefined."""
    return np.where((den > 0) & (num > 0), num / np.maximum(den, 1e-300), np.nan)


def _albedo_step(Gm, hm, F, counts, cfg: SolverConfig, prior=None, G=None, term_sh=None):
    """Closed-form region albedos given F (_region_albedos), scale-fixed by the prior (when it has an observed
    component) or else by cfg's albedo_reference rule and reference_albedo over the regions' weights `counts`; returns
    (rho (m, 3), per-channel scale to move into F). With extra terms (term_sh: their SH rows) the prior is
    compared with F's SH equivalent (_as_sh)."""
    rho = _region_albedos(Gm, hm, F)
    ok = np.isfinite(rho)
    if not ok.all():
        fill = np.array([alb.median(rho[ok[:, c], c]) if ok[:, c].any() else 1.0 for c in range(3)])
        rho = np.where(ok, rho, fill)
    scale = None
    if prior is not None and prior.any():
        scale = _prior_scale(_as_sh(F, term_sh), prior, G[:, :prior.shape[1], :prior.shape[1]])
    if scale is None:
        scale = alb.reference_scale(rho, counts, cfg.albedo_reference, cfg.reference_albedo)
    return rho / scale, scale


def _albedo_sums(regions: "_Regions", Gm, hm, w: np.ndarray, clip: np.ndarray):
    """The per-region sums (G_m, h_m) that estimate albedos: the fit's own (`Gm`, `hm` at weights w) without the
    clipped samples' rows (a saturated colour is no measure of the albedo)."""
    return (Gm, hm) if not clip.any() else regions.grams(w * ~clip)[:2]


def _as_sh(F: np.ndarray, term_sh: np.ndarray | None) -> np.ndarray:
    """SH (3, K) of a solution: F itself, or with extra terms (term_sh (p, K), zero rows for local terms)
    its SH part plus sum_j e_j * term j's SH."""
    if term_sh is None:
        return F
    k = F.shape[1] - term_sh.shape[0]
    return F[:, :k] + F[:, k:] @ term_sh[:, :k]


def _folds(n: int, points: np.ndarray | None, seed: int) -> np.ndarray:
    """Fold index per sample: FOLDS spatial folds of FOLD_CELL cells when points are given, else random."""
    if points is not None and np.isfinite(points).all():
        cell = np.floor(points / FOLD_CELL).astype(np.int64)
        key = (cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663) ^ (cell[:, 2] * 83492791)
        return np.abs(key + seed) % FOLDS
    return np.random.default_rng(seed).integers(0, FOLDS, n)


def _criterion(select: str, sse: float, dof: float, n: int) -> float:
    """GCV, AIC or BIC score (lower is better) of a fit with residual `sse` and `dof` degrees of freedom."""
    if select == "gcv":
        return n * sse / max(n - dof, 1.0) ** 2
    penalty = 2.0 if select == "aic" else math.log(max(n, 2))
    return n * math.log(max(sse / n, 1e-300)) + penalty * dof


def select_order(A, I, w, labels, rho, cfg: SolverConfig, prior: np.ndarray, points=None) -> tuple[int, float]:
    """(bands, relative lambda) minimising cfg.select's criterion over 1..cfg.max_bands x cfg.lambdas."""
    m = rho.shape[0]
    Gm, hm, c0 = _grams(A, I, w, labels, m)
    G, g, _ = _channel_systems(Gm, hm, c0, rho)
    n = int((w > 0).sum())
    if cfg.select == "holdout":
        fold = _folds(len(I), points, cfg.seed)
        parts = [_channel_systems(*_grams(A, I, w * (fold == k), labels, m), rho) for k in range(FOLDS)]
    best, best_score = (1, cfg.lambdas[0]), math.inf
    for b in range(1, cfg.max_bands + 1):
        k = b * b
        if 3 * k >= max(n, 1):
            break
        for lam_rel in cfg.lambdas:
            if cfg.select == "holdout":
                score = 0.0
                for Gf, gf, cf in parts:
                    Gt, gt = G[:, :k, :k] - Gf[:, :k, :k], g[:, :k] - gf[:, :k]
                    f, _ = _solve_channels(Gt, gt, lam_rel, prior[:, :k])
                    score += sum(f[c] @ Gf[c, :k, :k] @ f[c] - 2 * gf[c, :k] @ f[c] + cf[c] for c in range(3))
            else:
                f, lams = _solve_channels(G[:, :k, :k], g[:, :k], lam_rel, prior[:, :k])
                sse = sum(f[c] @ G[c, :k, :k] @ f[c] - 2 * g[c, :k] @ f[c] + c0[c] for c in range(3))
                dof = 0.0
                for c in range(3):
                    e = np.maximum(np.linalg.eigvalsh(G[c, :k, :k]), 0.0)
                    dof += float(np.sum(e / np.maximum(e + lams[c], 1e-300)))
                score = _criterion(cfg.select, max(sse, 0.0), dof, 3 * n)
            if score < best_score:
                best, best_score = (b, lam_rel), score
    return best


def coverage(G: np.ndarray, lam: float) -> tuple[list[str], float]:
    """Axis directions whose irradiance the system G (K, K) with Tikhonov lam leaves undetermined, and
    the share of the sphere's normals that it determines: irradiance at normal n is the functional
    e(n) = A_l Y_lm(n); it counts as observed when the resolution matrix V e/(e + lam) V^T keeps
    >= OBSERVED of |e(n)|^2."""
    b = sh.bands_of(G.shape[0])
    ev, V = np.linalg.eigh(G)
    ev = np.maximum(ev, 0.0)
    tiny = max(float(ev.max()), 0.0) * G.shape[0] * 1e-13
    filt = np.where(ev > tiny, ev / np.maximum(ev + lam, 1e-300), 0.0)
    e_axes, e_sphere = _irradiance_functionals(b)

    def observed(e):
        proj = e @ V
        return (proj * proj * filt).sum(axis=1) / np.maximum((e * e).sum(axis=1), 1e-300)

    axes = observed(e_axes)
    missing = [name for name, o in zip(AXES, axes) if o < OBSERVED]
    return missing, float(np.mean(observed(e_sphere) >= OBSERVED))


@functools.lru_cache(maxsize=8)
def _irradiance_functionals(b: int) -> tuple[np.ndarray, np.ndarray]:
    """coverage()'s functionals e(n) = A_l Y_lm(n) at the AXES and at COVERAGE_NORMALS for b bands (fixed)."""
    lobe = sh.cosine_lobe(b)
    return (sh.sh_basis(np.array(list(AXES.values()), dtype=np.float64), b) * lobe,
            sh.sh_basis(COVERAGE_NORMALS, b) * lobe)


def _split_mixed(labels, A, I, F, w, points, normals, min_count: int) -> np.ndarray:
    """Regions whose median relative luminance residual (own closed-form albedo, lighting F) is over
    MIXED_FACTOR times the median over all samples and over MIXED_MIN hold surfaces of different albedo that
    colour alone did not separate: split them by geometry (albedo.split_by_geometry). On the generated
    tabletop a near-grey white box and the sky-tinted shadowed floor around it shared one chroma region
    (median residual 0.26 against <= 0.10 for every other region); its albedo set the green and blue of the
    'max' reference, and the later frames keep frame 0's colour balance. Split (box alone, the shadowed floor
    joined to the floor), tabletop si-RMSE 0.155 -> 0.139, colour 3.3 -> 1.2 deg (medians over 12 frames)."""
    m = int(labels.max()) + 1
    if m < 2:
        return labels
    ok = np.flatnonzero(labels >= 0)
    ok = ok[np.argsort(labels[ok], kind="stable")]    # by region: each region's residuals are one slice
    lab, Io = labels[ok], np.take(I, ok, axis=0)
    S = np.take(A, ok, axis=0) @ F.T
    # _region_albedos from per-sample sums (h.F = sum w I S, F^T G F = sum w S^2): no per-region K x K sums
    wS = w[ok, None] * S
    rho = np.nan_to_num(_albedo_ratio(alb.index_sums(lab, wS * Io, m), alb.index_sums(lab, wS * S, m)), nan=0.0)
    rel = np.abs((Io - rho[lab] * S) @ sh.LUMINANCE) / np.maximum(np.abs(Io @ sh.LUMINANCE), 1e-12)
    limit = max(MIXED_FACTOR * alb.median(rel), MIXED_MIN)
    bounds = np.searchsorted(lab, np.arange(m + 1))
    flagged = [r for r in range(m) if bounds[r + 1] > bounds[r] and alb.median(rel[bounds[r]:bounds[r + 1]]) > limit]
    return alb.split_by_geometry(labels, flagged, points, normals, min_count) if flagged else labels


def _with_clipped(labels: np.ndarray, clipped: np.ndarray, points: np.ndarray | None) -> np.ndarray:
    """`labels` with every clipped sample in the region of its nearest unclipped labelled sample in space (a
    saturated colour says nothing of the albedo); -1 for them without points, all in region 0 when no sample is
    labelled (a saturated frame: one unknown albedo)."""
    if not clipped.any():
        return labels
    out = np.where(clipped, -1, labels)
    src = np.flatnonzero(out >= 0)
    if src.size == 0:
        return np.where(clipped, 0, out)
    if points is not None:
        out[clipped] = out[src[cKDTree(points[src]).query(points[clipped])[1]]]
    return out


def _first_regions(I: np.ndarray, clipped: np.ndarray, points: np.ndarray | None, cfg: SolverConfig,
                   min_count: int) -> np.ndarray:
    """First-pass (colour) albedo regions of the unclipped samples; the clipped ones join their neighbours'
    (_with_clipped)."""
    labels = -np.ones(len(I), dtype=np.int64)
    labels[~clipped] = alb.cluster(alb.colour_features(I[~clipped], with_intensity=False), cfg.chroma_bandwidth,
                                   min_count)
    return _with_clipped(labels, clipped, points)


def _lit(columns: np.ndarray, terms: list[Term]) -> np.ndarray | None:
    """Samples (N,) that the distant-light terms (a traced light) reach: a column over half the median of its
    positive values (the penumbra's outer half counts as shadow); None without such a term."""
    lit = None
    for j, term in enumerate(terms):
        if term.sh is None:
            continue
        col = columns[:, j]
        pos = col[col > 0]
        on = col > 0.5 * alb.median(pos) if pos.size else np.zeros(col.size, dtype=bool)
        lit = on if lit is None else lit | on
    return lit


def solve(radiance, transfer, normals, visible, cfg: SolverConfig, prior=None, mask=None,
          points=None, reference=None, terms: list[Term] | None = None, start: Solution | None = None,
          current: int | None = None, clipped=None) -> Solution:
    """Robust lighting of one frame (module docstring). Inputs as solver.solve_lighting, plus optional
    world `points` (N, 3) for spatial hold-out folds and `reference` (3, B'*B'), the previous lighting:
    its colour balance fixes the albedo scale (instead of cfg.albedo_reference) and it is returned
    when the frame has no usable samples. (A `prior` is also the Tikhonov target; regularising every
    frame toward the previous one lets the weakly observed directions drift to the biased
    least-squares values, so the pipeline passes the previous lighting as `reference` and fuses
    frames in photoreg.lighting.temporal instead.) Shapes that do not match raise ValueError; data
    problems give a finite, weak result with notes. `terms`: extra terms solved with the SH (module
    docstring; they need cfg.select = "fixed"). `start`: a solution of the same inputs with other terms or another
    regularisation (the pipeline's solve before the traced light is added): its sample weights and first-pass
    (colour) albedo regions are reused when it fitted the same samples with the same settings (same result,
    less work). `current`: the inputs' first `current` rows are the current view's, the rest earlier views' (the
    pipeline's history): Solution.current_system then holds the normal equations over the current view's rows
    alone, for the temporal filter's change test. `clipped` (N,) bool: samples whose colour saturated
    (lighting.censored), censored observations: their radiance is a lower bound, so they are kept whatever
    cfg.saturation_level says; at every iteration a clipped sample's value is the larger of what it shows and what
    the fit predicts (no residual where the fit predicts more, a pull up where it predicts less: the censored fit by
    imputation), and it neither finds nor estimates albedo regions (it takes its nearest neighbour's region). Left
    out, the sunlit surfaces a camera saturates went missing from the fit and took the sun's share with them
    (benchmarks/lighting_accuracy.md, "Saturated pixels as lower bounds")."""
    b_fit = cfg.fit_bands
    k_fit = b_fit * b_fit
    radiance, transfer, normals, idx, prior, notes = select_samples(radiance, transfer, normals, visible, cfg,
                                                                    b_fit, prior, mask, clipped)
    prior_fit = prior if prior is not None else np.zeros((3, k_fit))
    if reference is not None:
        reference = sh.truncate(np.asarray(reference, dtype=np.float64), b_fit)
        if reference.shape[0] != 3 or not np.isfinite(reference).all():
            notes.append("reference ignored (not a finite 3-channel SH)")
            reference = None
    ref_F = reference if reference is not None else prior
    n = idx.size
    if n == 0:
        b_out = cfg.bands if cfg.select == "fixed" else 1
        back = ref_F if ref_F is not None else prior_fit
        notes.append("no usable samples: returning the " + ("previous lighting" if ref_F is not None
                                                             else "zero lighting"))
        return Solution(Lighting(sh.truncate(back, b_out)),
                        SolveDiagnostics(n_samples=0, weak=True, notes=notes, bands=b_out), None, np.ones((1, 3)))
    # np.take: several times faster than fancy indexing of rows
    A, I, nrm = (np.take(x, idx, axis=0) for x in (transfer, radiance, normals))
    clip = np.zeros(n, dtype=bool) if clipped is None else np.asarray(clipped, dtype=bool)[idx]
    terms = list(terms or [])
    p = len(terms)
    tsh = None
    if terms:
        if cfg.select != "fixed":
            raise ValueError(f"extra terms need select = 'fixed', got {cfg.select!r}")
        cols, tsh = [], np.zeros((p, k_fit))
        for j, term in enumerate(terms):
            col = np.asarray(term.transfer, dtype=np.float64).reshape(-1)
            if col.shape[0] != radiance.shape[0] or (term.sh is not None and np.shape(term.sh)[-1] < k_fit):
                raise ValueError(f"term {term.name!r}: needs {radiance.shape[0]} transfers and >= {k_fit} SH "
                                 f"coefficients (got {col.shape[0]}, {None if term.sh is None else np.shape(term.sh)})")
            cols.append(np.nan_to_num(col[idx], nan=0.0, posinf=0.0, neginf=0.0))
            if term.sh is not None:
                tsh[j] = np.asarray(term.sh, dtype=np.float64)[:k_fit]
        A = np.hstack([A, np.stack(cols, axis=1)])
    ub = np.array([t.upper if t.upper is not None else np.full(3, np.inf) for t in terms]) if terms else None
    lit = _lit(A[:, A.shape[1] - p:], terms)
    pts = None if points is None else np.take(np.asarray(points, dtype=np.float64).reshape(-1, 3), idx, axis=0)
    min_count = max(int(cfg.min_region_fraction * n), 3)
    key = _setup_key(cfg, min_count)
    setup = start.setup if start is not None else None
    if (setup is None or setup.key != key or not np.array_equal(setup.samples, idx)
            or not np.array_equal(setup.clipped, clip)):
        first = _first_regions(I, clip, pts, cfg, min_count) if cfg.albedo == "regions" else None
        setup = _Setup(key, idx, normal_weights(nrm, cfg, first), first, clip)
    w0 = setup.w0
    held = np.zeros(n, dtype=bool)
    if cfg.holdout_fraction > 0 and n >= 20:
        held = _folds(n, pts, cfg.seed + 1) < round(cfg.holdout_fraction * FOLDS)
        w0 = np.where(held, 0.0, w0)

    labels = np.zeros(n, dtype=np.int64)
    if cfg.albedo == "regions":
        found = setup.labels
        if (found >= 0).any():
            labels = found.copy()
    m = int(labels.max()) + 1
    rho = np.ones((m, 3))
    rw = np.ones(n)
    F = np.hstack([prior_fit, np.zeros((3, p))])
    censored = bool(clip.any())
    I_shown = I
    iterations = cfg.iterations if (cfg.loss != "none" or cfg.albedo == "regions" or censored) else 1
    c = cfg.loss_scale or TUNING.get(cfg.loss, 1.0)
    F_last, regions = F, _Regions.of(A, I, labels, m, w0)
    for it in range(iterations):
        w = w0 * rw * (labels >= 0)
        Gm, hm, c0 = regions.grams(w)
        G, g, c0 = _channel_systems(Gm, hm, c0, rho)
        q = m - 1 if cfg.albedo == "regions" and cfg.albedo_step == "joint" and F.any() else 0
        if q:
            G, g = _with_albedo_columns(G, g, Gm, hm, rho, F)
        ubq = None if ub is None and not q else np.vstack([ub if ub is not None else np.zeros((0, 3)),
                                                          np.full((q, 3), np.inf)])
        F, _ = _solve_channels(G, g, cfg.regularization, prior_fit, p + q, ubq)
        F = F[:, :F.shape[1] - q]
        if cfg.albedo == "regions":
            if it == SECOND_PASS and iterations > SECOND_PASS + 1:
                S = np.maximum((A @ F.T) @ sh.LUMINANCE, 1e-12)
                ratio = np.maximum(I @ sh.LUMINANCE, 1e-12) / S
                labels = alb.split_by_intensity(np.where(clip, -1, labels), np.log(ratio), cfg.intensity_bandwidth,
                                                min_count)
                if pts is not None and normals is not None:
                    labels = _split_mixed(labels, A, I, F, w0 * rw, pts, nrm, min_count)
                    labels = alb.split_off_plane(labels, pts, nrm, min_count)
                    if lit is not None:
                        labels = alb.join_shadows(labels, lit, pts, nrm)
                labels = _with_clipped(labels, clip, pts)
                m = int(labels.max()) + 1
                w, regions = w0 * rw * (labels >= 0), _Regions.of(A, I, labels, m, w0)
                Gm, hm, c0 = regions.grams(w)
            rho, scale = _albedo_step(*_albedo_sums(regions, Gm, hm, w, clip), F, _counts(labels, w * ~clip, m),
                                      cfg, ref_F, G, tsh)
            F = F * scale[:, None]
            if m > 1:
                merged, m_merged = alb.merge_similar(labels, rho, MERGE_LOG_TOLERANCE)
                if not np.array_equal(merged, labels):
                    labels, m = merged, m_merged
                    w, regions = w0 * rw * (labels >= 0), _Regions.of(A, I, labels, m, w0)
                    Gm, hm, c0 = regions.grams(w)
                    rho, scale = _albedo_step(*_albedo_sums(regions, Gm, hm, w, clip), F,
                                              _counts(labels, w * ~clip, m), cfg, ref_F, G, tsh)
                    F = F * scale[:, None]
        if cfg.loss != "none" or censored:
            pred = np.take(rho, np.maximum(labels, 0), axis=0) * (A @ np.ascontiguousarray(F.T))
            if censored:   # a clipped sample says only that the radiance is at least what it shows: where the fit
                # predicts more, the prediction is its value (no residual); where less, the clipped value pulls up
                I = np.where(clip[:, None], np.maximum(I_shown, pred), I_shown)
                regions = _Regions.of(A, I, labels, m, w0)
            r = (I - pred) @ sh.LUMINANCE
            active = w0 * (labels >= 0) * ~clip
            rw = loss_weights(r / robust_scale(r, active), cfg.loss, c)
        moved = np.linalg.norm(F - F_last) / max(float(np.linalg.norm(F)), 1e-300)
        F_last = F
        if it > SECOND_PASS and moved < cfg.tolerance:
            break
    w = w0 * rw * (labels >= 0)
    if cfg.select != "fixed":
        bands, lam_rel = select_order(A, I, w, labels, rho, cfg, prior_fit, pts)
    else:
        bands, lam_rel = cfg.bands, cfg.regularization
    k = bands * bands
    Ak = A if p else np.ascontiguousarray(A[:, :k])  # extra terms imply fixed bands: k = k_fit
    # regions holds the final labels; its design is A's unless fewer bands were selected
    final = regions if Ak is A else _Regions.of(Ak, I, labels, m)
    G, g, c0 = _channel_systems(*final.grams(w), rho)
    prior_b = np.hstack([prior_fit[:, :k], np.zeros((3, p))])
    F, lams = _solve_channels(G, g, lam_rel, prior_b[:, :k], p, ub)
    G_sh, g_sh = G[:, :k, :k], g[:, :k]

    # Rank, conditioning and the fallback: with no prior, data that resolve fewer than MIN_DOF
    # combinations of coefficients (a single plane) fit band 0 only instead of inventing a direction.
    G_lum = np.einsum("c,cij->ij", sh.LUMINANCE, G_sh)
    ev = np.clip(np.linalg.eigvalsh(G_lum)[::-1], 0.0, None)
    lam_lum = float(sh.LUMINANCE @ lams)
    dof = float(np.sum(ev / np.maximum(ev + lam_lum, 1e-300)))
    n_fit = int((w > 0).sum())
    rank, cond, too_few = conditioning(np.sqrt(ev), n_fit, k, cfg, notes)
    fallback = prior is None and k > 1 and (n_fit < k or dof < MIN_DOF)
    measured = None
    if fallback:
        notes.append(f"band-0-only fallback ({dof:.1f} resolved combinations; a temporal filter that holds an "
                     "estimate fuses what the frame resolves instead)")
        measured = _as_sh(F, tsh) if np.isfinite(F).all() else None
        F0, _ = _solve_channels(G[:, :1, :1], g[:, :1], lam_rel, prior_b[:, :1])
        F = np.zeros((3, k + p))
        F[:, :1] = F0
    if cfg.mode == "white":
        lum = sh.LUMINANCE @ F
        mean_rgb = (w[:, None] * I).sum(axis=0) / max(w.sum(), 1e-300)
        F = (mean_rgb / max(float(sh.LUMINANCE @ mean_rgb), 1e-12))[:, None] * lum[None, :]
    if not np.isfinite(F).all():
        notes.append("solution overflowed: returning the " + ("prior" if prior is not None else "zero lighting"))
        F = prior_b.copy()

    pred = np.take(rho, np.maximum(labels, 0), axis=0) * (Ak @ np.ascontiguousarray(F.T))
    scale = float(np.abs(I).max()) or 1.0
    with np.errstate(over="ignore", invalid="ignore"):
        resid = (pred - I) / scale
        wn = w / max(w.sum(), 1e-300)
        mean_obs = float((wn[:, None] * np.abs(I / scale)).sum() / 3)
        rms = float(np.sqrt((wn[:, None] * resid * resid).sum() / 3)) / mean_obs if mean_obs > 0 else 0.0
        sigma2 = float(max(sum(F[c] @ G[c] @ F[c] - 2 * g[c] @ F[c] + c0[c] for c in range(3)), 0.0)
                       / max(3 * n_fit - 3 * k, 1))
    heldout = None
    use_held = held & (labels >= 0) & ~clip
    if use_held.any():
        r = np.abs((I[use_held] - pred[use_held]) @ sh.LUMINANCE)
        heldout = float(np.median(r / np.maximum(np.abs(I[use_held] @ sh.LUMINANCE), 1e-12)))
    missing, observed = coverage(G_lum, lam_lum)
    if missing:
        notes.append("unobserved directions: " + ", ".join(missing))
    unassigned = int((labels < 0).sum())
    if unassigned:
        notes.append(f"{unassigned} samples in no albedo region, left out of the fit (their colours form no cluster "
                     "large enough: textured or mixed surfaces; a concern only where they are most of the samples)")
    unclipped = int(((w > 0) & ~clip).sum())
    if censored:
        binding = int((clip & (w > 0) & (pred < I_shown).any(axis=1)).sum())
        notes.append(f"{int(clip.sum())} saturated samples as lower bounds, {binding} of them binding")
        if unclipped < cfg.min_samples_factor * k:
            too_few = True
            notes.append(f"only {unclipped} unsaturated samples for {k} unknowns")
    inliers = float((w0 * rw).sum() / max(w0.sum(), 1e-300))
    diag = SolveDiagnostics(
        n_samples=n_fit, condition_number=cond, effective_rank=rank,
        residual_rms=float(np.nan_to_num(rms, nan=0.0, posinf=np.finfo(np.float64).max)),
        weak=bool(too_few or rank < k or cond > cfg.max_condition or fallback), notes=notes,
        bands=bands, regularization=float(lam_rel), albedo=rho.tolist(), inlier_fraction=inliers,
        unobserved=missing, observed_fraction=observed, heldout_residual=heldout)
    sigma2 = sigma2 if np.isfinite(sigma2) else 1.0
    system = NormalEquations(G_sh, g_sh, c0, lams, sigma2, n_fit)
    current_system = None
    if current is not None:
        w_cur = np.where(idx < current, w, 0.0)
        G_c, g_c, c0_c = _channel_systems(*final.grams(w_cur), rho)
        current_system = NormalEquations(G_c[:, :k, :k], g_c[:, :k], c0_c, lams, sigma2, int((w_cur > 0).sum()))
    return Solution(Lighting(_as_sh(F, tsh)), diag, system, rho,
                    terms={t.name: F[:, k + j].copy() for j, t in enumerate(terms)}, samples=idx, labels=labels,
                    weights=w, setup=setup, current_system=current_system, measured=measured)
