"""Solver 'map_tree': open3d's point-to-plane ICP, reproduced over a kept KD-tree."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from helpers import box_scene, target_of
from scipy.spatial.transform import Rotation

from gft_odom.core.geometry import invert_transform, make_transform
from gft_odom.core.map_tree_icp import ExactNearest, MapTreeICP, euler_update
from gft_odom.core.registration import RegistrationConfig
from gft_odom.errors import ConfigError

reg = o3d.pipelines.registration
T_TRUE = make_transform(Rotation.from_euler('z', 4.0, degrees=True).as_matrix(),
                        [0.3, -0.15, 0.02])


@pytest.fixture(scope='module')
def scene():
    points = box_scene(seed=4)
    source = (invert_transform(T_TRUE)[:3, :3] @ points.T).T + invert_transform(T_TRUE)[:3, 3]
    source = source[::3] + np.random.default_rng(5).normal(0.0, 0.02, source[::3].shape)
    return target_of(points), source


def open3d_icp(target, source, init, distance_m, kernel, iterations):
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target.points))
    cloud.normals = o3d.utility.Vector3dVector(target.normals)
    return reg.registration_icp(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)), cloud, distance_m, init,
        reg.TransformationEstimationPointToPlane(kernel), reg.ICPConvergenceCriteria(
            1e-4, 1e-4, iterations))


@pytest.mark.parametrize('kernel', ['tukey', 'huber', 'none'])
@pytest.mark.parametrize('iterations', [1, 3, 30])
def test_reproduces_open3d_step_for_step(scene, kernel, iterations):
    target, source = scene
    o3d_kernel = {'tukey': reg.TukeyLoss(0.3), 'huber': reg.HuberLoss(0.3),
                  'none': reg.L2Loss()}[kernel]
    init = make_transform(Rotation.from_euler('z', 1.0, degrees=True).as_matrix(),
                          [0.05, 0.02, 0.0])
    theirs = open3d_icp(target, source, init, 1.0, o3d_kernel, iterations)
    ours = MapTreeICP(kernel, 0.3, 1e-4, 1e-4, iterations).register(source, target, init, 1.0)
    np.testing.assert_allclose(ours.transformation, np.asarray(theirs.transformation),
                               atol=1e-9)
    assert ours.fitness == pytest.approx(theirs.fitness, abs=1e-12)
    assert ours.inlier_rmse == pytest.approx(theirs.inlier_rmse, rel=1e-9)
    np.testing.assert_array_equal(ours.correspondence_set,
                                  np.asarray(theirs.correspondence_set))


def test_recovers_a_known_transform(scene):
    target, source = scene
    result = MapTreeICP('tukey', 0.3, 1e-6, 1e-6, 50).register(source, target, np.eye(4), 1.0)
    error = invert_transform(T_TRUE) @ result.transformation
    assert np.linalg.norm(error[:3, 3]) < 0.01
    assert Rotation.from_matrix(error[:3, :3]).magnitude() < np.deg2rad(0.05)
    assert result.information is None  # icp_information computes it from the pairs


def test_exact_nearest_matches_a_full_search_as_the_points_move(scene):
    target, source = scene
    nearest = ExactNearest(target, 1.0)
    rng = np.random.default_rng(6)
    world = source.copy()
    for step in range(6):
        valid, index, distance = nearest.query(world)
        d, full = target.tree.query(world, k=1, distance_upper_bound=1.0)
        np.testing.assert_array_equal(valid, np.flatnonzero(np.isfinite(d)))
        np.testing.assert_array_equal(index, full[valid])
        np.testing.assert_allclose(distance, d[valid])
        world = world + rng.normal(0.0, 0.02 * (step + 1), 3)  # moves of 2 to 12 cm
    # It searched again only for the points its candidates could no longer vouch for.
    assert nearest.n_searched < 6 * source.shape[0]


def test_no_pairs_leaves_the_guess():
    target = target_of(box_scene(seed=7))
    far = np.array([[500.0, 500.0, 0.0]] * 10)
    result = MapTreeICP().register(far, target, np.eye(4), 1.0)
    np.testing.assert_array_equal(result.transformation, np.eye(4))
    assert result.fitness == 0.0 and result.correspondence_set.shape == (0, 2)


def test_euler_update_is_open3d_order():
    x = np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0])
    expected = Rotation.from_euler('ZYX', x[2::-1]).as_matrix()  # Rz @ Ry @ Rx
    np.testing.assert_allclose(euler_update(x)[:3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(euler_update(x)[:3, 3], x[3:])


def test_map_tree_needs_point_to_plane():
    with pytest.raises(ConfigError, match='map_tree'):
        RegistrationConfig(solver='map_tree', estimation='gicp').validate()
    RegistrationConfig(solver='map_tree').validate()
