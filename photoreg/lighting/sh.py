"""Real orthonormal spherical harmonics (DESIGN.md convention), projection and irradiance.

Index i = l*(l+1)+m; Y_l^m = sqrt(2) K_l^m P_l^|m|(z) * {cos(m phi) m>0, sin(|m| phi) m<0}, K for m=0
without sqrt(2); no Condon-Shortley phase, so Y_1^-1 = c*y, Y_1^0 = c*z, Y_1^1 = c*x.
Evaluated from (x, y, z) by polynomial recurrences (no trigonometry), for any band count.
"""
from __future__ import annotations

import math

import numpy as np

Y00 = 0.5 / math.sqrt(math.pi)  # the band-0 basis value, 0.282095
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 weights for linear RGB


def n_coeffs(bands: int) -> int:
    return bands * bands


def sh_index(l: int, m: int) -> int:
    return l * (l + 1) + m


def bands_of(n: int) -> int:
    b = int(round(math.sqrt(n)))
    if b * b != n:
        raise ValueError(f"{n} is not a square number of SH coefficients")
    return b


def sh_basis(dirs: np.ndarray, bands: int) -> np.ndarray:
    """Basis values Y_i(dir) for unit directions (N, 3) -> (N, bands*bands) float64."""
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = np.zeros((d.shape[0], bands * bands))
    c = np.ones_like(x)  # Re (x + i y)^m
    s = np.zeros_like(x)  # Im (x + i y)^m
    for m in range(bands):
        if m > 0:
            c, s = c * x - s * y, c * y + s * x
        # Q_l^m(z) = P_l^m(z) / sin^m(theta): polynomial recurrence in l for fixed m.
        q_mm = float(np.prod(np.arange(2 * m - 1, 0, -2))) if m > 0 else 1.0
        q_prev2 = q_prev = None
        for l in range(m, bands):
            if l == m:
                q = np.full_like(z, q_mm)
            elif l == m + 1:
                q = z * (2 * m + 1) * q_mm
            else:
                q = ((2 * l - 1) * z * q_prev - (l + m - 1) * q_prev2) / (l - m)
            q_prev2, q_prev = q_prev, q
            k = math.sqrt((2 * l + 1) / (4 * math.pi) * math.exp(math.lgamma(l - m + 1) - math.lgamma(l + m + 1)))
            if m == 0:
                out[:, sh_index(l, 0)] = k * q
            else:
                out[:, sh_index(l, m)] = math.sqrt(2.0) * k * q * c
                out[:, sh_index(l, -m)] = math.sqrt(2.0) * k * q * s
    return out


