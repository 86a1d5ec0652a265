"""Per-frame exposure gain against a fused surface radiance map (real cameras run auto-exposure).

A Lambertian surface point has the same radiance from every view, so a frame whose pixels are all
brighter than the fused model by one factor had its exposure changed, not its lighting. The map
holds the running mean luminance of the gain-corrected samples in world cells of `cell` metres
(a hashed sparse grid, independent of the TSDF). A frame's gain is exp(median(log I - log map)) over
the cells it shares with the map (median: robust to highlights, new shadows and misregistration);
its radiance is divided by the gain before the solve, so the lighting stays on the first frame's
exposure scale instead of jumping with the camera's. Cells forget after `memory` frames (running
mean with capped count), so after a real lighting change the map follows. Without enough overlap the
last gain is kept. The same map tells what a ray that real geometry blocks sees (photoreg.lighting.bounce:
its sorted keys and luminance go to kernels.transfer.observed_bounce).
"""
from __future__ import annotations

import numpy as np

from . import sh

DARK = 1e-3  # luminance below this carries no exposure information (noise, quantisation)
CELL_BITS = 21                     # cell keys: per axis floor(p / cell) + CELL_OFFSET, clamped to CELL_BITS bits,
CELL_OFFSET = 1 << (CELL_BITS - 1)  # packed x, y, z (kernels.transfer.cell_key packs the same on the device)


class ExposureTracker:
    """Fused luminance per world cell and the running exposure gain (module docstring)."""

    def __init__(self, cell: float = 0.02, memory: int = 10, min_matches: int = 30):
        if not (cell > 0 and memory >= 1 and min_matches >= 1):
            raise ValueError("cell > 0, memory >= 1 and min_matches >= 1 are required")
        self.cell, self.memory, self.min_matches = cell, memory, min_matches
        # (sorted cell keys, mean luminance, count): replaced whole by update, so a thread that reads it once sees
        # one consistent map while another updates it (lighting.asynchronous: the frames and the worker, no lock)
        self.map = (np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0))
        self.last_gain = 1.0

    def _keys(self, points: np.ndarray) -> np.ndarray:
        """Cell key of each (finite) world point (M, 3) (CELL_BITS)."""
        c = np.clip(np.floor(points / self.cell).astype(np.int64) + CELL_OFFSET, 0, (1 << CELL_BITS) - 1)
        return (c[:, 0] << (2 * CELL_BITS)) | (c[:, 1] << CELL_BITS) | c[:, 2]

    def _cells(self, points: np.ndarray, radiance: np.ndarray):
        """Unique cell keys of the usable samples and their mean luminance."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        lum = np.asarray(radiance, dtype=np.float64).reshape(-1, 3) @ sh.LUMINANCE
        ok = np.isfinite(p).all(axis=1) & np.isfinite(lum) & (lum > DARK)
        uniq, inv = np.unique(self._keys(p[ok]), return_inverse=True)
        return uniq, np.bincount(inv, weights=lum[ok]) / np.bincount(inv)

    @staticmethod
    def _find(map_keys: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(position in the sorted `map_keys`, whether they hold it) of each cell key."""
        if len(map_keys) == 0:
            return np.zeros(len(keys), dtype=np.int64), np.zeros(len(keys), dtype=bool)
        pos = np.minimum(np.searchsorted(map_keys, keys), len(map_keys) - 1)
        return pos, map_keys[pos] == keys

    def gain(self, points: np.ndarray, radiance: np.ndarray) -> tuple[float, int]:
        """(gain of this frame relative to the map, number of cells compared); the last gain when
        fewer than min_matches cells overlap (1 for the first frame)."""
        map_keys, map_lum, _ = self.map
        keys, lum = self._cells(points, radiance)
        pos, hit = self._find(map_keys, keys)
        n = int(hit.sum())
        if n >= self.min_matches:
            g = float(np.exp(np.median(np.log(lum[hit]) - np.log(map_lum[pos[hit]]))))
            if np.isfinite(g) and g > 0:
                self.last_gain = g
        return self.last_gain, n

    def update(self, points: np.ndarray, radiance: np.ndarray) -> None:
        """Fuse gain-corrected samples into the map (running mean, count capped at `memory`)."""
        keys, lum = self._cells(points, radiance)
        if keys.size == 0:
            return
        map_keys, map_lum, map_count = self.map
        all_keys = np.union1d(map_keys, keys)
        new_lum, new_count = np.zeros(len(all_keys)), np.zeros(len(all_keys))
        old = np.searchsorted(all_keys, map_keys)
        new_lum[old], new_count[old] = map_lum, map_count
        at = np.searchsorted(all_keys, keys)
        new_count[at] = np.minimum(new_count[at] + 1, self.memory)
        new_lum[at] += (lum - new_lum[at]) / new_count[at]
        self.map = (all_keys, new_lum, new_count)
