"""Official accuracy metrics (pure functions): lighting against ground-truth SH, composites against renders.

Lighting is compared only up to scale: the estimate is relative to the scene's unknown albedo
(DESIGN.md), so every lighting metric here is invariant to a positive scale of the estimate.
  * direction_error_deg: angle between the dominant directions (the l=1 band of luminance).
  * si_rmse: scale-invariant relative RMSE of irradiance at a fixed set of normals, dimensionless:
    alpha = argmin over alpha >= 0 of ||alpha E_est - E_gt||, si_rmse = ||alpha E_est - E_gt||_rms / ||E_gt||_rms.
    0 is perfect; 1 is what an estimate with no usable signal (alpha = 0) scores, a negated one included.
  * colour_error_deg: angle between the mean RGB irradiance vectors (white balance of the light).
  * flicker: temporal stability of a sequence of estimates (no ground truth needed), see flicker().
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from ..lighting import sh
from ..lighting.visualize import lit_sphere

NO_DIRECTION_DEG = 90.0  # error charged when an estimate carries no direction (l=1 band zero or non-finite)
ROI_DILATION_PX = 40

SPHERE_NORMALS = sh.fibonacci_sphere(4096)
UPPER_NORMALS = SPHERE_NORMALS[SPHERE_NORMALS[:, 2] > 0]  # world z up


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Angle between two non-zero vectors in degrees (atan2 form: accurate near 0 and 180; each scaled by its largest
    component first, so that neither a tiny nor a huge one underflows or overflows)."""
    u, v = (np.asarray(x, np.float64) / np.max(np.abs(x)) for x in (u, v))
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(u, v))), float(np.dot(u, v))))


def l1_vector(sh_rgb: np.ndarray) -> np.ndarray:
    """(x, y, z) of the l=1 band of luminance; zeros when the SH has fewer than 2 bands."""
    lum = sh.luminance(sh_rgb)
    return np.array([lum[3], lum[1], lum[2]]) if lum.shape[0] >= 4 else np.zeros(3)


def has_direction(sh_rgb: np.ndarray) -> bool:
    """Whether the l=1 band of luminance is finite and non-zero (relative to band 0)."""
    v = l1_vector(sh_rgb)
    scale = max(abs(float(sh.luminance(sh_rgb)[0])), 1e-300)
    return bool(np.isfinite(v).all() and np.linalg.norm(v / scale) > 1e-9)


def direction_error_deg(sh_est: np.ndarray, sh_gt: np.ndarray) -> float:
    """Angle between dominant light directions (the estimate's l=1 vector at any positive scale); NO_DIRECTION_DEG
    when the estimate has none."""
    if not has_direction(sh_est):
        return NO_DIRECTION_DEG
    return _angle_deg(l1_vector(sh_est), sh.dominant_direction(sh_gt))


def light_direction_error_deg(traced, true_direction) -> float:
    """Angle between a traced light's direction (SolveDiagnostics.sun["direction"]; None: no light held) and the
    true light's (its brightest sun): where a sun dominates, the SH's l=1 direction (direction_error_deg) mixes it
    with the sky's, the truth's own too (the demo's: tens of degrees from its sun), and this is where shadows fall.
    NO_DIRECTION_DEG without a light or with a non-finite one."""
    if traced is None or not np.isfinite(traced).all() or not np.linalg.norm(traced) > 0:
        return NO_DIRECTION_DEG
    return _angle_deg(np.asarray(traced, dtype=np.float64), np.asarray(true_direction, dtype=np.float64))


