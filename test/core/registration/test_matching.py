"""The map's match: open3d's point-to-plane ICP reproduced over a kept search index, and
the paper's point-to-point ICP."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from helpers import box_scene, target_of
from scipy.spatial.transform import Rotation

from gft_odom.core.geometry import invert_transform, make_transform
from gft_odom.core.registration.matching import (
    CONVERGENCE_RELATIVE,
    ExactNearest,
    euler_update,
    point_to_plane_icp,
    point_to_point_icp,
    to_cloud,
    tukey_weights,
)

reg = o3d.pipelines.registration
T_TRUE = make_transform(Rotation.from_euler('z', 4.0, degrees=True).as_matrix(),
                        [0.3, -0.15, 0.02])


@pytest.fixture(scope='module')
def scene():
    points = box_scene(seed=4)
    source = (invert_transform(T_TRUE)[:3, :3] @ points.T).T + invert_transform(T_TRUE)[:3, 3]
    source = source[::3] + np.random.default_rng(5).normal(0.0, 0.02, source[::3].shape)
    return target_of(points), source


@pytest.mark.parametrize('iterations', [1, 3, 30])
def test_reproduces_open3d_step_for_step(scene, iterations):
    target, source = scene
    cloud = to_cloud(target.points)
    cloud.normals = o3d.utility.Vector3dVector(target.normals)
    init = make_transform(Rotation.from_euler('z', 1.0, degrees=True).as_matrix(),
                          [0.05, 0.02, 0.0])
    theirs = reg.registration_icp(
        to_cloud(source), cloud, 1.0, init, reg.TransformationEstimationPointToPlane(
            reg.TukeyLoss(0.3)),
        reg.ICPConvergenceCriteria(CONVERGENCE_RELATIVE, CONVERGENCE_RELATIVE, iterations))
    ours = point_to_plane_icp(source, target, init, 1.0, iterations, 0.3)
    np.testing.assert_allclose(ours.transformation, np.asarray(theirs.transformation),
                               atol=1e-9)
    assert ours.fitness == pytest.approx(theirs.fitness, abs=1e-12)
    assert ours.inlier_rmse == pytest.approx(theirs.inlier_rmse, rel=1e-9)
    np.testing.assert_array_equal(ours.correspondence_set,
                                  np.asarray(theirs.correspondence_set))


def test_recovers_a_known_transform(scene):
    target, source = scene
    result = point_to_plane_icp(source, target, np.eye(4), 1.0, 50, 0.3)
    error = invert_transform(T_TRUE) @ result.transformation
    assert np.linalg.norm(error[:3, 3]) < 0.01
    assert Rotation.from_matrix(error[:3, :3]).magnitude() < np.deg2rad(0.05)
    assert 1 <= result.n_iterations <= 50


def test_the_papers_point_to_point_icp_recovers_a_known_transform(scene):
    target, source = scene
    result = point_to_point_icp(source, to_cloud(target.points), np.eye(4), 1.0, 60)
    error = invert_transform(T_TRUE) @ np.asarray(result.transformation)
    assert np.linalg.norm(error[:3, 3]) < 0.03


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
    result = point_to_plane_icp(far, target, np.eye(4), 1.0, 30, 0.3)
    np.testing.assert_array_equal(result.transformation, np.eye(4))
    assert result.fitness == 0.0 and result.correspondence_set.shape == (0, 2)


def test_euler_update_is_open3d_order():
    x = np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0])
    expected = Rotation.from_euler('ZYX', x[2::-1]).as_matrix()  # Rz @ Ry @ Rx
    np.testing.assert_allclose(euler_update(x)[:3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(euler_update(x)[:3, 3], x[3:])


def test_tukey_weighs_a_residual_down_to_zero_at_its_scale():
    e = np.array([0.0, 0.15, 0.3, 0.6])
    np.testing.assert_allclose(tukey_weights(e, 0.3), [1.0, 0.5625, 0.0, 0.0])
