"""Frame conversions and stamp arithmetic: one helper each, checked against plain algebra."""

from __future__ import annotations

import numpy as np

from gft_odom.core.constants import NS_PER_S, ns_to_sec_nanosec, sec_nanosec_to_ns
from gft_odom.core.geometry import base_to_sensor_poses, rpy_transform, sensor_to_base_poses


def _random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([rpy_transform(rng.uniform(-5, 5, 3), rng.uniform(-np.pi, np.pi, 3))
                     for _ in range(n)])


def test_sensor_and_base_poses_convert_both_ways():
    T_base_sensor = rpy_transform((0.04, 0.0, 0.38), (0.01, -0.02, 0.3))
    T_world_sensor = _random_poses(5, seed=1)
    base = sensor_to_base_poses(T_world_sensor, T_base_sensor)
    expected = np.stack([T_base_sensor @ P @ np.linalg.inv(T_base_sensor)
                         for P in T_world_sensor])
    np.testing.assert_allclose(base, expected, atol=1e-12)
    np.testing.assert_allclose(base_to_sensor_poses(base, T_base_sensor), T_world_sensor,
                               atol=1e-12)
    # One pose works as a stack of one, and the first sensor frame maps to the odom origin.
    np.testing.assert_allclose(sensor_to_base_poses(T_world_sensor[2], T_base_sensor),
                               base[2], atol=0)
    np.testing.assert_allclose(sensor_to_base_poses(np.eye(4), T_base_sensor), np.eye(4),
                               atol=1e-15)


def test_stamps_convert_exactly():
    stamp_ns = 1_690_000_000_123_456_789
    assert ns_to_sec_nanosec(stamp_ns) == (1_690_000_000, 123_456_789)
    assert sec_nanosec_to_ns(1_690_000_000, 123_456_789) == stamp_ns
    assert ns_to_sec_nanosec(NS_PER_S - 1) == (0, 999_999_999)
    assert ns_to_sec_nanosec(-1) == (-1, 999_999_999)
