"""SH basis: DESIGN.md constants exactly, orthonormality by exact quadrature up to 8 bands."""
import math

import numpy as np
import pytest

from photoreg.lighting import sh


def gauss_sphere_quadrature(n_theta=24, n_phi=48):
    """Gauss-Legendre in cos(theta) x uniform phi: exact for spherical polynomials of degree < 2*n_theta."""
    z, wz = np.polynomial.legendre.leggauss(n_theta)
    phi = (np.arange(n_phi) + 0.5) * 2 * math.pi / n_phi
    Z, P = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1 - Z**2)
    dirs = np.stack([r * np.cos(P), r * np.sin(P), Z], -1).reshape(-1, 3)
    w = (wz[:, None] * np.full(n_phi, 2 * math.pi / n_phi)[None, :]).reshape(-1)
    return dirs, w


def test_orthonormal_to_1e6_up_to_8_bands():
    dirs, w = gauss_sphere_quadrature()
    Y = sh.sh_basis(dirs, 8)
    gram = (Y * w[:, None]).T @ Y
    assert np.abs(gram - np.eye(64)).max() < 1e-6


def test_band_0_to_2_constants_are_designs():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x, y, z = d.T
    ref = np.stack([np.full_like(x, 0.282095), 0.488603 * y, 0.488603 * z, 0.488603 * x, 1.092548 * x * y,
                    1.092548 * y * z, 0.315392 * (3 * z**2 - 1), 1.092548 * x * z, 0.546274 * (x**2 - y**2)], 1)
    np.testing.assert_allclose(sh.sh_basis(d, 3), ref, atol=2e-6)
    assert sh.sh_index(1, -1) == 1 and sh.sh_index(2, 2) == 8


def test_cosine_lobe_constants_and_irradiance_of_constant_light():
    a = sh.cosine_lobe(5)
    np.testing.assert_allclose(a[[0, 1, 4, 9, 16]], [math.pi, 2 * math.pi / 3, math.pi / 4, 0.0, -math.pi / 24])
    F = np.zeros((3, 9))
    F[:, 0] = 1.0 / 0.282095  # L(w) = 1 everywhere -> E = pi for every normal
    E = sh.irradiance(F, sh.fibonacci_sphere(10))
    np.testing.assert_allclose(E, math.pi, rtol=1e-5)


def test_projection_of_irradiance_kernel_by_quadrature_matches_analytic():
    """(1/pi) integral max(n.w,0) Y(w) dw equals unoccluded_transfer (Funk-Hecke)."""
    dirs, w = gauss_sphere_quadrature(200, 400)
    n = np.array([[0.2, -0.3, 0.93]])
    n /= np.linalg.norm(n)
    cos = np.maximum(dirs @ n[0], 0)[:, None]
    R = sh.project(dirs, cos / math.pi, w, 5)[0]
    np.testing.assert_allclose(R, sh.unoccluded_transfer(n, 5)[0], atol=2e-4)


def test_dominant_direction_and_degenerate():
    F = np.zeros((3, 4))
    F[:, 3] = 1.0  # +x lobe
    np.testing.assert_allclose(sh.dominant_direction(F), [1, 0, 0])
    assert np.all(np.isfinite(sh.dominant_direction(np.zeros((3, 1)))))
    with pytest.raises(ValueError):
        sh.bands_of(5)
