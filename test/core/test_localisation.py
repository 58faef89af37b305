"""Localisation in an earlier day's map: the drive map, the prior map, the localiser."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import box_scene

from gft_odom.core.geometry import invert_transform, rpy_transform, transform_points
from gft_odom.core.localisation import DriveMap, Localiser, PriorMap
from gft_odom.errors import RegistrationError


def test_the_drive_map_keeps_the_first_point_of_each_voxel_with_its_attributes():
    drive_map = DriveMap(voxel_m=1.0)
    first = np.array([[0.1, 0.1, 0.1], [5.2, 0.1, 0.1]])
    assert drive_map.add(first, np.array([0.5, 0.1]), surface=np.array([1, 2])) == 2
    # One voxel already seen (kept as it was), one new; a voxel twice in one call: the first.
    later = np.array([[0.9, 0.9, 0.9], [9.1, 0.2, 0.2], [9.2, 0.3, 0.3]])
    assert drive_map.add(later, np.array([0.9, 0.3, 0.4]), surface=np.array([0, 0, 1])) == 1
    assert len(drive_map) == 3
    np.testing.assert_allclose(drive_map.points_xyz, [[0.1, 0.1, 0.1], [5.2, 0.1, 0.1],
                                                      [9.1, 0.2, 0.2]])
    np.testing.assert_allclose(drive_map.nu, [0.5, 0.1, 0.3])
    np.testing.assert_array_equal(drive_map.attributes['surface'], [1, 2, 0])
    assert drive_map.add(later, surface=np.zeros(3, dtype=int)) == 0  # nothing new
    with pytest.raises(RegistrationError):
        drive_map.add(np.array([[20.0, 0.0, 0.0]]), surface=np.array([1]), colour=np.array([3]))


def test_a_prior_map_needs_points():
    with pytest.raises(RegistrationError):
        PriorMap(np.zeros((5, 3)), np.zeros(5))


def _drifted(T: np.ndarray) -> np.ndarray:
    """An odometry pose that drifted 0.3 m and 2 degrees from `T`."""
    return rpy_transform((0.3, -0.2, 0.0), (0.0, 0.0, np.radians(2.0))) @ T


def test_the_localiser_takes_the_pose_back_from_a_drifted_odometry():
    scene = box_scene(seed=1)
    prior = PriorMap(scene, np.full(len(scene), np.nan, dtype=np.float32))
    T_map_sensor = rpy_transform((1.0, 0.5, 0.4), (0.0, 0.0, 0.1))
    scan = transform_points(invert_transform(T_map_sensor), box_scene(seed=2))
    T_odom_sensor = np.eye(4)
    localiser = Localiser(prior, _drifted(T_map_sensor))  # map -> odom off by the drift
    result = None
    for _ in range(3):  # a few scans from the same place converge
        result = localiser.localise(scan, T_odom_sensor)
    assert result.status == 'localised'
    assert np.linalg.norm(result.T_map_sensor[:3, 3] - T_map_sensor[:3, 3]) < 0.03
    np.testing.assert_allclose(result.T_map_odom @ T_odom_sensor, result.T_map_sensor)


def test_a_scan_that_does_not_fit_leaves_map_to_odom_as_it_was():
    scene = box_scene(seed=1)
    prior = PriorMap(scene, np.full(len(scene), np.nan, dtype=np.float32))
    far_away = transform_points(rpy_transform((200.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
                                box_scene(seed=3))
    start = rpy_transform((1.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    localiser = Localiser(prior, start)
    result = localiser.localise(far_away, np.eye(4))
    assert result.status == 'not_fitted'
    np.testing.assert_array_equal(localiser.T_map_odom, start)
    np.testing.assert_array_equal(result.T_map_sensor, start)
    assert localiser.localise(np.zeros((10, 3)), np.eye(4)).status == 'too_few_points'


def test_a_selected_map_and_scan_match_only_the_points_kept():
    scene = box_scene(seed=1)
    label = (scene[:, 2] < 1e-9).astype(np.int8)  # 1: ground
    prior = PriorMap(scene, np.zeros(len(scene), dtype=np.float32), {'ground': label})
    walls_and_posts = prior.selected(label == 0)
    assert len(walls_and_posts.points_xyz) == int((label == 0).sum())
    assert not walls_and_posts.attributes['ground'].any()
    T_map_sensor = rpy_transform((0.5, 0.2, 0.4), (0.0, 0.0, 0.05))
    scan = transform_points(invert_transform(T_map_sensor), box_scene(seed=2))
    keep = (transform_points(T_map_sensor, scan)[:, 2] > 0.05)
    localiser = Localiser(walls_and_posts, rpy_transform((0.1, 0.1, 0.0), (0, 0, 0))
                          @ T_map_sensor)
    result = localiser.localise(scan, np.eye(4), keep=keep)
    assert result.status == 'localised'
    assert np.linalg.norm(result.T_map_sensor[:3, 3] - T_map_sensor[:3, 3]) < 0.05


def test_the_drive_map_grows_past_its_buffers_and_stops_at_its_cap():
    rng = np.random.default_rng(0)
    drive_map = DriveMap(voxel_m=0.5, max_points=6000)
    for k in range(4):  # 4 x 2500 distinct voxels: past the first buffer, then the cap
        points = np.c_[np.arange(2500) * 1.0 + 10_000 * k, rng.uniform(0, 0.1, (2500, 2))]
        drive_map.add(points, np.full(2500, k, dtype=np.float32))
    assert len(drive_map) == 6000 and drive_map.full
    np.testing.assert_array_equal(np.bincount(drive_map.nu.astype(int)), [2500, 2500, 1000])
    assert drive_map.add(np.array([[1e6, 0.0, 0.0]])) == 0


def test_smooth_points_weigh_fully_rough_and_unknown_ones_a_quarter():
    from gft_odom.core.localisation import ROUGH_WEIGHT, smoothness_weights
    np.testing.assert_allclose(smoothness_weights(np.array([0.0, 0.2, 0.4, 0.9, np.nan])),
                               [ROUGH_WEIGHT, 0.625, 1.0, 1.0, ROUGH_WEIGHT])


def test_a_map_with_frequencies_is_matched_weighted_and_one_without_alike():
    from gft_odom.core.localisation import MapLocalisation
    scene = box_scene(seed=1)
    with_nu = MapLocalisation(PriorMap(scene, np.full(len(scene), 0.1, np.float32)), np.eye(4))
    np.testing.assert_allclose(with_nu.prior.target.weights, 0.25 + 0.75 * 0.25)
    without = MapLocalisation(PriorMap(scene, np.full(len(scene), np.nan, np.float32)),
                              np.eye(4))
    assert without.prior.target.weights is None
