"""photoreg.kernels.packing: several arrays through one buffer (one upload, one read-back on a GPU). The staging
path runs here on the CPU with pack=True: the same layout a GPU gets, copied once."""
import gc
import weakref

import numpy as np
import pytest

from photoreg.kernels.packing import ALIGN, Packed, upload, wp


def test_packed_parts_are_separate_arrays_read_back_together():
    pk = Packed([((3, 5), wp.float32), ((3, 5), wp.vec3), ((7,), wp.uint8), ((2,), wp.vec4)], "cpu")
    values = [2.5, wp.vec3(1.0, -2.0, 3.0), 9, wp.vec4(4.0, 5.0, 6.0, 7.0)]
    for a, v in zip(pk.arrays, values):
        a.fill_(v)
    assert all(a.ptr % ALIGN == 0 for a in pk.arrays)
    d, v, u, q = pk.numpy()
    assert d.shape == (3, 5) and d.dtype == np.float32 and np.all(d == 2.5)
    assert v.shape == (3, 5, 3) and np.all(v == [1.0, -2.0, 3.0])
    assert u.shape == (7,) and u.dtype == np.uint8 and np.all(u == 9)
    assert q.shape == (2, 4) and np.all(q == [4.0, 5.0, 6.0, 7.0])


def test_an_array_keeps_its_buffer_alive():
    pk = Packed([((4,), wp.float32), ((4,), wp.vec3)], "cpu")
    keep, owner = pk.arrays[1], weakref.ref(pk.buffer)
    keep.fill_(wp.vec3(1.0, 2.0, 3.0))
    host = pk.numpy()[1]   # on the CPU a view of the buffer itself
    del pk
    gc.collect()
    assert owner() is not None and np.all(keep.numpy() == [1.0, 2.0, 3.0])
    del keep
    gc.collect()
    assert owner() is not None and np.all(host == [1.0, 2.0, 3.0])
    del host
    gc.collect()
    assert owner() is None   # freed with the last array pointing into it


@pytest.mark.parametrize("pack", [True, False])
def test_upload_gives_the_inputs(pack):
    rng = np.random.default_rng(0)
    colour = rng.integers(0, 256, (6, 8, 4), dtype=np.uint8)[:, :, :3]   # strided, as pyrender's colour slice
    usable = rng.random((6, 8)) > 0.5                                     # bool into uint8
    depth = rng.random((6, 8))                                            # float64 into float32
    points = rng.random((5, 3)).astype(np.float32)
    c, u, d, p = upload([colour, usable, depth, points], [wp.vec3ub, wp.uint8, wp.float32, wp.vec3], "cpu", pack=pack)
    assert c.shape == (6, 8) and c.dtype == wp.vec3ub and np.array_equal(c.numpy(), colour)
    assert np.array_equal(u.numpy(), usable.astype(np.uint8))
    assert d.dtype == wp.float32 and np.array_equal(d.numpy(), depth.astype(np.float32))
    assert p.shape == (5,) and np.array_equal(p.numpy(), points)
    if pack:   # one buffer: the arrays follow one another at aligned offsets
        assert all(a.ptr % ALIGN == 0 for a in (c, u, d, p)) and c.ptr < u.ptr < d.ptr < p.ptr


def test_upload_and_packed_name_what_does_not_fit():
    with pytest.raises(ValueError, match=r"vec3f must end in \(3,\)"):
        upload([np.zeros((4, 2), np.float32)], [wp.vec3], "cpu", pack=True)
    with pytest.raises(ValueError, match="no numpy layout"):
        Packed([((2,), wp.mat33)], "cpu")
