"""Solver 'map_tree': open3d's point-to-plane ICP, reproduced over a kept KD-tree."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from helpers import box_scene, target_of
from scipy.spatial.transform import Rotation

from gft_odom.core.gauss_newton import kernel_loss, kernel_weights
from gft_odom.core.geometry import invert_transform, make_transform
from gft_odom.core.icp_backend import IcpBackend
from gft_odom.core.map_tree_icp import AndersonPose, ExactNearest, MapTreeICP, euler_update
from gft_odom.core.registration import RegistrationConfig, ScanRegistration
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


def crowns(rng: np.random.Generator, n: int) -> np.ndarray:
    """Two rows of porous crowns over flat ground: a scan samples other returns of the same
    foliage than the map, and nearest-neighbour ICP slides slowly towards its optimum."""
    centres = np.c_[np.repeat([-3.0, 3.0], 8), np.tile(np.arange(-14.0, 14.0, 3.5), 2),
                    np.full(16, 2.0)]
    foliage = centres[rng.integers(0, 16, n)] + rng.normal(0.0, 0.6, (n, 3))
    ground = np.c_[rng.uniform(-15, 15, (n // 3, 2)), rng.normal(0.0, 0.01, n // 3)]
    return np.concatenate([foliage, ground])


@pytest.mark.parametrize('seed', [0, 1])
def test_anderson_acceleration_needs_fewer_iterations_at_no_higher_energy(seed):
    rng = np.random.default_rng(seed)
    target = target_of(crowns(rng, 12000))
    T_true = make_transform(Rotation.from_euler('z', 1.0, degrees=True).as_matrix(),
                            [0.15, 0.05, 0.0])
    source = crowns(rng, 4000) @ invert_transform(T_true)[:3, :3].T + invert_transform(
        T_true)[:3, 3]
    plain_icp = MapTreeICP('tukey', 0.3, 1e-4, 1e-4, 100)
    accelerated_icp = MapTreeICP('tukey', 0.3, 1e-4, 1e-4, 100, anderson_memory=3)
    plain = plain_icp.register(source, target, np.eye(4), 1.0)
    accelerated = accelerated_icp.register(source, target, np.eye(4), 1.0)
    assert accelerated_icp.n_accelerated > 0
    assert accelerated.n_iterations < plain.n_iterations

    def energy(result):
        world = source @ result.transformation[:3, :3].T + result.transformation[:3, 3]
        return plain_icp._energy(world, target, result.correspondence_set, 1.0)
    assert energy(accelerated) <= energy(plain)


def test_anderson_chart_round_trip_and_extrapolation():
    reference = make_transform(Rotation.from_euler('xyz', [0.1, -0.2, 1.0]).as_matrix(),
                               [100.0, -50.0, 2.0])
    anderson = AndersonPose(reference, 3)
    T = make_transform(Rotation.from_euler('z', 0.01).as_matrix(), [0.05, 0.0, 0.0]) @ reference
    np.testing.assert_allclose(anderson.pose(anderson.chart(T)), T, atol=1e-12)
    # A linear contraction x -> x* + 0.8 (x - x*): two steps tell Anderson where x* is.
    fixed = np.array([0.01, 0.0, -0.02, 0.3, -0.1, 0.05])
    x = np.zeros(6)
    assert anderson.propose(anderson.pose(x), anderson.pose(fixed + 0.8 * (x - fixed))) is None
    x = fixed + 0.8 * (x - fixed)
    proposal = anderson.propose(anderson.pose(x), anderson.pose(fixed + 0.8 * (x - fixed)))
    np.testing.assert_allclose(anderson.chart(proposal), fixed, atol=1e-9)


@pytest.mark.parametrize('kind', ['tukey', 'huber', 'cauchy', 'none'])
def test_kernel_loss_is_what_the_weights_integrate(kind):
    e = np.linspace(0.01, 0.6, 50)
    h = 1e-6
    slope = (kernel_loss(kind, e + h, 0.3) - kernel_loss(kind, e - h, 0.3)) / (2 * h)
    np.testing.assert_allclose(slope / e, kernel_weights(kind, e, 0.3), atol=1e-5)
    assert kernel_loss(kind, np.zeros(1), 0.3)[0] == 0.0


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


def test_map_tree_is_the_point_to_plane_solver():
    local_map = ScanRegistration.from_config(RegistrationConfig()).local_map
    assert IcpBackend(RegistrationConfig(solver='map_tree'), local_map).map_tree is not None
    for estimation in ('gicp', 'point_to_point'):  # open3d's own ICP runs them
        config = RegistrationConfig(solver='map_tree', estimation=estimation)
        config.validate()
        assert IcpBackend(config, local_map).map_tree is None
    assert IcpBackend(RegistrationConfig(solver='open3d'), local_map).map_tree is None
    with pytest.raises(ConfigError, match='anderson_memory'):
        RegistrationConfig(solver='open3d', anderson_memory=3).validate()
    with pytest.raises(ConfigError, match='anderson_memory'):
        RegistrationConfig(solver='map_tree', anderson_memory=-1).validate()
    RegistrationConfig(solver='map_tree', anderson_memory=3).validate()
