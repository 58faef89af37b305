"""The anchor store: sorted by voxel key in two runs, served by slab, the same as one array."""

import numpy as np
import pytest

from gft_odom.core.registration.anchors import AnchorStore, _insert
from gft_odom.core.registration.local_map import LocalMap
from gft_odom.core.registration.voxels import voxel_keys, voxel_x_slab


def test_insert_matches_numpy_for_rows_and_values():
    rng = np.random.default_rng(1)
    old = np.sort(rng.integers(0, 1000, 50))
    new = np.sort(rng.integers(0, 1000, 7))
    at = np.searchsorted(old, new)
    assert np.array_equal(_insert(old, at, new), np.insert(old, at, new))
    rows, new_rows = rng.random((50, 3)), rng.random((7, 3))
    assert np.array_equal(_insert(rows, at, new_rows), np.insert(rows, at, new_rows, axis=0))
    assert _insert(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3))).shape == (0, 3)


def _brute_near(points, x_m, radius_m):
    """Every anchor within the radius along x, sorted by voxel key: one sorted array."""
    keys = voxel_keys(points, 0.3)
    order = np.argsort(keys)
    near = np.abs(points[order, 0] - x_m) <= radius_m
    return points[order][near]


@pytest.mark.parametrize('recent_rows', [1, 40, 10_000])
def test_the_store_serves_what_one_sorted_array_would(recent_rows):
    """Anchors added in batches (some flushed into the large run, some recent) are served
    near a point as one sorted array would give them: the same points, in key order."""
    rng = np.random.default_rng(2)
    store = AnchorStore(recent_rows=recent_rows)
    every = np.zeros((0, 3))
    for _ in range(12):
        points = rng.uniform([-100.0, -20.0, 0.0], [100.0, 20.0, 3.0], (30, 3))
        keys, first = np.unique(voxel_keys(points, 0.3), return_index=True)
        known, _ = store.find(keys)
        store.add(keys[~known], points[first][~known], rng.random((~known).sum()),
                  np.zeros(((~known).sum(), 3)))
        every = np.vstack([every, points[first][~known]])
    assert len(store) == every.shape[0]
    for x_m in (-60.0, 0.0, 75.0):
        points, _, _ = store.in_slab(*voxel_x_slab(x_m, 20.0, 0.3))
        within = np.abs(points[:, 0] - x_m) <= 20.0
        # A superset by at most the margin voxels, in key order, holding every anchor within.
        assert np.all(np.abs(points[:, 0] - x_m) <= 20.0 + 0.9)
        assert np.all(np.diff(voxel_keys(points, 0.3)) > 0)
        assert np.array_equal(points[within], _brute_near(every, x_m, 20.0))


def test_found_anchors_report_their_smoothness_and_can_be_replaced():
    store = AnchorStore(recent_rows=1)
    points = np.array([[0.1, 0.1, 0.1], [5.1, 0.1, 0.1]])
    keys = voxel_keys(points, 0.3)
    store.add(keys[:1], points[:1], np.array([0.2]), np.zeros((1, 3)))
    store.add(keys[1:], points[1:], np.array([0.9]), np.zeros((1, 3)))  # flushes the first
    known, smoothness = store.find(np.r_[keys, 12345])
    assert known.tolist() == [True, True, False]
    assert smoothness[:2].tolist() == [0.2, 0.9] and np.isnan(smoothness[2])
    store.replace(keys[:1], np.array([[0.2, 0.2, 0.2]]), np.array([1.0]), np.ones((1, 3)))
    points_near, smooth_near, views = store.in_slab(*voxel_x_slab(0.0, 1.0, 0.3))
    assert points_near.tolist() == [[0.2, 0.2, 0.2]]
    assert smooth_near.tolist() == [1.0] and views.tolist() == [[1.0, 1.0, 1.0]]


def test_a_long_runs_anchors_far_away_are_not_served():
    """A map with anchors along 2 km serves only those near its newest keyframe."""
    local_map = LocalMap(0.3, 40.0, 80_000, 1, 1.0)
    rng = np.random.default_rng(3)
    farm = rng.uniform([-1000.0, -50.0, 0.0], [1000.0, 50.0, 3.0], (20_000, 3))
    keys, first = np.unique(voxel_keys(farm, 0.3), return_index=True)
    # Each seen from where the keyframe will stand: the view rule serves them all.
    local_map._anchors.add(keys, farm[first], np.ones(first.shape[0]),
                           np.tile([500.0, 0.0, 0.0], (first.shape[0], 1)))
    T = np.eye(4)
    T[0, 3] = 500.0
    local_map.add_keyframe(np.array([[500.0, 0.0, 0.0]]), T, np.array([1.0]))
    served = local_map.points_xyz
    expected = farm[first][np.linalg.norm(farm[first] - T[:3, 3], axis=1) <= 40.0]
    assert served.shape[0] == expected.shape[0] + 1  # and the keyframe's own point
    assert {tuple(p) for p in expected} <= {tuple(p) for p in served}
