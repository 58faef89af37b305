"""The map's nearest-neighbour index answers as scipy's cKDTree does."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gft_odom.core.registration.map_index import MapIndex


@pytest.mark.parametrize('k', [1, 4, 15])
def test_map_index_gives_cKDTree_neighbours_within_the_bound(k):
    rng = np.random.default_rng(k)
    points = rng.uniform(-10.0, 10.0, (2000, 3))
    queries = rng.uniform(-12.0, 12.0, (300, 3))
    expected_d, expected_i = cKDTree(points).query(queries, k=k, distance_upper_bound=1.5)
    d, i = MapIndex(points).query(queries, k=k, distance_upper_bound=1.5)
    assert d.shape == expected_d.shape and i.shape == expected_i.shape
    np.testing.assert_array_equal(i, expected_i)
    np.testing.assert_allclose(d, expected_d, rtol=1e-12)
    assert np.any(np.isinf(d))  # some neighbours lie beyond the bound: (inf, n)


def test_map_index_pads_when_k_exceeds_the_points_and_takes_empty_input():
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    d, i = MapIndex(points).query(np.array([[0.1, 0.0, 0.0]]), k=4)
    np.testing.assert_array_equal(i, [[0, 1, 2, 2]])
    np.testing.assert_allclose(d, [[0.1, 0.9, np.inf, np.inf]])
    d, i = MapIndex(points).query(np.zeros((0, 3)), k=4)
    assert d.shape == (0, 4) and i.shape == (0, 4)
    d, i = MapIndex(np.zeros((0, 3))).query(np.ones((2, 3)), k=1)
    np.testing.assert_array_equal(i, [0, 0])
    assert np.all(np.isinf(d))
