"""Several arrays through one host-device copy. On a GPU every upload (wp.array of numpy data) and every read-back
(.numpy()) costs a fixed host time besides its bytes (0.03-0.04 ms a call on the H100's host, benchmarks/copy_cost.py;
a held frame with an object made 13 uploads and 15 read-backs): the arrays of one launch travel as one byte buffer
instead, cut into Warp arrays that point into it (each keeps the buffer alive). On the CPU nothing is copied either way.
"""
from __future__ import annotations

import numpy as np

from photoreg.device import init_warp

wp = init_warp()

ALIGN = 16   # bytes: each array starts on this boundary in the buffer
_NUMPY = {wp.float32: (np.float32, ()), wp.vec3: (np.float32, (3,)), wp.vec4: (np.float32, (4,)),
          wp.uint8: (np.uint8, ()), wp.vec3ub: (np.uint8, (3,)), wp.int64: (np.int64, ())}


def _numpy_of(dtype) -> tuple[type, tuple[int, ...]]:
    if dtype not in _NUMPY:
        raise ValueError(f"packing: no numpy layout for the Warp dtype {dtype}")
    return _NUMPY[dtype]


def _layout(parts: list[tuple[tuple[int, ...], type]]) -> tuple[list[int], int]:
    """Byte offsets of the parts (shape, Warp dtype) in one buffer, and its size."""
    offsets, end = [], 0
    for shape, dtype in parts:
        offsets.append(end)
        end += -(-int(np.prod(shape, dtype=np.int64)) * wp.types.type_size_in_bytes(dtype) // ALIGN) * ALIGN
    return offsets, max(end, ALIGN)


def _views(buffer: wp.array, parts, offsets: list[int]) -> list[wp.array]:
    """Warp arrays of the parts pointing into `buffer`; each holds it (its deleter's default) so the memory outlives
    whichever array is dropped last."""
    return [wp.array(ptr=buffer.ptr + off, dtype=dtype, shape=tuple(shape), device=buffer.device,
                     deleter=lambda ptr, size, owner=buffer: None) for (shape, dtype), off in zip(parts, offsets)]


class Packed:
    """Kernel outputs (shape, Warp dtype) in one device buffer: `arrays` to launch with, `numpy` reads them all back in
    one copy."""

    def __init__(self, parts: list[tuple[tuple[int, ...], type]], device: str):
        self.parts = [(tuple(int(s) for s in shape), dtype) for shape, dtype in parts]
        for _, dtype in self.parts:
            _numpy_of(dtype)   # a dtype numpy() could not read back fails here, before any launch
        self.offsets, size = _layout(self.parts)
        self.buffer = wp.empty(size, dtype=wp.uint8, device=device)
        self.arrays = _views(self.buffer, self.parts, self.offsets)

    def numpy(self) -> list[np.ndarray]:
        """Host copies of the arrays (views of one read-back; on the CPU views of the arrays themselves)."""
        raw = self.buffer.numpy()
        out = []
        for (shape, dtype), off in zip(self.parts, self.offsets):
            scalar, inner = _numpy_of(dtype)
            n = int(np.prod(shape, dtype=np.int64)) * wp.types.type_size_in_bytes(dtype)
            out.append(raw[off:off + n].view(scalar).reshape(shape + inner))
        return out


def upload(arrays: list[np.ndarray], dtypes: list, device: str, pack: bool | None = None) -> list[wp.array]:
    """Warp arrays on `device` of numpy `arrays` (each of its dtype's layout: (..., 3) float32 for wp.vec3). Packed (on
    a GPU by default): one copy, each array cast and gathered into the staging buffer once, strided ones too. Else one
    by one, made contiguous first: on the CPU wrapping the numpy memory without copying, on a GPU one copy each (for
    large arrays contiguous already, which packing would copy once more on the host)."""
    arrays, parts, scalars = [np.asarray(a) for a in arrays], [], []
    for a, dt in zip(arrays, dtypes):
        scalar, inner = _numpy_of(dt)
        if inner and a.shape[a.ndim - len(inner):] != inner:
            raise ValueError(f"upload: an array of {dt.__name__} must end in {inner}, got {a.shape}")
        parts.append((a.shape[:a.ndim - len(inner)], dt))
        scalars.append(scalar)
    on_cpu = wp.get_device(device).is_cpu
    if not (pack if pack is not None else not on_cpu):
        return [wp.array(np.ascontiguousarray(a, dtype=scalar), dtype=dt, device=device, copy=not on_cpu)
                for a, dt, scalar in zip(arrays, dtypes, scalars)]
    offsets, size = _layout(parts)
    staging = np.empty(size, np.uint8)   # the padding between arrays is never read
    for a, scalar, off in zip(arrays, scalars, offsets):
        staging[off:off + a.size * np.dtype(scalar).itemsize].view(scalar).reshape(a.shape)[...] = a
    return _views(wp.array(staging, dtype=wp.uint8, device=device), parts, offsets)
