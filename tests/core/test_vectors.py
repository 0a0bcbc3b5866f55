"""deepcharuco.core.vectors: the lengths np.linalg.norm gives, and the rows np.c_ makes, bit for bit."""

import numpy as np
import pytest

from deepcharuco.core.vectors import homogeneous, lengths, pairwise_distances


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_lengths_equal_numpy_norm_bit_for_bit(dtype):
    rng = np.random.default_rng(0)
    vectors = (rng.normal(size=(40, 30, 2)) * rng.choice([1e-3, 1.0, 300.0], size=(40, 30, 1))).astype(dtype)
    result = lengths(vectors)
    assert result.dtype == dtype and result.shape == (40, 30)
    np.testing.assert_array_equal(result, np.linalg.norm(vectors, axis=-1))
    assert lengths(np.array([3.0, -4.0])) == 5.0


def test_pairwise_distances():
    a, b = np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[3.0, 4.0], [1.0, 1.0], [0.0, 0.0]])
    np.testing.assert_array_equal(pairwise_distances(a, b), [[5.0, np.sqrt(2.0), 0.0], [np.sqrt(13.0), 0.0, np.sqrt(2.0)]])
    np.testing.assert_array_equal(pairwise_distances(a, b), np.linalg.norm(a[:, None] - b[None], axis=2))


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int64])
def test_homogeneous_rows_are_what_numpy_c_makes(dtype):
    xy = (np.random.default_rng(1).normal(size=(7, 2)) * 100).astype(dtype)
    rows = homogeneous(xy[::-1])  # a view with negative strides, as callers pass slices
    expected = np.c_[xy[::-1], np.ones(len(xy))]
    assert rows.dtype == expected.dtype == np.float64 and rows.flags.c_contiguous
    np.testing.assert_array_equal(rows, expected)
    assert homogeneous(np.zeros((0, 2))).shape == (0, 3)
