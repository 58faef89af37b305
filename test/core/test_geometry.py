"""Frame conversions and stamp arithmetic: one helper each, checked against plain algebra."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gft_odom.core.constants import NS_PER_S, ns_to_sec_nanosec, sec_nanosec_to_ns
from gft_odom.core.geometry import (
    along_beams,
    base_to_sensor_poses,
    finite_rows,
    least_variance_axis,
    rotation_matrix,
    rotation_vector,
    rpy_transform,
    sensor_to_base_poses,
)


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


def test_least_variance_axis_is_eighs_smallest_eigenvector():
    rng = np.random.default_rng(3)
    # Planes of random tilt and noise, isotropic blobs, lines (two equal small eigenvalues:
    # the eigh fallback), and a matrix of zeros.
    flat = rng.normal(size=(500, 15, 3)) * [1.0, 0.5, 1e-3]
    rotations = np.linalg.qr(rng.normal(size=(500, 3, 3)))[0]
    clouds = np.concatenate([flat @ rotations, rng.normal(size=(50, 15, 3)),
                             np.linspace(0, 1, 15)[None, :, None] * rng.normal(size=(20, 1, 3))])
    clouds = clouds - clouds.mean(axis=1, keepdims=True)
    C = np.concatenate([np.matmul(clouds.transpose(0, 2, 1), clouds), np.zeros((1, 3, 3))])
    axis = least_variance_axis(C)
    np.testing.assert_allclose(np.linalg.norm(axis, axis=1), 1.0, atol=1e-9)
    values, vectors = np.linalg.eigh(C)
    # The eigenvalue along the axis is the smallest one, to the matrix's scale.
    along = np.einsum('mi,mij,mj->m', axis, C, axis)
    np.testing.assert_allclose(along, values[:, 0], atol=1e-9 * (1.0 + values[:, 2].max()))
    # Where the smallest eigenvalue is well separated, the axis is eigh's, up to sign.
    separated = values[:, 1] > 10.0 * values[:, 0] + 1e-9
    assert separated.sum() >= 500
    dot = np.abs(np.einsum('ij,ij->i', axis[separated], vectors[separated, :, 0]))
    np.testing.assert_allclose(dot, 1.0, atol=1e-9)


@pytest.mark.parametrize('angle_rad', [0.0, 1e-9, 1e-4, 0.1, 1.0, 2.9, 3.1, np.pi])
def test_rotation_vector_and_matrix_are_scipys_log_and_exp(angle_rad):
    rng = np.random.default_rng(int(1e3 * angle_rad))
    for axis in rng.normal(size=(20, 3)):
        rotvec = axis / np.linalg.norm(axis) * angle_rad
        R = Rotation.from_rotvec(rotvec).as_matrix()
        np.testing.assert_allclose(rotation_matrix(rotvec), R, atol=1e-12)
        # At a half turn +v and -v are the same rotation: compare the rotations.
        np.testing.assert_allclose(rotation_matrix(rotation_vector(R)), R, atol=1e-12)
        if angle_rad < 3.0:
            np.testing.assert_allclose(rotation_vector(R), rotvec, atol=1e-12)


def test_finite_rows_is_isfinite_all_along_rows():
    rng = np.random.default_rng(4)
    points = rng.normal(size=(50, 3))
    np.testing.assert_array_equal(finite_rows(points), np.ones(50, dtype=bool))
    points[[3, 17, 40], [0, 2, 1]] = [np.nan, np.inf, -np.inf]
    np.testing.assert_array_equal(finite_rows(points), np.isfinite(points).all(axis=1))
    assert finite_rows(np.zeros((0, 3))).shape == (0,)


def test_along_beams_moves_each_point_radially_by_its_distance():
    points = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 2.0], [1.0, 0.0, 0.0]])
    moved = along_beams(points, np.array([1.0, -0.5, -5.0]))
    np.testing.assert_allclose(np.linalg.norm(moved, axis=1), [6.0, 1.5, 0.5])  # last: halved
    np.testing.assert_allclose(moved / np.linalg.norm(moved, axis=1)[:, None],
                               points / np.linalg.norm(points, axis=1)[:, None])
