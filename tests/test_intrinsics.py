"""The Numba intrinsics: borrowed arrays are the same memory without their reference counts."""

import numpy as np
from numba import njit

from pipeline._intrinsics import borrowed


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
