"""Albedo regions: which samples share one albedo, as far as the data show it, and the albedo scale fix.

The lighting model I = rho * R.F holds one albedo per surface. Regions are found by clustering the
samples in colour space, on a grid of cells (mode seeking on a histogram, so the number of regions
follows the data instead of being fixed):
  * first pass, no lighting known: log-chromaticity (ln R/G, ln B/G) of the observed radiance; a
    change of intensity alone (shading, shadows) keeps a sample in its region;
  * second pass, with a lighting estimate: each region is split where the log-luminance of its albedo
    estimates I / (R.F) (shading divided out) has separate modes, so surfaces of one colour but
    different brightness (a black and a white half of one floor) separate, while a shadow does not.
Cells of `bandwidth` in each feature are counted, counts are summed over each cell's 3^d neighbourhood,
local maxima holding at least `min_count` samples become region centres, every sample goes to the
nearest centre (two k-means refinements) and samples farther than FAR_CELLS from all centres, or in
regions smaller than `min_count`, get label -1 (left out of the fit).

Scale: rho * F is unchanged by rho / s, F * s per channel, so one rule fixes s (REFERENCES): the rule's
region gets the assumed albedo `value` (lighting.reference_albedo), which puts F in absolute units
(virtual objects with absolute albedos are then lit at the right brightness).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

DENSE_CELLS = 1 << 22   # cluster(): histograms of up to this many cells are counted on a dense grid
FAR_CELLS = 3.0          # a sample farther than this (in cells) from every centre belongs to no region
NEIGHBOUR_SPACINGS = 2.5  # split_by_geometry: samples closer than this many median spacings are neighbours ...
SMOOTH_DEG = 20.0         # ... on one surface when their normals differ by less than this ...
CONVEX_TOLERANCE = 0.15   # ... and their edge is not concave by more than this (|dn| along the edge; else convex)
JOIN_FRACTION = 0.3       # a part with this share of its samples on another region's surface joins it
COPY_RATIO = 0.3          # sample_spacing: a median nearest neighbour under this share of the second's is a copy
PLANE_DEG = 20.0          # split_off_plane: on the largest region's plane within this angle ...
PLANE_SPACINGS = 3.0      # ... and this many median sample spacings; off it: farther, or facing away by more than
OFF_PLANE_DEG = 70.0      # ... this (samples in between, the fillet fusion rounds a corner into, belong to none)
PLANE_SHARE = 0.6         # the region is taken for a plane when this share of its samples lies on it
SHADOW_LIT = 0.5          # join_shadows: a region on the plane lit by the traced light at most this times as often ...
FLOOR_LIT = 0.5           # ... as the plane's region joins it, when at least this share of that one is lit
REFERENCES = {
    "max": "per channel, the largest albedo over regions holding >= 5% of the samples is `value` (max-RGB)",
    "largest": "the region holding the most samples has albedo `value`",
    "mean": "the mean albedo over regions (each region counted once) is `value` (grey world)",
}


def by_size(labels: np.ndarray) -> tuple[np.ndarray, int]:
    """Labels renumbered largest region first, empty ones dropped (-1 stays -1), and the region count; labels
    already in that order are returned as they are (the solve's merge step mostly finds nothing to merge)."""
    m = int(labels.max()) + 1 if labels.size else 0
    size = np.bincount(labels + 1, minlength=m + 1)[1:]   # -1 counted in the dropped bin 0
    order = np.argsort(-size, kind="stable")
    order = order[size[order] > 0]
    if len(order) == m and (order == np.arange(m)).all():
        return labels, m
    remap = -np.ones(m + 1, dtype=np.int64)
    remap[order] = np.arange(len(order))
    return remap[labels], len(order)


def median(a: np.ndarray) -> float:
    """np.median of a non-empty 1-D array (NaN when it holds one) with one partition: np.median partitions
    at three positions, several times slower, and the solve takes about a dozen medians per frame."""
    h = a.size // 2
    p = np.partition(a, h)
    if np.isnan(p[h:].max()):   # NaN sorts last
        return math.nan
    return float(p[h]) if a.size % 2 else float((p[:h].max() + p[h]) / 2)


def colour_features(rgb: np.ndarray, with_intensity: bool, floor: float = 1e-3) -> np.ndarray:
    """(ln R/G, ln B/G[, ln luminance]) of linear RGB (N, 3); channels below `floor` times the median
    channel value are clamped (relative, so the features do not depend on the exposure)."""
    x = np.asarray(rgb, dtype=np.float64)
    finite = x[np.isfinite(x) & (x > 0)]
    low = floor * (median(finite) if finite.size else 1.0)
    x = np.maximum(np.nan_to_num(x, nan=low, posinf=low / floor ** 2, neginf=low), low)
    f = [np.log(x[:, 0] / x[:, 1]), np.log(x[:, 2] / x[:, 1])]
    if with_intensity:
        f.append(np.log(x @ np.array([0.2126, 0.7152, 0.0722])))
    return np.stack(f, axis=1)


def index_sums(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Per-index column sums (n, d) of values (N, d) (np.add.at, a bincount per column: much faster)."""
    return np.stack([np.bincount(index, weights=v, minlength=n) for v in values.T], axis=1)


def cluster(features: np.ndarray, bandwidth, min_count: int) -> np.ndarray:
    """Labels (N,) of histogram-mode clusters of `features` (N, d), largest cluster 0, -1 = none.

    `bandwidth` (scalar or per feature) is the cell size; see the module docstring."""
    f = np.asarray(features, dtype=np.float64)
    n, d = f.shape
    labels = -np.ones(n, dtype=np.int64)
    # the features as contiguous rows (d, N): numpy is several times slower along a short last axis
    ft = np.ascontiguousarray(f.T)
    ok = np.isfinite(ft).all(axis=0)
    if ok.sum() < max(min_count, 1):
        return labels
    zt = np.compress(ok, ft, axis=1) / np.asarray(bandwidth, dtype=np.float64).reshape(-1, 1)
    lo = np.floor(zt.min(axis=1)) - 1
    cells = (np.floor(zt) - lo[:, None]).astype(np.int64)
    base = int(cells.max()) + 2
    if base ** d > 2 ** 62:  # absurd spread (garbage inputs): clip to a manageable grid
        cells = np.clip(cells, 0, 2 ** (62 // d) - 3)
        base = int(cells.max()) + 2
    weights = base ** np.arange(d, dtype=np.int64)
    flat = sum(cells[j] * weights[j] for j in range(d))
    offsets = np.array(list(itertools.product((-1, 0, 1), repeat=d)), dtype=np.int64) @ weights
    # cells lie in 1..base-2 per feature, so a neighbour's flat key never wraps into another row
    if base ** d <= DENSE_CELLS:  # the histogram as a dense grid: each neighbour lookup is a shifted slice
        dense = np.bincount(flat, minlength=base ** d)
        keys = np.flatnonzero(dense)
        counts = dense[keys]
        inverse = np.searchsorted(keys, flat)
        pad = int(weights.sum())  # the largest |offset|
        padded = np.zeros(base ** d + 2 * pad, dtype=np.int64)
        padded[pad:pad + base ** d] = dense
        sm = np.zeros(base ** d, dtype=np.int64)
        for o in offsets:
            sm += padded[pad + o:pad + o + base ** d]
        smooth = sm[keys]
        padded[pad:pad + base ** d] = np.where(dense > 0, sm, 0)  # as lookup(): occupied cells only
        peak = smooth >= min_count
        for o in offsets[offsets != 0]:
            nb = padded[keys + pad + o]
            peak &= (smooth > nb) | ((smooth == nb) & (o > 0))  # ties: the lower key wins
    else:
        keys, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)

        def lookup(values: np.ndarray, at: np.ndarray) -> np.ndarray:
            pos = np.clip(np.searchsorted(keys, at), 0, len(keys) - 1)
            return np.where(keys[pos] == at, values[pos], 0)

        smooth = sum(lookup(counts, keys + o) for o in offsets)
        peak = smooth >= min_count
        for o in offsets[offsets != 0]:
            nb = lookup(smooth, keys + o)
            peak &= (smooth > nb) | ((smooth == nb) & (o > 0))  # ties: the lower key wins
    if not peak.any():
        return labels

    def nearest(centres):
        """Index of each sample's nearest centre (the first of equals, as argmin) and its squared distance,
        one centre at a time (not argmin over an (n, few) array)."""
        near, best = np.zeros(zt.shape[1], dtype=np.int64), None
        for k, ck in enumerate(centres):
            dist = (zt[0] - ck[0]) ** 2
            for j in range(1, d):
                dist += (zt[j] - ck[j]) ** 2
            if best is None:
                best = dist
            else:
                near[dist < best] = k
                np.minimum(best, dist, out=best)
        return near, best

    centres = index_sums(inverse, zt.T, len(keys))[peak] / counts[peak][:, None]
    for _ in range(2):  # k-means refinement
        near = nearest(centres)[0]
        sums = index_sums(near, zt.T, len(centres))
        num = np.bincount(near, minlength=len(centres))
        centres = np.where(num[:, None] > 0, sums / np.maximum(num, 1)[:, None], centres)
    near, dist = nearest(centres)
    near[np.sqrt(dist) > FAR_CELLS] = -1
    size = np.bincount(near[near >= 0], minlength=len(centres))
    order = [c for c in np.argsort(-size, kind="stable") if size[c] >= min_count]
    remap = -np.ones(len(centres) + 1, dtype=np.int64)
    remap[np.array(order, dtype=np.int64)] = np.arange(len(order))
    labels[ok] = remap[near]  # near = -1 picks remap[-1] = -1
    return labels


def split_by_intensity(labels: np.ndarray, log_albedo: np.ndarray, bandwidth: float, min_count: int) -> np.ndarray:
    """Split each region where its log albedo estimates (shading divided out) form separate modes
    (cluster() in 1-D with cell `bandwidth`); samples between modes stay with the region's largest part.
    Returns new labels, largest region first."""
    out = labels.copy()
    nxt = int(labels.max()) + 1 if labels.size else 0
    for r in range(nxt):
        sel = np.flatnonzero(labels == r)
        parts = cluster(log_albedo[sel, None], bandwidth, min_count)
        for p in range(1, int(parts.max()) + 1 if parts.size else 0):
            out[sel[parts == p]] = nxt
            nxt += 1
    return by_size(out)[0]


def reference_scale(rho: np.ndarray, counts: np.ndarray, rule: str, value: float = 1.0) -> np.ndarray:
    """Per-channel scale s (3,) such that rho / s obeys `rule` (REFERENCES) with albedo `value`; regions
    with no samples ignored."""
    rho = np.asarray(rho, dtype=np.float64)
    used = np.asarray(counts) > 0
    if not used.any():
        return np.full(3, 1.0 / value)
    if rule == "largest":
        s = rho[int(np.argmax(counts))]
    elif rule == "mean":
        s = rho[used].mean(axis=0)
    elif rule == "max":
        big = np.asarray(counts) >= 0.05 * np.sum(counts)
        s = rho[big if big.any() else used].max(axis=0)
    else:
        raise ValueError(f"albedo reference must be one of {sorted(REFERENCES)}, got {rule!r}")
    return np.where(np.isfinite(s) & (s > 0), s, 1.0) / value


def merge_similar(labels: np.ndarray, rho: np.ndarray, tolerance: float) -> tuple[np.ndarray, int]:
    """Merge regions whose albedos differ by less than `tolerance` in every channel's log (the data
    do not tell them apart); returns relabelled samples (largest first) and the region count."""
    m = len(rho)
    parent = list(range(m))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    logs = np.log(np.maximum(rho, 1e-6))
    close = np.abs(logs[:, None, :] - logs[None, :, :]).max(axis=2) < tolerance
    pairs = np.nonzero(np.triu(close, 1))  # the pairs (a < b) in order
    if not pairs[0].size:
        return by_size(labels)
    for a, b in zip(*pairs):
        parent[root(int(b))] = root(int(a))
    roots = np.array([root(i) for i in range(m)] + [-1])
    return by_size(roots[labels])  # labels -1 -> -1


def _joined(pi: np.ndarray, ni: np.ndarray, pj: np.ndarray, nj: np.ndarray) -> np.ndarray:
    """Whether sample pairs (points p, unit normals n) lie on one surface: the edge between them is convex,
    c = (n_i - n_j).(p_i - p_j) / |p_i - p_j| > CONVEX_TOLERANCE with neither point above the other's tangent
    plane (the top and sides of one box; the second test keeps a floor point beside one face of a box from
    passing as convex with the next face round the corner), or smooth (normals within SMOOTH_DEG) and not
    concave (c > -CONVEX_TOLERANCE). A concave edge (an object standing on the floor, including the rounded
    fillet that fusion makes of that corner) joins nothing."""
    dp = pi - pj
    t = CONVEX_TOLERANCE * np.linalg.norm(dp, axis=1)
    above_i, above_j = -np.einsum("ij,ij->i", ni, dp), np.einsum("ij,ij->i", nj, dp)  # p_j over i's plane, ...
    c = -(above_i + above_j)
    convex = (c > t) & (above_i < t) & (above_j < t)
    return convex | ((np.einsum("ij,ij->i", ni, nj) > math.cos(math.radians(SMOOTH_DEG))) & (c > -t))


@dataclass
class Plane:
    """A plane of samples: unit normal, offset (points p on it have p . normal = offset) and the distance
    tolerance within which a sample counts as on it."""

    normal: np.ndarray
    offset: float
    tolerance: float

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance of points (N, 3) from the plane along its normal."""
        return points @ self.normal - self.offset

    def on(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Samples lying on the plane: within the tolerance and facing within PLANE_DEG of its normal."""
        return ((normals @ self.normal > math.cos(math.radians(PLANE_DEG)))
                & (np.abs(self.height(points)) < self.tolerance))


def sample_spacing(tree, queries: np.ndarray) -> float:
    """Median spacing of the samples of a cKDTree at `queries` (some of its points): the median distance to the
    nearest other sample, or to the second nearest where that is over 1 / COPY_RATIO times as far: then most
    samples come with a copy of the same surface point, as a static camera's frame and the history's kept samples
    of the same pixels do (millimetres apart). The copies' spacing made split_by_geometry cut regions into specks:
    on a static camera over the generated tabletop the white box's samples fell out of every region every other
    frame, and the traced light's irradiance swung between 2.2 and 3.0 (truth 2.8) with them."""
    d = tree.query(queries, k=3)[0]
    nearest, second = median(d[:, 1]), median(d[:, 2])
    return second if np.isfinite(second) and nearest < COPY_RATIO * second else nearest   # two points: no second


def dominant_plane(points: np.ndarray, normals: np.ndarray) -> Plane | None:
    """The plane that at least PLANE_SHARE of the samples lie on (their median normal and median offset, the
    tolerance PLANE_SPACINGS median sample spacings), or None when they are not mostly one plane."""
    if len(points) < 4:
        return None
    from scipy.spatial import cKDTree   # scipy only here and in split_by_geometry
    n0 = np.array([median(v) for v in normals.T])
    n0 /= max(float(np.linalg.norm(n0)), 1e-12)
    spacing = sample_spacing(cKDTree(points, balanced_tree=False), points[::max(1, len(points) // 256)])
    plane = Plane(n0, median(points @ n0), PLANE_SPACINGS * spacing)   # 256 queries: 10x faster, the same spacing
    return plane if plane.on(points, normals).mean() >= PLANE_SHARE else None


def split_off_plane(labels: np.ndarray, points: np.ndarray, normals: np.ndarray, min_count: int) -> np.ndarray:
    """The largest region, where it is mostly one plane (the floor or table a scene stands on: dominant_plane),
    keeps only that plane: samples clearly off it (farther, or facing away by more than OFF_PLANE_DEG)
    become one region of their own when there are min_count of them, samples in between (the rounded fillet
    of the corner at an object's base) none. An object standing on the floor whose shaded faces took the
    floor's colour is then fitted with its own albedo; where it has the floor's albedo after all, the
    solve's merge_similar joins them again. On the generated tabletop a white box (albedo 0.8) sat in the
    floor's region (0.46) as 1-3% of its samples in 10 of 12 frames, too few to flag the region as mixed
    (robust._split_mixed), and pulled the floor's albedo and the traced light's colour."""
    sizes = np.bincount(labels[labels >= 0])
    if sizes.size == 0:
        return labels
    r = int(np.argmax(sizes))
    sel = np.flatnonzero(labels == r)
    if sel.size < 4 * min_count:
        return labels
    p, nrm = points[sel], normals[sel]
    plane = dominant_plane(p, nrm)
    if plane is None:
        return labels
    on = plane.on(p, nrm)
    off = ~on & ((np.abs(plane.height(p)) >= plane.tolerance)
                 | (nrm @ plane.normal < math.cos(math.radians(OFF_PLANE_DEG))))
    if off.sum() < min_count:
        return labels
    out = labels.copy()
    out[sel[off]] = int(labels.max()) + 1
    out[sel[~on & ~off]] = -1
    return by_size(out)[0]


def join_shadows(labels: np.ndarray, lit: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The largest region, where it is mostly one plane (dominant_plane) and mostly lit by the traced light
    (`lit` (N,) bool: the light reaches the sample), takes the samples on that plane of every other region that
    is mostly on it and far more often in the light's shadow (SHADOW_LIT, FLOOR_LIT; a patch of another albedo
    is lit about as often as the plane around it, a shadow's region is not, even where the light is a few degrees
    off and its traced shadow covers a part of the true one): the plane in shadow, which the
    sky tints to a colour region of its own, is the same surface. Without it the shadow's region gets its own
    albedo and explains the shadow away: on the generated tabletop lit by a low sun (HDR rooitou_park, 10
    degrees high) the shadowed floor was 22% of the samples, its albedo a third of the lit floor's, and the
    traced light came out a third as strong as the truth against the sky. Returns new labels, largest first."""
    sizes = np.bincount(labels[labels >= 0])
    if sizes.size < 2:
        return labels
    r0 = int(np.argmax(sizes))
    sel = labels == r0
    plane = dominant_plane(points[sel], normals[sel])
    floor_lit = float(lit[sel].mean())
    if plane is None or floor_lit < FLOOR_LIT:
        return labels
    on = plane.on(points, normals)
    out = labels.copy()
    for r in range(sizes.size):
        part = (labels == r) & on
        if r != r0 and 2 * part.sum() >= sizes[r] > 0 and lit[part].mean() <= SHADOW_LIT * floor_lit:
            out[part] = r0
    return by_size(out)[0]


def split_by_geometry(labels: np.ndarray, flagged, points: np.ndarray, normals: np.ndarray,
                      min_count: int) -> np.ndarray:
    """Split each region in `flagged` into its surfaces (connected components of _joined pairs of samples
    closer than NEIGHBOUR_SPACINGS times the region's median sample spacing: locally convex connected
    patches, the usual way to cut objects off the surface they stand on). A part of which >= JOIN_FRACTION
    of the samples are _joined to samples of one other (unflagged) region continues that surface (a shadowed
    piece of the floor whose colour the sky tinted) and joins that region; of the rest the largest keeps the
    label, others of >= min_count samples become regions and smaller ones get -1.
    Returns new labels, largest region first."""
    from scipy.sparse import coo_matrix                  # scipy only here: the split runs on mixed regions
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    out = labels.copy()
    nxt = int(labels.max()) + 1 if labels.size else 0
    others = np.flatnonzero((labels >= 0) & ~np.isin(labels, list(flagged)))
    # trees built without median splits: about half the build time, the same neighbours
    other_tree = cKDTree(points[others], balanced_tree=False) if others.size else None
    for r in flagged:
        sel = np.flatnonzero(labels == r)
        if sel.size < 2 * min_count:
            continue
        p, nrm = points[sel], normals[sel]
        tree = cKDTree(p, balanced_tree=False)
        radius = NEIGHBOUR_SPACINGS * sample_spacing(tree, p)
        i, j = tree.query_pairs(radius, output_type="ndarray").T
        ok = _joined(p[i], nrm[i], p[j], nrm[j])
        nc, comp = connected_components(coo_matrix((np.ones(ok.sum()), (i[ok], j[ok])), shape=(sel.size,) * 2),
                                        directed=False)
        size = np.bincount(comp, minlength=nc)
        target = -np.ones(nc, dtype=np.int64)
        if other_tree is not None:
            near = other_tree.query_ball_point(p, radius, return_sorted=False)
            counts = np.fromiter(map(len, near), dtype=np.int64, count=len(near))
            a = np.repeat(np.arange(sel.size), counts)
            if a.size:
                b = others[np.fromiter(itertools.chain.from_iterable(near), dtype=np.int64, count=a.size)]
                ok = _joined(p[a], nrm[a], points[b], normals[b])
                m = nxt + 1
                a, region = np.divmod(np.unique(a[ok] * m + labels[b[ok]]), m)  # each (sample, region) once
                share = np.bincount(comp[a] * m + region, minlength=nc * m).reshape(nc, m) / size[:, None]
                best = share.argmax(axis=1)
                target = np.where(share[np.arange(nc), best] >= JOIN_FRACTION, best, -1)
        kept = False
        for c in np.argsort(-size, kind="stable"):
            part = sel[comp == c]
            if target[c] >= 0:
                out[part] = target[c]
            elif not kept:
                kept = True
            elif size[c] >= min_count:
                out[part], nxt = nxt, nxt + 1
            else:
                out[part] = -1
    return by_size(out)[0]