def scale_invariant_rmse(est: np.ndarray, gt: np.ndarray) -> float:
    """||alpha est - gt||_rms / ||gt||_rms with the least-squares alpha >= 0 over all values (0 if gt is 0); both
    scaled by their largest magnitude first (the result does not change; their products stay finite)."""
    e = np.asarray(est, dtype=np.float64).ravel()
    g = np.asarray(gt, dtype=np.float64).ravel()
    e, g = (x / m if (m := float(np.max(np.abs(x), initial=0.0))) > 0 and math.isfinite(m) else x for x in (e, g))
    gg = float(g @ g)
    if gg <= 0:
        return 0.0 if not e.any() else 1.0
    ee = float(e @ e)
    alpha = max(float(e @ g) / ee, 0.0) if ee > 0 else 0.0
    r = alpha * e - g
    return math.sqrt(max(float(r @ r), 0.0) / gg)


def rmse(est: np.ndarray, gt: np.ndarray) -> float:
    """Root-mean-square difference over all values (0 for empty inputs)."""
    d = np.asarray(est, dtype=np.float64) - np.asarray(gt, dtype=np.float64)
    return math.sqrt(float(np.mean(d * d))) if d.size else 0.0


def irradiance_si_rmse(sh_est: np.ndarray, sh_gt: np.ndarray, normals: np.ndarray) -> float:
    """Scale-invariant RMSE of RGB irradiance (each SH with all its bands) at `normals`."""
    return scale_invariant_rmse(sh.irradiance(sh_est, normals), sh.irradiance(sh_gt, normals))


def colour_error_deg(sh_est: np.ndarray, sh_gt: np.ndarray, normals: np.ndarray = SPHERE_NORMALS) -> float:
    """Angle between the mean RGB irradiance over `normals`; NO_DIRECTION_DEG for a zero estimate."""
    e = sh.irradiance(sh_est, normals).mean(axis=0)
    g = sh.irradiance(sh_gt, normals).mean(axis=0)
    if not (np.linalg.norm(e) > 0 and np.linalg.norm(g) > 0):
        return NO_DIRECTION_DEG
    return _angle_deg(e, g)


def lighting_metrics(sh_est: np.ndarray, sh_gt: np.ndarray) -> dict[str, float]:
    """All per-frame lighting metrics of a finite estimate (3, B*B) against ground truth (3, B'*B')."""
    return {"direction_deg": direction_error_deg(sh_est, sh_gt),
            "irradiance_si_rmse_upper": irradiance_si_rmse(sh_est, sh_gt, UPPER_NORMALS),
            "irradiance_si_rmse_sphere": irradiance_si_rmse(sh_est, sh_gt, SPHERE_NORMALS),
            "colour_deg": colour_error_deg(sh_est, sh_gt)}


def _flicker_view() -> np.ndarray:
    """Fixed camera-to-world pose (OpenCV axes) of the flicker sphere: from +x, 30 degrees above the horizon."""
    el = math.radians(30.0)
    forward = -np.array([math.cos(el), 0.0, math.sin(el)])   # looking at the origin
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    return T


FLICKER_VIEW = _flicker_view()


def flicker(sequence, size: int = 64) -> float | None:
    """Flicker E = mean over disc pixels, channels and consecutive frame pairs of exp(3 |I_t - I_(t-1)|) - 1,
    I_t the diffuse sphere lit by estimate t (photoreg.lighting.visualize.lit_sphere, fixed view FLICKER_VIEW).

    The images of a sequence share one scale, its 99th percentile pixel (so E ignores the estimate's
    arbitrary albedo scale but sees every per-frame jump); pairs with a non-finite estimate are skipped;
    None where no consecutive pair is usable (no pair: not a flicker of 0, as image_flicker)."""
    imgs = [lit_sphere(np.asarray(f, dtype=np.float64), FLICKER_VIEW, size) if np.isfinite(f).all() else None
            for f in sequence]
    u = (np.arange(size) + 0.5) / size * 2 - 1
    disc = (u[None, :] ** 2 + u[:, None] ** 2) < 1
    pairs = [(a[disc], b[disc]) for a, b in zip(imgs, imgs[1:]) if a is not None and b is not None]
    if not pairs:
        return None
    ref = float(np.percentile(np.stack([i[disc] for i in imgs if i is not None]), 99))
    if not ref > 0:
        return 0.0   # every sphere black: nothing changed
    return float(np.mean([np.mean(np.exp(3.0 * np.abs(b - a) / ref) - 1.0) for a, b in pairs]))


