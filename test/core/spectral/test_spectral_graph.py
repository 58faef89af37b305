"""Slice graphs: the Laplacian's defining properties and the edge cases of slicing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gft_odom.core.spectral.graph import components, gaussian_graph, laplacian
from gft_odom.core.spectral.slicing import slice_points, voxelise
from gft_odom.errors import SpectralError


def random_slices(seed: int, n: int = 300, n_slices: int = 3):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-2.0, 2.0, (n, 2))
    slice_of_point = np.sort(rng.integers(0, n_slices, n))
    return xy, slice_of_point


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), tau=st.floats(0.05, 1.0))
def test_laplacian_symmetric_psd_and_constant_in_nullspace(seed, tau):
    xy, s = random_slices(seed)
    L = laplacian(gaussian_graph(xy, s, tau, tau / 2))
    dense = L.toarray()
    np.testing.assert_allclose(dense, dense.T, atol=1e-12)
    assert np.linalg.eigvalsh(dense).min() > -1e-9
    np.testing.assert_allclose(L @ np.ones(len(xy)), 0.0, atol=1e-10)


def test_weights_match_brute_force_and_never_cross_slices():
    xy, s = random_slices(1, n=150)
    tau, sigma = 0.6, 0.3
    W = gaussian_graph(xy, s, tau, sigma).toarray()
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    expected = np.where((d <= tau) & (s[:, None] == s[None]) & ~np.eye(len(xy), dtype=bool),
                        np.exp(-d**2 / (2 * sigma**2)), 0.0)
    np.testing.assert_allclose(W, expected, atol=1e-12)


def test_graph_without_edges_and_with_one_point():
    far = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    W = gaussian_graph(far, np.zeros(3, dtype=int), 0.5, 0.25)
    assert W.nnz == 0
    assert np.all(laplacian(W).toarray() == 0.0)
    assert components(W)[0] == 3
    one = gaussian_graph(np.zeros((1, 2)), np.zeros(1, dtype=int), 0.5, 0.25)
    assert one.shape == (1, 1) and one.nnz == 0
    empty = gaussian_graph(np.zeros((0, 2)), np.zeros(0, dtype=int), 0.5, 0.25)
    assert empty.shape == (0, 0)


def test_bad_graph_parameters_raise():
    with pytest.raises(SpectralError, match='tau_m'):
        gaussian_graph(np.zeros((3, 2)), None, 0.0, 0.1)


def test_slicing_sorts_by_layer_and_marks_out_of_range():
    z = np.array([0.05, 1.9, -3.0, 0.31, np.nan, 0.0, 2.0, 0.26])
    sl = slice_points(z, 0.25, 0.0, 2.0)
    assert list(sl.in_range) == [True, True, False, True, False, True, False, True]
    layers = np.floor(z[sl.order] / 0.25)
    assert np.all(np.diff(layers) >= 0)
    assert sl.n_slices == len(np.unique(layers))
    assert np.all(np.diff(sl.starts) > 0)
    np.testing.assert_array_equal(np.repeat(np.arange(sl.n_slices), sl.sizes), sl.slice_of_point)
    with pytest.raises(SpectralError):
        slice_points(z, 0.0, 0.0, 2.0)
    with pytest.raises(SpectralError):
        slice_points(z, 0.1, 2.0, 2.0)


def test_voxelise_merges_close_points_within_one_slice_only():
    xy = np.array([[0.01, 0.01], [0.02, 0.03], [0.01, 0.01], [1.0, 1.0]])
    s = np.array([0, 0, 1, 1])
    node_xy, node_slice, starts, node_of_point = voxelise(xy, s, 2, 0.05)
    assert node_xy.shape == (3, 2)
    assert node_of_point[0] == node_of_point[1] != node_of_point[2]
    np.testing.assert_allclose(node_xy[node_of_point[0]], [0.015, 0.02])
    np.testing.assert_array_equal(starts, [0, 1, 3])
    np.testing.assert_array_equal(node_slice, [0, 1, 1])
    same = voxelise(xy, s, 2, 0.0)
    np.testing.assert_array_equal(same[3], np.arange(4))


def ring_points(azimuth_rad: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """One horizontal ring (elevation 0) of returns at the given azimuths and ranges."""
    return np.c_[range_m * np.cos(azimuth_rad), range_m * np.sin(azimuth_rad),
                 np.zeros(azimuth_rad.size)]


def test_range_slope_weights_do_not_fall_with_range_but_distance_weights_do():
    from gft_odom.core.spectral.graph import scan_line_graph
    azimuth = np.deg2rad(np.arange(-10.0, 10.0, 0.2))
    ring = np.zeros(azimuth.size, dtype=np.uint16)
    weights = {}
    for kind in ('distance', 'range_slope'):
        for r in (5.0, 30.0):
            # A wall perpendicular to the middle beam: range r / cos(azimuth).
            L, _ = scan_line_graph(ring_points(azimuth, r / np.cos(azimuth)), ring, 0.2, 0.05,
                                   weight=kind)
            weights[kind, r] = np.median(L.w_next)
    assert weights['range_slope', 30.0] > 0.9 and weights['range_slope', 5.0] > 0.9
    assert weights['distance', 30.0] < 0.5 * weights['distance', 5.0]


def test_range_slope_weights_separate_porous_returns_from_a_surface():
    from gft_odom.core.spectral.graph import scan_line_graph
    rng = np.random.default_rng(0)
    azimuth = np.deg2rad(np.arange(-10.0, 10.0, 0.2))
    ring = np.zeros(azimuth.size, dtype=np.uint16)
    canopy = 8.0 + rng.uniform(0.0, 0.6, azimuth.size)  # returns at random depths
    wall = 8.0 / np.cos(azimuth) + rng.normal(0.0, 0.03, azimuth.size)  # 3 cm range noise
    L, _ = scan_line_graph(ring_points(azimuth, canopy), ring, 0.2, 0.05, weight='range_slope')
    L_wall, _ = scan_line_graph(ring_points(azimuth, wall), ring, 0.2, 0.05,
                                weight='range_slope')
    assert np.median(L.w_next) < 0.4 < 0.8 < np.median(L_wall.w_next)
    with pytest.raises(SpectralError, match='weight'):
        scan_line_graph(ring_points(azimuth, canopy), ring, 0.2, 0.05, weight='angle')