def cosine_lobe(bands: int) -> np.ndarray:
    """A_l of the clamped cosine, per coefficient (bands*bands,): A0=pi, A1=2pi/3, odd l>1 vanish."""
    a = np.zeros(bands)
    for l in range(bands):
        if l == 0:
            a[l] = math.pi
        elif l == 1:
            a[l] = 2 * math.pi / 3
        elif l % 2 == 0:
            a[l] = (2 * math.pi * (-1) ** (l // 2 - 1) / ((l + 2) * (l - 1))
                    * math.factorial(l) / (2 ** l * math.factorial(l // 2) ** 2))
    return np.repeat(a, [2 * l + 1 for l in range(bands)])


def irradiance(sh: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """E(n) = sum A_l F_lm Y_lm(n) for SH radiance (C, B*B) and normals (N, 3) -> (N, C)."""
    sh = np.atleast_2d(sh)
    b = bands_of(sh.shape[1])
    return sh_basis(normals, b) @ (sh * cosine_lobe(b)).T


def unoccluded_transfer(normals: np.ndarray, bands: int) -> np.ndarray:
    """Analytic R_TR of an unoccluded point: (1/pi) A_l Y_lm(n), shape (N, bands*bands)."""
    return sh_basis(normals, bands) * cosine_lobe(bands) / math.pi


def radiance(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Incident radiance L(w) reconstructed from SH (C, B*B) at directions (N, 3) -> (N, C)."""
    sh = np.atleast_2d(sh)
    return sh_basis(dirs, bands_of(sh.shape[1])) @ sh.T


def project(dirs: np.ndarray, values: np.ndarray, weights: np.ndarray, bands: int) -> np.ndarray:
    """Quadrature projection sum_k w_k f(w_k) Y(w_k): values (N, C), weights (N,) -> (C, B*B)."""
    v = np.asarray(values, dtype=np.float64).reshape(len(weights), -1)
    return ((sh_basis(dirs, bands) * np.asarray(weights, dtype=np.float64)[:, None]).T @ v).T


def rotate(sh: np.ndarray, R: np.ndarray) -> np.ndarray:
    """SH (C, B*B) of the lighting turned by rotation R (3x3): L'(w) = L(R^T w), e.g. from a camera's frame into the
    world with R camera-to-world. Exact to rounding (each band is closed under rotation): fitted to the turned
    function at 4 B^2 directions."""
    sh = np.atleast_2d(np.asarray(sh, dtype=np.float64))
    dirs = fibonacci_cap(4 * sh.shape[1], -1.0)
    values = radiance(sh, dirs @ np.asarray(R, dtype=np.float64))   # rows w @ R = (R^T w)^T
    return np.linalg.lstsq(sh_basis(dirs, bands_of(sh.shape[1])), values, rcond=None)[0].T


def fibonacci_cap(n: int, cos_min: float) -> np.ndarray:
    """n unit directions (n, 3) spread uniformly in solid angle over the cap z >= cos_min around +z
    (a spherical Fibonacci spiral; cos_min = -1 is the whole sphere)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - (1.0 - cos_min) * i / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def fibonacci_sphere(n: int, rotation_seed: int | None = None) -> np.ndarray:
    """n quasi-uniform unit directions (spherical Fibonacci), optionally randomly rotated."""
    d = fibonacci_cap(n, -1.0)
    if rotation_seed is not None:
        from scipy.spatial.transform import Rotation
        d = d @ Rotation.random(random_state=rotation_seed).as_matrix().T
    return d


def luminance(sh: np.ndarray) -> np.ndarray:
    """Luminance SH (B*B,) of RGB SH (3, B*B)."""
    return LUMINANCE @ np.asarray(sh, dtype=np.float64)


def one_chroma(sh: np.ndarray) -> np.ndarray:
    """RGB SH (3, B*B) as one colour times a luminance SH: its luminance scaled per channel by its band 0's colour
    (lighting.mode "white" after a filter that weighs the channels apart)."""
    sh = np.asarray(sh, dtype=np.float64)
    lum = luminance(sh)
    return (sh[:, 0] / lum[0])[:, None] * lum[None, :] if abs(lum[0]) > 1e-12 else sh.copy()


def dominant_direction(sh: np.ndarray) -> np.ndarray:
    """Unit direction of the l=1 band of luminance (world frame); +z when that band is zero."""
    lum = luminance(sh) if np.ndim(sh) == 2 else np.asarray(sh, dtype=np.float64)
    if lum.shape[0] < 4:
        return np.array([0.0, 0.0, 1.0])
    v = np.array([lum[3], lum[1], lum[2]])  # (x, y, z) = (Y11, Y1-1, Y10)
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 and np.isfinite(n) else np.array([0.0, 0.0, 1.0])


def truncate(sh: np.ndarray, bands: int) -> np.ndarray:
    """First `bands` bands of SH (C, B*B), zero-padded when asking for more."""
    sh = np.atleast_2d(sh)
    out = np.zeros((sh.shape[0], bands * bands))
    k = min(bands * bands, sh.shape[1])
    out[:, :k] = sh[:, :k]
    return out


def blocked_share(transfer: np.ndarray) -> np.ndarray:
    """(1/pi) * integral (1 - V) max(n.w, 0) dw per point, from the band-0 transfer (R_00 = Y00 * that
    integral of V), clipped to [0, 1]: (N, B*B) -> (N, 1)."""
    return np.clip(1.0 - transfer[:, :1] / Y00, 0.0, 1.0)