def changed_region(composites, cameras, tolerance: float = 1e-3) -> np.ndarray:
    """Pixels (bool HxW) where any composite differs from its camera frame by more than `tolerance` in
    some channel: where an insertion (object or shadow) changed the frame."""
    return np.any([np.abs(np.asarray(c) - np.asarray(k)).max(axis=-1) > tolerance
                   for c, k in zip(composites, cameras)], axis=0)


def image_flicker(images, region: np.ndarray) -> float | None:
    """Flicker E of an image sequence itself: mean over `region` pixels (bool HxW), channels and
    consecutive pairs of exp(3 |I_t - I_(t-1)|) - 1, on linear images as they are (composites share the
    camera's scale); None for fewer than two images (no pair: not a flicker of 0), 0 for an empty region."""
    imgs = [np.asarray(i, dtype=np.float64)[region] for i in images]
    if len(imgs) < 2:
        return None
    if not region.any():
        return 0.0
    return float(np.mean([np.mean(np.exp(3.0 * np.abs(b - a)) - 1.0) for a, b in zip(imgs, imgs[1:])]))


def summarize(values) -> dict[str, float | None]:
    """Median, mean and 90th percentile of the finite values (None when there are none) and their count."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"median": None, "mean": None, "p90": None, "n": 0}
    return {"median": float(np.median(v)), "mean": float(v.mean()), "p90": float(np.percentile(v, 90)), "n": int(v.size)}


# --- composites -----------------------------------------------------------------------------------------

def roi_mask(object_mask: np.ndarray, radius_px: int = ROI_DILATION_PX) -> np.ndarray:
    """Region of interest: the virtual-object mask dilated by `radius_px` (elliptical element), bool HxW."""
    m = (np.asarray(object_mask) > 0).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
    return cv2.dilate(m, kernel) > 0


def flip_available() -> bool:
    """Whether the optional FLIP package (flip_evaluator) can be imported."""
    try:
        import flip_evaluator  # noqa: F401
    except ImportError:
        return False
    return True


def flip_error(est: np.ndarray, gt: np.ndarray, roi: np.ndarray) -> float:
    """Mean HDR-FLIP (flip_evaluator; linear inputs, negatives and non-finite clipped to 0) over the ROI."""
    import flip_evaluator

    def prep(img):
        return np.ascontiguousarray(np.clip(np.nan_to_num(img, nan=0.0, posinf=0.0), 0.0, None), dtype=np.float32)

    error_map = flip_evaluator.evaluate(prep(gt), prep(est), "HDR", applyMagma=False)[0]
    return float(np.asarray(error_map).reshape(roi.shape)[roi].mean())


def composite_metrics(est: np.ndarray, gt: np.ndarray, roi: np.ndarray, with_flip: bool = False) -> dict[str, float]:
    """RMSE and scale-invariant RMSE (linear RGB) of a composite against the GT render over the ROI."""
    if est.shape != gt.shape or gt.shape[:2] != roi.shape:
        raise ValueError(f"image shapes differ: estimate {est.shape}, ground truth {gt.shape}, roi {roi.shape}")
    e, g = est[roi], gt[roi]
    out = {"rmse": rmse(e, g), "si_rmse": scale_invariant_rmse(e, g)}
    if with_flip:
        out["flip"] = flip_error(est, gt, roi)
    return out


def no_shadow_baseline(camera_linear: np.ndarray, insert_linear: np.ndarray, object_mask: np.ndarray) -> np.ndarray:
    """The 'no shadow' baseline: the perfect object pasted into the camera frame, surroundings untouched."""
    m = np.asarray(object_mask) > 0
    return np.where(m[..., None], insert_linear, camera_linear).astype(np.float32)
