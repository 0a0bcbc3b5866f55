"""deepcharuco.core.vectors: the lengths np.linalg.norm gives, bit for bit."""

import numpy as np
import pytest

from deepcharuco.core.vectors import lengths, pairwise_distances


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
