"""The Numba intrinsics: borrowed and carved arrays are the caller's memory without reference counts."""

import numpy as np
from numba import njit

from pipeline._intrinsics import borrowed, carve


@njit(cache=False)
def _write_through(x, k):
    a, scale, (b,) = borrowed(x)
    a[k] = scale * 2.0  # writes land in the caller's arrays
    b[k, 1] = a[k] + 1.0
    return a.shape[0], b.shape, b.strides[0], scale


def test_borrowed_arrays_are_the_callers_memory_with_their_shape_and_scalars_kept():
    a = np.zeros(5)
    b = np.zeros((4, 3))[::2]  # a strided view: shapes and strides carry over
    n, shape, stride, scale = _write_through((a, 1.5, (b,)), 1)
    assert (n, shape, stride, scale) == (5, (2, 3), 48, 1.5)
    assert a.tolist() == [0.0, 3.0, 0.0, 0.0, 0.0] and b[1].tolist() == [0.0, 4.0, 0.0]


@njit(cache=False, _nrt=False)
def _carved(flat, ints, rows):
    a = carve(flat, 3, (rows, 4))  # a runtime shape
    for i in range(rows):
        for j in range(4):
            a[i, j] = 10.0 * i + j
    b = carve(ints, 2, (2, 2, 2))
    b[1, 0, 1] = -7
    return a.shape, a.strides, b.strides


def test_carved_arrays_are_the_buffers_memory_in_c_order_and_leave_the_rest_alone():
    flat = np.full(20, -1.0)
    ints = np.zeros(12, np.int64)
    shape, strides, bstrides = _carved(flat, ints, 3)
    assert shape == (3, 4) and strides == (32, 8) and bstrides == (32, 16, 8)
    assert flat[:3].tolist() == [-1.0] * 3 and flat[15:].tolist() == [-1.0] * 5  # outside the part: untouched
    assert np.array_equal(flat[3:15].reshape(3, 4), 10.0 * np.arange(3)[:, None] + np.arange(4))
    assert ints.tolist() == [0] * 7 + [-7] + [0] * 4  # element (1, 0, 1) of a part starting at 2: 2 + 4 + 1
