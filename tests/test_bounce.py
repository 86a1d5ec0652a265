"""The bounce from observed radiance (photoreg.lighting.bounce): hit distances of the transfer pass against a
plane in closed form, the columns against the transfer's own quadrature, the solve on model data whose blocked
directions see surfaces of different brightness, and the pipeline on the demo recording."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from photoreg.config import Session
from photoreg.io.recording import iter_frames, open_recording
from photoreg.kernels.transfer import make_direction_set, radiance_transfer
from photoreg.lighting import sh
from photoreg.lighting.bounce import OBSERVED_GAIN_MAX, bounce_columns, observed_bounce_terms
from photoreg.lighting.exposure import ExposureTracker
from photoreg.lighting.parametric import lobe_sh
from photoreg.lighting.robust import Term, bounce_term, solve
from photoreg.lighting.solver import SolverConfig
from photoreg.pipeline import Pipeline
from photoreg.render.scene import sdf_grid
from test_sun import SUN, model_samples

REPO = Path(__file__).resolve().parents[1]
VOXEL, TRUNC, WALL_X = 0.02, 0.08, 0.3


def wall_grid():
    """Real geometry: the half-space x >= WALL_X (a wall facing -x), in a 64^3 brick round the origin."""
    origin = np.array([-0.64, -0.64, -0.64])
    x = origin[0] + np.arange(64) * VOXEL
    sdf = np.broadcast_to((WALL_X - x)[:, None, None], (64, 64, 64)).copy()
    return sdf_grid(sdf, origin, VOXEL, TRUNC, "cpu")


def wall_samples(n=40, seed=0):
    """Points between x = 0 and the wall with tilted normals, so some rays reach the wall and some do not."""
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(0.0, 0.2, n), rng.uniform(-0.2, 0.2, n), rng.uniform(-0.2, 0.2, n)])
    normals = rng.normal(size=(n, 3)) + [1.0, 0.0, 0.0]
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def test_hit_distances_reach_the_surface_and_leave_the_transfer_unchanged():
    grid = wall_grid()
    points, normals = wall_samples()
    dirs, Y = make_direction_set(32, 3, seed=0)
    offset, length = 0.03, 0.5
    tr = radiance_transfer(grid, points, normals, dirs, Y, offset, length, hit_distances=True)
    plain = radiance_transfer(grid, points, normals, dirs, Y, offset, length)
    assert plain.hit_distance_wp is None
    np.testing.assert_array_equal(tr.transfer, plain.transfer)
    np.testing.assert_array_equal(tr.occlusion_wp.numpy(), plain.occlusion_wp.numpy())
    origin = points + normals * offset
    with np.errstate(divide="ignore"):
        exact = (WALL_X - origin[:, :1]) / dirs[None, :, 0]      # where the ray meets the plane x = WALL_X
    reach = (normals @ dirs.T > 0) & (dirs[None, :, 0] > 0) & (exact <= length)
    t = tr.hit_distance_wp.numpy()
    assert reach.mean() > 0.2 and (~reach & (normals @ dirs.T > 0)).mean() > 0.1   # both kinds of ray occur
    assert np.all(t[~reach] == -1.0) and np.array_equal(tr.occlusion_wp.numpy() != 0, t >= 0)
    far = reach & (exact < length - VOXEL)   # a ray ending within a step of the plane may stop short of it
    np.testing.assert_allclose(t[far], exact[far], atol=1e-3)   # the linear SDF interpolates to the plane


def test_bounce_columns_split_the_blocked_share_by_what_the_camera_saw():
    grid = wall_grid()
    points, normals = wall_samples()
    dirs, Y = make_direction_set(32, 3, seed=0)
    tr = radiance_transfer(grid, points, normals, dirs, Y, 0.03, 0.5, hit_distances=True)
    t = tr.hit_distance_wp.numpy()
    blocked = t >= 0
    cos = np.clip(normals @ dirs.T, 0.0, None)
    # Nothing seen yet (the first frame): every blocked direction is unseen, and the column is the blocked share
    # of the transfer's own quadrature.
    empty = ExposureTracker(cell=2 * VOXEL)
    cols = bounce_columns(tr, points, normals, dirs, 0.03, empty)
    assert np.all(cols[:, 0] == 0)
    share = (4.0 / len(dirs)) * cos.sum(axis=1) - tr.transfer[:, 0] / sh.Y00
    np.testing.assert_allclose(cols[:, 1], share, atol=1e-5)
    # The wall seen with luminance 0.6 below z = 0 and 0.2 above: each blocked ray takes its own hit's value.
    seen = ExposureTracker(cell=2 * VOXEL)
    yz = np.stack(np.meshgrid(np.arange(-0.7, 0.7, 0.01), np.arange(-0.7, 0.7, 0.01)), -1).reshape(-1, 2)
    wall = np.column_stack([np.full(len(yz), WALL_X + 0.001), yz])
    seen.update(wall, np.where(wall[:, 2:] < 0, 0.6, 0.2) * np.ones(3))
    cols = bounce_columns(tr, points, normals, dirs, 0.03, seen)
    hit = points[:, None, :] + 0.03 * normals[:, None, :] + dirs[None] * t[..., None]
    lum = np.where(hit[..., 2] < 0, 0.6, 0.2)
    np.testing.assert_allclose(cols[:, 0], (4.0 / len(dirs)) * (blocked * cos * lum).sum(axis=1), rtol=1e-5)
    assert np.abs(cols[:, 1]).max() < 1e-12
    # Only the wall below z = -4 cm seen: the rays hitting the rest are unseen; the two columns share the rays.
    lower = ExposureTracker(cell=2 * VOXEL)
    lower.update(wall[wall[:, 2] < -0.04], np.full((int((wall[:, 2] < -0.04).sum()), 3), 0.6))
    cols = bounce_columns(tr, points, normals, dirs, 0.03, lower)
    low = blocked & (hit[..., 2] < -0.04)
    unseen = blocked & ~low
    assert low.any() and unseen.any()
    np.testing.assert_allclose(cols[:, 0], (4.0 / len(dirs)) * (low * cos * 0.6).sum(axis=1), rtol=1e-5)
    np.testing.assert_allclose(cols[:, 1], (4.0 / len(dirs)) * (unseen * cos).sum(axis=1), rtol=1e-5)


def test_observed_bounce_explains_surfaces_of_different_brightness():
    """Model data whose blocked directions see a bright surface at the samples facing +x and a dark one at the
    others (luminance 0.9 against 0.1, as beside a sunlit and a shaded wall): one fitted radiance for every
    blocked direction cannot hold that and tilts the sky; with the observed radiance as a column the solve
    recovers the light exactly."""
    rng = np.random.default_rng(5)
    radiance, transfer, normals, t_sun, sky, colour, _ = model_samples(rng, albedos=((0.8, 0.8, 0.8),) * 2)
    blocked = sh.blocked_share(transfer)[:, 0]
    seen_lum = np.where(normals[:, 0] > 0, 0.9, 0.1)
    lit = radiance / 0.8 + np.outer(blocked * seen_lum, np.ones(3))   # albedo 0.8 everywhere
    cfg = SolverConfig(bands=5, regularization=0.0, saturation_level=None, loss="huber")
    sun = Term("sun", t_sun, lobe_sh(np.ones(1), SUN, 1e-9, 5)[0])
    truth = sky + np.outer(colour, sun.sh)
    up = sh.fibonacci_sphere(500)
    up = up[up[:, 2] > 0]

    def err(F):
        return float(np.abs(sh.irradiance(F, up) - sh.irradiance(truth, up)).max() / sh.irradiance(truth, up).max())

    cols = np.column_stack([blocked * seen_lum, np.zeros(len(normals))])
    observed = solve(lit, transfer, normals, np.ones(len(normals)), cfg,
                     terms=[sun, *observed_bounce_terms(cols, transfer, lit)])
    fitted = solve(lit, transfer, normals, np.ones(len(normals)), cfg, terms=[sun, bounce_term(transfer, lit)])
    assert np.allclose(observed.terms["bounce_observed"], 1.0, atol=1e-4)
    assert err(observed.lighting.sh) < 1e-6 < 0.005 < err(fitted.lighting.sh)


def test_pipeline_reports_the_observed_bounce_from_the_second_frame():
    """On the demo recording: the first frame has no fused radiance yet (every blocked direction unseen), the
    later ones fit a colour gain on what the camera saw; `bounce_observed = false` is the single fitted term."""
    rec = open_recording(REPO / "data" / "demo")

    def run(observed: bool):
        s = Session()
        s.device = "cpu"
        s.lighting.rays, s.lighting.stride, s.lighting.bounce_observed = 16, 8, observed
        pipe = Pipeline(s, rec.intrinsics)
        return [pipe.process(f).diagnostics for f in iter_frames(rec, [0, 1, 2])]

    on, off = run(True), run(False)
    assert on[0].bounce_observed == [0.0, 0.0, 0.0]
    gains = np.array([d.bounce_observed for d in on[1:]])
    assert np.isfinite(gains).all() and gains.min() >= 0 and gains.max() <= OBSERVED_GAIN_MAX and gains.max() > 0
    assert all(d.bounce_observed is None and d.bounce_radiance is not None for d in off)
    assert math.isfinite(on[-1].residual_rms) and "bounce_observed" in on[-1].to_json()
