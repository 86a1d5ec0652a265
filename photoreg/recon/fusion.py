"""TSDF fusion with Open3D's VoxelBlockGrid, and its export to a dense Warp SDF brick.

Open3D 0.20 conventions (checked in tests/test_fusion_kernels.py):
- integrate/ray_cast take the extrinsic as world-to-camera and depth in depth_scale units (we pass
  float metres with depth_scale = 1);
- 'tsdf' holds the projective SDF (depth - z_camera) divided by the truncation and clamped to [-1, 1],
  positive in front of surfaces; voxels more than one truncation behind a surface are left alone;
  'weight' counts the frames that updated a voxel (0 = never observed);
- block b, local voxel (x, y, z) sits at world (b * res + (x, y, z)) * voxel_size and is stored at
  attribute[buf, z, y, x] (z-major inside the block);
- ray_cast returns camera-frame vertices and normals, the normals pointing away from the camera.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from photoreg.device import init_warp, open3d_device
from photoreg.io.poses import check_pose
from photoreg.kernels.grid import SDF_DTYPE, DenseGrid, copy_into, scatter_blocks, update_empty_distance
from photoreg.preprocess import masked_depth
from photoreg.types import Intrinsics

wp = init_warp()


class VolumeLimitError(ValueError):
    """A frame would stretch the dense brick past FusionConfig.max_dense_voxels (a wrong pose, usually): it was not
    fused, and the volume is as it was."""


# frames in a row that do not fit with the fused volume (VolumeLimitError) before it starts again from the next one:
# one wrong pose is left out, but a first pose that was wrong, or a camera that walked past the brick's size, does not
# keep every later frame out
RESTART_AFTER = 3


@dataclass
class FusionConfig:
    """TSDF volume settings (metres)."""

    voxel_size: float = 0.01
    block_resolution: int = 16         # voxels per block edge
    block_count: int = 4000            # initial hash map capacity; Open3D doubles it when full. Each
                                       # block preallocates res^3 * 8 bytes (32 KB at res 16)
    trunc_voxels: float = 4.0          # truncation distance in voxels
    depth_min: float = 0.1             # depth below this is ignored (sensor near limit)
    depth_max: float = 4.0             # depth beyond this is ignored
    min_weight: float = 1.0            # voxels with less integrated weight count as unobserved
    grid_margin_blocks: int = 1        # extra blocks around the touched region when the brick (re)grows
    # A side the brick must grow on grows by at least this share of the brick's extent on that axis, so a
    # turning camera regrows it less often (each growth copies the whole brick). A live scan of a 4 x 4 x 3 m
    # room (72 views, an export per frame): 8 growths and a 384 MiB brick; 0.25: 7 and 605 MiB; 0: 9, 302 MiB.
    grid_growth: float = 0.1
    max_dense_voxels: int = 1 << 27    # dense brick limit (256 MB of float16)

    def __post_init__(self):
        if not (self.voxel_size > 0 and self.trunc_voxels > 0 and self.block_resolution > 0):
            raise ValueError("voxel_size, trunc_voxels and block_resolution must be positive")
        if not 0 <= self.depth_min < self.depth_max:
            raise ValueError(f"need 0 <= depth_min < depth_max, got {self.depth_min}, {self.depth_max}")
        if self.grid_margin_blocks < 0 or self.max_dense_voxels <= 0 or not self.grid_growth >= 0:
            raise ValueError("grid_margin_blocks and grid_growth must be >= 0 and max_dense_voxels > 0")

    @property
    def trunc(self) -> float:
        """Truncation distance in metres."""
        return self.trunc_voxels * self.voxel_size


class TSDFVolume:
    """An Open3D VoxelBlockGrid ('tsdf', 'weight') plus a dense SDF brick on the Warp device. No colour is
    fused: nothing reads it (the lighting samples each frame's own radiance), and it cost 37% of a CPU
    integration (TUM 640x480, 53 -> 33 ms) and 12 of every voxel's 20 bytes.

    integrate() fuses frames; dense_grid() brings the brick up to date with the blocks touched since
    the last export (scattered by a Warp kernel straight from Open3D's buffers via DLPack).
    """

    def __init__(self, cfg: FusionConfig | None = None, device: str = "cpu"):
        import open3d as o3d

        self.cfg = cfg or FusionConfig()
        self.device = str(wp.get_device(device))  # Warp device string, e.g. "cpu" or "cuda:0"
        self._o3d = o3d
        self.o3d_device = open3d_device(self.device)
        self.frames_integrated = 0
        self.rejected_in_row = 0   # frames refused in a row for the brick's size (RESTART_AFTER)
        self.restarts = 0          # times the volume started again
        self._start()

    def _start(self) -> None:
        """An empty volume: a new VoxelBlockGrid, no brick yet."""
        c = self._o3d.core
        self.vbg = self._o3d.t.geometry.VoxelBlockGrid(
            ("tsdf", "weight"), (c.float32, c.float32), ((1,), (1,)),
            self.cfg.voxel_size, self.cfg.block_resolution, self.cfg.block_count, self.o3d_device)
        self._pending: list = []   # block-coordinate tensors touched since the last export
        self._pending_bounds = None  # their (lo, hi) block coordinates, inclusive
        self._sdf = None           # wp.array3d brick
        self._occupied = None      # uint8 per block: any voxel below +trunc
        self._empty = None         # uint8 per block: Chebyshev distance to the nearest occupied block
        self._lo_block = None      # (3,) int64 block coordinate of the brick's first block
        self._dims_blocks = None   # (3,) int64 brick size in blocks

    # --- Open3D side -------------------------------------------------------------------------
    def _tensor(self, a: np.ndarray):
        return self._o3d.core.Tensor(np.ascontiguousarray(a), device=self.o3d_device)

    def _camera(self, intr: Intrinsics, pose_c2w: np.ndarray, where: str):
        intr.check(where)
        pose = check_pose(pose_c2w, where)
        return self._o3d.core.Tensor(intr.K), self._o3d.core.Tensor(np.linalg.inv(pose)), pose

    def integrate(self, depth: np.ndarray, intr: Intrinsics, pose_c2w: np.ndarray, clean: bool = False) -> None:
        """Fuse one frame: depth HxW metres (0/NaN invalid; outside [depth_min, depth_max] ignored), pose
        camera-to-world. clean: the depth is finite with 0 wherever it is below depth_min (preprocess.prepare's,
        with a depth_min of at least this volume's), so it is not masked again (0.4-0.5 ms a 640x480 frame on the
        H100's host)."""
        o3d = self._o3d
        depth = np.asarray(depth, dtype=np.float32)
        if depth.shape != (intr.height, intr.width):
            raise ValueError(f"depth shape {depth.shape} does not match intrinsics {intr.height}x{intr.width}")
        K, extrinsic, _ = self._camera(intr, pose_c2w, "TSDFVolume.integrate")
        # Open3D reads the depth pixel floor(u) for a voxel projecting to u; shifting the principal
        # point by half a pixel makes that the nearest pixel (OpenCV: pixel centres at integers).
        K_nearest = K + self._o3d.core.Tensor(np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [0.0, 0.0, 0.0]]))
        cfg = self.cfg
        if not clean:
            depth = masked_depth(depth, cfg.depth_min)[0]
        if not np.any((depth > 0) & (depth < cfg.depth_max)):
            return  # nothing to fuse (Open3D would raise)
        depth_img = o3d.t.geometry.Image(self._tensor(depth))
        depth_max, trunc_voxels = float(cfg.depth_max), float(cfg.trunc_voxels)
        try:
            blocks = self.vbg.compute_unique_block_coordinates(depth_img, K, extrinsic, 1.0, depth_max, trunc_voxels)
        except RuntimeError as e:   # Open3D raises where its touch pass finds no block (a pixel of depth in an 8x6
            if "No block is touched" in str(e):   # frame; a 640x480 frame's single pixel touches one): nothing to fuse
                return
            raise
        if blocks.shape[0] == 0:
            return
        own = tuple(b.cpu().numpy().astype(np.int64) for b in (blocks.min(dim=[0]), blocks.max(dim=[0])))
        lo, hi = own
        if self._pending_bounds is not None:
            lo, hi = np.minimum(lo, self._pending_bounds[0]), np.maximum(hi, self._pending_bounds[1])
        new_lo, new_hi, n_vox = self._brick(lo, hi)
        if n_vox > self.cfg.max_dense_voxels:
            self.rejected_in_row += 1
            alone = math.prod(int(d) * self.cfg.block_resolution for d in own[1] - own[0] + 1)
            if self.rejected_in_row < RESTART_AFTER or alone > self.cfg.max_dense_voxels:
                raise VolumeLimitError(f"{self._limit_message(n_vox, new_hi - new_lo + 1)}; the frame (camera at "
                                       f"{np.round(np.asarray(pose_c2w)[:3, 3], 3).tolist()} m) was not fused")
            self._start()   # RESTART_AFTER frames in a row did not fit: this one starts the volume again
            self.restarts += 1
            lo, hi = own
        self.rejected_in_row = 0
        self.vbg.integrate(blocks, depth_img, K_nearest, extrinsic, 1.0, depth_max, trunc_voxels)
        self._pending.append(blocks)
        self._pending_bounds = (lo, hi)
        self.frames_integrated += 1

    def active_block_coords(self):
        """(M, 3) int32 Open3D tensor of every allocated block."""
        hm = self.vbg.hashmap()
        return hm.key_tensor()[hm.active_buf_indices().to(self._o3d.core.int64)]

    def _raycast_o3d(self, intr: Intrinsics, pose_c2w: np.ndarray, attributes: list[str], where: str):
        """Open3D's VoxelBlockGrid.ray_cast of the given attributes; None when the volume is empty."""
        K, extrinsic, pose = self._camera(intr, pose_c2w, where)
        blocks = self.active_block_coords()
        if blocks.shape[0] == 0:
            return None
        # Open3D 0.20 sizes its range-map fragment buffer from the range-map area: with too few
        # range pixels per block it leaves pixels unrendered or hangs, so keep >= 8 pixels per block.
        factor = 8
        while factor > 1 and (intr.height // factor) * (intr.width // factor) < 8 * blocks.shape[0]:
            factor //= 2
        cfg = self.cfg
        return self.vbg.ray_cast(blocks, K, extrinsic, intr.width, intr.height, attributes, 1.0,
                                 float(cfg.depth_min), float(cfg.depth_max), float(cfg.min_weight),
                                 float(cfg.trunc_voxels), factor)

    def raycast_open3d(self, intr: Intrinsics, pose_c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Open3D's own ray cast (the reference for the Warp one): depth HxW metres (0 = miss) and
        world-frame unit normals HxWx3 pointing toward free space (0 = miss)."""
        out = self._raycast_o3d(intr, pose_c2w, ["depth", "normal"], "TSDFVolume.raycast_open3d")
        if out is None:
            return np.zeros((intr.height, intr.width), np.float32), np.zeros((intr.height, intr.width, 3), np.float32)
        depth = out["depth"].cpu().numpy()[..., 0].astype(np.float32)
        normal_cam = out["normal"].cpu().numpy().astype(np.float64)
        normal = -(normal_cam @ np.asarray(pose_c2w)[:3, :3].T)
        normal[depth <= 0] = 0.0
        return depth, normal.astype(np.float32)

    def extract_mesh(self):
        """Marching-cubes mesh (open3d.t.geometry.TriangleMesh) of observed voxels."""
        return self.vbg.extract_triangle_mesh(weight_threshold=float(self.cfg.min_weight))

    # --- dense Warp brick ----------------------------------------------------------------------
    def _to_warp(self, tensor):
        a = wp.from_dlpack(tensor.to_dlpack())
        return a if str(a.device) == str(wp.get_device(self.device)) else a.to(self.device)

    def _brick(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """(first block, last block, voxels) of the brick that covers blocks [lo, hi] (inclusive): a new brick with
        grid_margin_blocks round them; a grown one extends only the sides that fall short, each by the blocks it
        lacks plus max(grid_margin_blocks, grid_growth * its extent); without margin or slack where they would pass
        max_dense_voxels."""
        R, m = self.cfg.block_resolution, self.cfg.grid_margin_blocks
        if self._sdf is not None:
            cur_lo, cur_hi = self._lo_block, self._lo_block + self._dims_blocks - 1
            slack = np.maximum(m, np.ceil(self.cfg.grid_growth * self._dims_blocks)).astype(np.int64)
            lo, hi = np.minimum(lo, cur_lo), np.maximum(hi, cur_hi)
            new_lo, new_hi = np.where(lo < cur_lo, lo - slack, lo), np.where(hi > cur_hi, hi + slack, hi)
        else:
            new_lo, new_hi = lo - m, hi + m
        voxels = math.prod(int(d) * R for d in new_hi - new_lo + 1)   # Python ints: no overflow for absurd poses
        if voxels > self.cfg.max_dense_voxels:
            new_lo, new_hi = lo, hi
            voxels = math.prod(int(d) * R for d in new_hi - new_lo + 1)
        return new_lo, new_hi, voxels

    def _limit_message(self, n_vox: int, dims_blocks: np.ndarray) -> str:
        size_m = dims_blocks * self.cfg.block_resolution * self.cfg.voxel_size
        return (f"dense SDF brick would need {n_vox} voxels ({size_m[0]:.4g} x {size_m[1]:.4g} x {size_m[2]:.4g} m at "
                f"{self.cfg.voxel_size} m), more than FusionConfig.max_dense_voxels = {self.cfg.max_dense_voxels}: "
                "a wrong pose or wrong intrinsics, or a scene that needs larger voxels (reconstruction.voxel_size) "
                "or a smaller reconstruction.depth_max")

    def _ensure_covers(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Allocate or grow the brick so that it covers blocks [lo, hi] (inclusive), as _brick sizes it."""
        R = self.cfg.block_resolution
        if self._sdf is not None:
            cur_lo, cur_hi = self._lo_block, self._lo_block + self._dims_blocks - 1
            if np.all(lo >= cur_lo) and np.all(hi <= cur_hi):
                return
        new_lo, new_hi, n_vox = self._brick(lo, hi)
        dims = (new_hi - new_lo + 1).astype(np.int64)
        if n_vox > self.cfg.max_dense_voxels:
            raise RuntimeError(self._limit_message(n_vox, dims))
        sdf = wp.full(tuple(int(d * R) for d in dims), self.cfg.trunc, dtype=SDF_DTYPE, device=self.device)
        occupied = wp.zeros(tuple(int(d) for d in dims), dtype=wp.uint8, device=self.device)
        if self._sdf is not None:
            copy_into(self._sdf, sdf, (self._lo_block - new_lo) * R)
            copy_into(self._occupied, occupied, self._lo_block - new_lo)
        self._sdf, self._occupied, self._empty = sdf, occupied, wp.empty_like(occupied)
        self._lo_block, self._dims_blocks = new_lo.astype(np.int64), dims

    def dense_grid(self) -> DenseGrid:
        """The dense SDF brick, updated with every block touched since the last call (before any
        integration: an all-empty brick around the origin)."""
        cfg, R = self.cfg, self.cfg.block_resolution
        if self._sdf is None and not self._pending:
            self._ensure_covers(np.zeros(3, np.int64), np.zeros(3, np.int64))
            update_empty_distance(self._occupied, self._empty)
        if self._pending:
            o3c = self._o3d.core
            blocks = self._pending[0] if len(self._pending) == 1 else o3c.concatenate(self._pending, 0)
            self._ensure_covers(*self._pending_bounds)
            bufs, found = self.vbg.hashmap().find(blocks)
            cap = self.vbg.hashmap().capacity()
            tsdf = self.vbg.attribute("tsdf").reshape((cap, R ** 3))
            weight = self.vbg.attribute("weight").reshape((cap, R ** 3))
            scatter_blocks(self._to_warp(blocks.contiguous()), self._to_warp(bufs), self._to_warp(found),
                           self._to_warp(tsdf), self._to_warp(weight), R, self._lo_block, cfg.trunc,
                           cfg.min_weight, self._sdf, self._occupied)
            update_empty_distance(self._occupied, self._empty)
            wp.synchronize_device(self.device)  # the DLPack views of Open3D's buffers end here
            self._pending, self._pending_bounds = [], None
        return DenseGrid(sdf=self._sdf, origin=(self._lo_block * R).astype(np.float64) * cfg.voxel_size,
                         voxel_size=float(cfg.voxel_size), trunc=float(cfg.trunc),
                         shape=tuple(int(s) for s in self._sdf.shape), empty=self._empty, cell=R)
