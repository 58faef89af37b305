"""Solver 'map_tree': open3d's point-to-plane ICP, reproduced over a kept KD-tree."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from helpers import box_scene, target_of
from scipy.spatial.transform import Rotation

from gft_odom.core.gauss_newton import MapTarget, kernel_loss, kernel_weights
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


def test_normals_on_demand_are_open3ds_and_estimated_once(scene):
    eager, source = scene
    lazy = MapTarget(eager.points, None)
    index = np.array([5, 17, 5, 900, 17, 3000])
    dot = np.einsum('ij,ij->i', lazy.normals_at(index), eager.normals[index])
    np.testing.assert_allclose(np.abs(dot), 1.0, atol=1e-6)  # the sign is arbitrary in both
    assert lazy.n_normals_estimated == 4  # each point once, repeats not again
    lazy.normals_at(index[:3])
    assert lazy.n_normals_estimated == 4


def test_icp_on_demand_normals_matches_precomputed(scene):
    eager, source = scene
    lazy = MapTarget(eager.points, None)
    icp = MapTreeICP('tukey', 0.3, 1e-6, 1e-6, 30)
    ours, theirs = icp.register(source, lazy, np.eye(4), 1.0), icp.register(source, eager,
                                                                            np.eye(4), 1.0)
    np.testing.assert_allclose(ours.transformation, theirs.transformation, atol=1e-9)
    # Only the map points some pair used have a normal.
    assert 0 < lazy.n_normals_estimated < eager.points.shape[0]
    assert lazy.n_normals_estimated == np.count_nonzero(lazy._known)


def test_registration_leaves_map_normals_to_the_solver():
    points = box_scene(seed=6)
    registration = ScanRegistration(RegistrationConfig(solver='map_tree',
                                                       map_normals='on_demand'))
    registration.register(points, 0)
    registration.register(points, 100_000_000)
    assert not registration.local_map.cloud.has_normals()  # the rebuild skipped them
    result = registration.register(points, 200_000_000)
    assert result.status == 'ok'
    target = registration.local_map.target()
    assert 0 < target.n_normals_estimated <= len(registration.local_map)
    # The information comes from the pairs' point-to-plane rows [n, a x n] (without the
    # normals it would fall back to point-to-point rows, whose translation block is m I).
    translation = result.information[:3, :3]
    assert np.all(np.isfinite(result.information))
    assert not np.allclose(translation, np.eye(3) * translation[0, 0], rtol=0.05)


def test_a_rebuilt_map_inherits_the_normals_it_would_estimate():
    from gft_odom.core.local_map import LocalMap
    rng = np.random.default_rng(8)
    scene = box_scene(seed=8)
    local_map = LocalMap(0.1, 100.0, 100_000, 2, 1.0, 0.2, 15, with_normals=False)
    local_map.add_keyframe(scene[:4000], np.eye(4))
    before = local_map.target()
    before.normals_at(np.arange(len(local_map)))
    # A second keyframe: some voxels gain a point nearer than a normal's neighbours were.
    T = np.eye(4)
    T[0, 3] = 1.5
    local_map.add_keyframe(scene[4000:] + rng.normal(0.0, 0.01, scene[4000:].shape), T)
    after = local_map.target()
    inherited = after._known.copy()
    assert 0 < after.n_normals_inherited == np.count_nonzero(inherited) < len(local_map)
    # Some points stayed but lost their normal: a new neighbour came within its reach.
    survivors = np.count_nonzero(local_map._index_of(before.points) >= 0)
    assert after.n_normals_inherited < survivors
    fresh = MapTarget(after.points, None)
    every = np.arange(len(local_map))
    dot = np.einsum('ij,ij->i', after.normals_at(every), fresh.normals_at(every))
    np.testing.assert_allclose(np.abs(dot), 1.0, atol=1e-9)
    np.testing.assert_array_equal(np.sort(after._neighbours[inherited], axis=1),
                                  np.sort(fresh._neighbours[inherited], axis=1))


def test_kept_normals_are_estimated_once_when_a_point_enters_the_map():
    from gft_odom.core.local_map import LocalMap
    rng = np.random.default_rng(8)
    scene = box_scene(seed=8)
    local_map = LocalMap(0.1, 100.0, 100_000, 2, 1.0, 0.2, 15, with_normals=False)
    local_map.keep_normals = True
    local_map.add_keyframe(scene[:4000], np.eye(4))
    before = local_map.target()
    every = np.arange(len(local_map))
    assert before._known.all() and before.n_normals_estimated == len(local_map)
    first = before.normals_at(every).copy()
    T = np.eye(4)
    T[0, 3] = 1.5
    local_map.add_keyframe(scene[4000:] + rng.normal(0.0, 0.01, scene[4000:].shape), T)
    after = local_map.target()
    every = np.arange(len(local_map))
    of_old = local_map._index_of(before.points)
    stayed = of_old >= 0
    # Every point that stayed keeps its first normal, even where new neighbours came near;
    # only the points new to the map were estimated, all at the update.
    assert after._known.all()
    assert after.n_normals_inherited == np.count_nonzero(stayed)
    assert after.n_normals_estimated == len(local_map) - np.count_nonzero(stayed) > 0
    np.testing.assert_array_equal(after.normals_at(of_old[stayed]), first[stayed])
    fresh = MapTarget(after.points, None)
    new = np.setdiff1d(every, of_old[stayed])
    dot = np.einsum('ij,ij->i', after.normals_at(new), fresh.normals_at(new))
    np.testing.assert_allclose(np.abs(dot), 1.0, atol=1e-9)
    # Not what a fresh estimate gives everywhere: some stayed points' neighbourhoods changed.
    dot = np.einsum('ij,ij->i', after.normals_at(every), fresh.normals_at(every))
    assert np.min(np.abs(dot)) < 1.0 - 1e-6


@pytest.mark.parametrize('solver', ['map_tree', 'gauss_newton'])
def test_on_demand_normals_give_the_rebuilds_trajectory(solver):
    points = box_scene(seed=9)
    poses = {}
    for normals in ('rebuild', 'on_demand'):
        registration = ScanRegistration(RegistrationConfig(
            solver=solver, map_normals=normals, keyframe_distance_m=0.1))
        poses[normals] = _turn_and_drive(registration, points, 6)
    np.testing.assert_allclose(poses['on_demand'], poses['rebuild'], atol=1e-9)


def _turn_and_drive(registration, points, n_scans, after_each=None):
    """The poses of `points` seen along a short turn-and-drive; `after_each(i)`: after
    scan i's pose (its map update deferred to then)."""
    moved = []
    for i in range(n_scans):
        T = make_transform(Rotation.from_euler('z', 1.5 * i, degrees=True).as_matrix(),
                           [0.12 * i, 0.02 * i, 0.0])
        moved.append(registration.register(
            (invert_transform(T)[:3, :3] @ points.T).T + invert_transform(T)[:3, 3],
            i * 100_000_000, defer_map_update=after_each is not None).T_world_sensor)
        if after_each is not None:
            after_each(i)
    return np.array(moved)


def test_in_time_normals_are_estimated_at_a_rebuild_only_when_they_fit():
    import time

    from gft_odom.core.local_map import LocalMap
    scene = box_scene(seed=8)
    local_map = LocalMap(0.1, 100.0, 100_000, 3, 1.0, 0.2, 15)
    local_map.normals_in_time = True
    past = time.perf_counter() - 1.0
    # The first rebuild has no cost measured yet: it estimates them, however late.
    local_map.add_keyframe(scene[:3000], np.eye(4), normals_due_s=past)
    assert local_map.cloud.has_normals() and local_map.target().normals is not None
    T = np.eye(4)
    T[0, 3] = 1.5
    local_map.add_keyframe(scene[3000:6000], T, normals_due_s=time.perf_counter() - 1.0)
    late = local_map.target()
    assert not local_map.cloud.has_normals() and late.normals is None
    assert local_map.n_rebuilds_left_to_pairs == 1
    assert late.n_normals_estimated == 0  # no time was left to estimate any ahead
    every = np.arange(len(local_map))
    fresh = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(late.points))
    fresh.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(15))
    dot = np.einsum('ij,ij->i', late.normals_at(every), np.asarray(fresh.normals))
    np.testing.assert_allclose(np.abs(dot), 1.0, atol=1e-9)  # what a rebuild would give
    T[0, 3] = 3.0
    local_map.add_keyframe(scene[6000:], T, normals_due_s=time.perf_counter() + 60.0)
    assert local_map.cloud.has_normals() and local_map.n_rebuilds_left_to_pairs == 1
    # Late, but within the slack: still every normal at the rebuild.
    local_map.normals_slack_s = 120.0
    local_map.add_keyframe(scene[:3000], T, normals_due_s=time.perf_counter() - 1.0)
    assert local_map.cloud.has_normals() and local_map.n_rebuilds_left_to_pairs == 1
    local_map.normals_slack_s = 0.0
    # Without a deadline, or without 'in_time', a rebuild always estimates them.
    local_map.add_keyframe(scene[:3000], np.eye(4), normals_due_s=None)
    local_map.normals_in_time = False
    local_map.add_keyframe(scene[3000:6000], T, normals_due_s=time.perf_counter() - 1.0)
    assert local_map.cloud.has_normals() and local_map.n_rebuilds_left_to_pairs == 1


@pytest.mark.parametrize('solver', ['map_tree', 'gauss_newton'])
def test_in_time_normals_give_the_rebuilds_trajectory(solver):
    import time
    points = box_scene(seed=9)
    poses = {}
    for normals in ('rebuild', 'in_time'):
        registration = ScanRegistration(RegistrationConfig(
            solver=solver, map_normals=normals, keyframe_distance_m=0.1))
        # Every other keyframe late: its map leaves the normals to the pairs.
        poses[normals] = _turn_and_drive(registration, points, 8, lambda i: (
            registration.update_map(time.perf_counter() + (-1.0 if i % 2 else 60.0))))
        left = registration.local_map.n_rebuilds_left_to_pairs
        assert left == (0 if normals == 'rebuild' else 4)  # scans 1, 3, 5 and 7
    np.testing.assert_allclose(poses['in_time'], poses['rebuild'], atol=1e-9)


def test_spare_time_estimates_the_nearest_normals_first(monkeypatch):
    from types import SimpleNamespace

    from gft_odom.core import gauss_newton
    points = box_scene(seed=8)
    clock = iter(np.arange(0.0, 1000.0))  # each reading a second later: a chunk takes 1 s
    monkeypatch.setattr(gauss_newton, 'time', SimpleNamespace(perf_counter=lambda: next(clock)))
    near = points[0]
    target = MapTarget(points, None)
    # Readings: 0 (start), then 1 and 2 around the first chunk (1 s), then 3 and 4 around
    # the second: the third would end after 5.5 s, so two chunks are estimated.
    target.estimate_normals_until(5.5, near, chunk=100)
    assert target.n_normals_estimated == 200
    distance = np.linalg.norm(points - near, axis=1)
    assert distance[target._known].max() <= distance[~target._known].min()
    every = np.arange(points.shape[0])
    fresh = MapTarget(points, None)
    known = target._known.copy()
    dot = np.einsum('ij,ij->i', target.normals_at(every)[known], fresh.normals_at(every)[known])
    np.testing.assert_allclose(np.abs(dot), 1.0, atol=1e-12)
    past = MapTarget(points, None)
    past.estimate_normals_until(-1.0, near)
    assert past.n_normals_estimated == 0


def test_in_time_normals_need_a_numpy_solver_and_an_inline_map_update():
    with pytest.raises(ConfigError, match='in_time'):
        RegistrationConfig(solver='open3d', map_normals='in_time').validate()
    with pytest.raises(ConfigError, match='background'):
        RegistrationConfig(map_normals='in_time', map_update='background').validate()
    RegistrationConfig(map_normals='in_time', map_update='auto').validate()
    with pytest.raises(ConfigError, match='map_normals_slack_s'):
        RegistrationConfig(map_normals='in_time', map_normals_slack_s=-0.01).validate()


def test_on_demand_normals_need_a_numpy_solver():
    with pytest.raises(ConfigError, match='on_demand'):
        RegistrationConfig(solver='open3d', map_normals='on_demand').validate()
    with pytest.raises(ConfigError, match='map_normals'):
        RegistrationConfig(map_normals='sometimes').validate()


def _drive_box(config: RegistrationConfig, n_scans: int = 8) -> np.ndarray:
    """The poses of a short turn-and-drive through the box scene, each scan's map update
    after its pose."""
    registration = ScanRegistration(config)
    return _turn_and_drive(registration, box_scene(seed=9), n_scans,
                           lambda i: registration.update_map())


def test_background_rebuild_normals_are_the_inline_ones():
    from gft_odom.core.local_map import LocalMap
    scene = box_scene(seed=8)
    local_map = LocalMap(0.1, 100.0, 100_000, 2, 1.0, 0.2, 15)
    local_map.add_keyframe(scene[:4000], np.eye(4))
    inline = local_map.cloud
    served = local_map.target()
    T = np.eye(4)
    T[0, 3] = 1.5
    local_map.add_keyframe(scene[4000:], T, background=True)
    # Until adopted, the map before the keyframe is what is served.
    assert local_map.rebuild_in_flight and local_map.cloud is inline
    assert local_map.target() is served
    assert local_map.adopt() >= 0.0 and not local_map.rebuild_in_flight
    background = local_map.target()
    assert background.normals is not None and local_map.cloud is not inline
    reference = LocalMap(0.1, 100.0, 100_000, 2, 1.0, 0.2, 15)
    reference.add_keyframe(scene[:4000], np.eye(4))
    reference.add_keyframe(scene[4000:], T)
    np.testing.assert_array_equal(background.points, reference.points_xyz)
    dot = np.einsum('ij,ij->i', background.normals, np.asarray(reference.cloud.normals))
    np.testing.assert_allclose(np.abs(dot), 1.0, atol=1e-6)


def test_background_map_update_serves_each_rebuild_from_the_second_scan_after():
    # Without deskew: a deskewed first scan's keyframe is provisional (its motion is unknown)
    # and the first match replaces it, which shifts this schedule by a scan.
    config = RegistrationConfig(map_update='background', keyframe_distance_m=0.1, deskew=False)
    points = box_scene(seed=9)
    registration = ScanRegistration(config)
    served = []
    for i in range(4):
        T = make_transform(np.eye(3), [0.15 * i, 0.0, 0.0])
        registration.register((points - T[:3, 3]), i * 100_000_000, defer_map_update=True)
        served.append(registration.local_map.cloud)
        registration.update_map()
    # Scan 0's keyframe is built at once; scan 1's rebuild is served from scan 3 on (scan
    # 2's keyframe waits for it first), so scan 2 is matched against scan 0's map.
    assert len(served[0].points) == 0 and len(served[1].points) > 0
    assert served[2] is served[1] and served[3] is not served[2]


def test_background_map_update_does_not_depend_on_the_threads_speed(monkeypatch):
    from gft_odom.core import local_map as local_map_module
    config = RegistrationConfig(map_update='background', keyframe_distance_m=0.1)
    threaded = _drive_box(config)
    slow_submit = local_map_module._Worker.submit

    def late(self, work):  # the rebuild finishes only when waited for, much later
        import time

        def slow():
            time.sleep(0.05)
            return work()
        slow_submit(self, slow)
    monkeypatch.setattr(local_map_module._Worker, 'submit', late)
    np.testing.assert_array_equal(_drive_box(config), threaded)
    # And it tracks the drive as the inline update does.
    inline = _drive_box(RegistrationConfig(keyframe_distance_m=0.1))
    np.testing.assert_allclose(threaded[:, :3, 3], inline[:, :3, 3], atol=0.01)


def test_a_failed_background_rebuild_raises_when_adopted_and_the_old_map_stays():
    from gft_odom.core.local_map import LocalMap
    scene = box_scene(seed=8)
    local_map = LocalMap(0.1, 100.0, 100_000, 2, 1.0, 0.2, 15)
    local_map.add_keyframe(scene[:4000], np.eye(4))
    before = local_map.cloud

    def broken(*args, **kwargs):
        raise MemoryError('no room for the map')
    local_map._rebuilt = broken
    local_map.add_keyframe(scene[4000:], np.eye(4), background=True)
    with pytest.raises(MemoryError):
        local_map.adopt()
    assert local_map.cloud is before and not local_map.rebuild_in_flight


@pytest.mark.parametrize('change', [{'map_normals': 'on_demand'}, {'solver': 'open3d'},
                                    {'solver': 'gauss_newton', 'residual_model': 'planarity'},
                                    {'mode': 'paper'}, {'map_update': 'sometimes'}])
def test_background_map_update_needs_what_its_thread_can_compute(change):
    with pytest.raises(ConfigError, match='map_update'):
        RegistrationConfig(**{'map_update': 'background', **change}).validate()
    # 'auto' (the default) is the inline update there, and background where it can be.
    auto = RegistrationConfig(**{**change, 'map_update': 'auto'})
    if change.get('map_update') is None:
        auto.validate()
        assert auto.resolved_map_update == 'inline'
    assert RegistrationConfig(map_update='auto').resolved_map_update == 'background'
    assert RegistrationConfig().resolved_map_update == 'inline'


def test_a_point_kernel_scale_per_scan_point(scene):
    """Each scan point's own Tukey scale: the same everywhere is the one scale; a tight scale
    on the points marked rough stops a displaced cluster of them from pulling the pose."""
    target, source = scene
    rng = np.random.default_rng(9)
    wall = source[(source[:, 2] > 0.3) & (source[:, 1] > 3.0)]  # the wall at y = 4
    cluster = wall[rng.choice(wall.shape[0], 300)] + [0.0, 0.2, 0.0]  # 0.2 m off it
    points = np.concatenate([source, cluster])
    solver = MapTreeICP('tukey', 0.3, 1e-6, 1e-6, 50)
    one = solver.register(points, target, np.eye(4), 1.0)
    same = solver.register(points, target, np.eye(4), 1.0, point_scale_m=np.full(len(points), 0.3))
    np.testing.assert_array_equal(one.transformation, same.transformation)
    scale = np.r_[np.full(len(source), 0.3), np.full(len(cluster), 0.05)]
    tight = solver.register(points, target, np.eye(4), 1.0, point_scale_m=scale)

    def error_m(result):
        return np.linalg.norm((invert_transform(T_TRUE) @ result.transformation)[:3, 3])

    assert error_m(tight) < 0.01 < error_m(one)


def test_a_graduated_kernel_pulls_in_a_guess_beyond_the_kernel_and_ends_as_without_it(scene):
    target, source = scene
    # The truth is 0.34 m and 4 deg from identity: a Tukey scale of 0.1 m gives most pairs
    # zero weight from there.
    tight = MapTreeICP('tukey', 0.1, 1e-6, 1e-6, 60)
    stuck = tight.register(source, target, np.eye(4), 1.0)
    graduated = MapTreeICP('tukey', 0.1, 1e-6, 1e-6, 60, anneal_from_m=1.0, anneal_factor=0.8)
    pulled = graduated.register(source, target, np.eye(4), 1.0)
    error_stuck = np.linalg.norm(stuck.transformation[:3, 3] - T_TRUE[:3, 3])
    error_pulled = np.linalg.norm(pulled.transformation[:3, 3] - T_TRUE[:3, 3])
    assert error_pulled < 0.02 < error_stuck, (error_pulled, error_stuck)
    # Its last iterations weigh as the plain kernel: from the truth both end at one pose.
    near = make_transform(translation=[0.01, 0.0, 0.0]) @ T_TRUE
    plain_end = MapTreeICP('tukey', 0.1, 1e-9, 1e-9, 60).register(source, target, near, 1.0)
    graduated_end = graduated.register(source, target, near, 1.0)
    np.testing.assert_allclose(graduated_end.transformation, plain_end.transformation,
                               atol=2e-3)


def test_a_graduated_match_does_not_stop_before_its_kernel_is_the_plain_one(scene):
    target, source = scene
    # From the truth a plain match stops at once; the graduated one (1.0 -> 0.1 m by halves:
    # iterations 0-3 wider, the plain scale from iteration 4) goes on to weigh as the plain.
    plain = MapTreeICP('tukey', 0.1, 1e-4, 1e-4, 30).register(source, target, T_TRUE, 1.0)
    graduated = MapTreeICP('tukey', 0.1, 1e-4, 1e-4, 30, anneal_from_m=1.0,
                           anneal_factor=0.5).register(source, target, T_TRUE, 1.0)
    assert plain.n_iterations < 5 <= graduated.n_iterations, (plain.n_iterations,
                                                               graduated.n_iterations)


def test_the_graduated_kernels_schedule():
    icp = MapTreeICP('tukey', 0.3, anneal_from_m=1.2, anneal_factor=0.5)
    assert [icp._anneal_at(i) for i in range(4)] == pytest.approx([4.0, 2.0, 1.0, 1.0])
    assert MapTreeICP('tukey', 0.3)._anneal_at(0) == 1.0
    RegistrationConfig(kernel_anneal_from_m=1.0).validate()
    for bad in ({'kernel_anneal_from_m': 1.0, 'solver': 'open3d'},
                {'kernel_anneal_from_m': 1.0, 'estimation': 'gicp'},
                {'kernel_anneal_from_m': 1.0, 'anderson_memory': 3},
                {'kernel_anneal_from_m': 1.0, 'rough_kernel_scale_m': 0.1},
                {'kernel_anneal_from_m': 1.0, 'turn_continue_min_rad': 0.02},
                {'kernel_anneal_from_m': 1.0, 'turn_check_screen_iterations': 10},
                {'kernel_anneal_from_m': 0.2},  # not above the kernel's 0.3 m
                {'kernel_anneal_from_m': 1.0, 'kernel_anneal_factor': 0.97},  # 40 iterations
                {'kernel_anneal_factor': 1.0}, {'kernel_anneal_from_m': -1.0}):
        with pytest.raises(ConfigError, match='kernel_anneal|graduated'):
            RegistrationConfig(**bad).validate()


def test_a_failed_graduated_match_leaves_no_wide_kernel_behind(scene, monkeypatch):
    target, source = scene
    icp = MapTreeICP('tukey', 0.1, anneal_from_m=1.0, anneal_factor=0.5)
    monkeypatch.setattr(icp, '_update', lambda *args: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        icp.register(source, target, np.eye(4), 1.0)
    assert icp._anneal == 1.0


def test_a_gate_per_scan_point_pairs_each_point_within_its_own(scene):
    """`max_distance_m` (n,): each point is paired only within its own gate, as a full search
    bounded by that gate finds; one value for all is the one gate."""
    target, source = scene
    rng = np.random.default_rng(10)
    gate_m = rng.choice([0.05, 0.2, 1.0], source.shape[0])
    nearest = ExactNearest(target, gate_m)
    world = source + rng.normal(0.0, 0.1, 3)
    for _ in range(3):
        valid, index, distance = nearest.query(world)
        d, full = target.tree.query(world, k=1, distance_upper_bound=1.0)
        within = np.flatnonzero(d <= gate_m)
        np.testing.assert_array_equal(valid, within)
        np.testing.assert_array_equal(index, full[within])
        world = world + rng.normal(0.0, 0.05, 3)
    solver = MapTreeICP('tukey', 0.3, 1e-6, 1e-6, 50)
    one = solver.register(source, target, np.eye(4), 1.0)
    same = solver.register(source, target, np.eye(4), np.full(source.shape[0], 1.0))
    np.testing.assert_array_equal(one.transformation, same.transformation)
    # From a guess 0.2 m off, the pairs of the narrow-gated points are all within 0.1 m.
    start = make_transform(translation=[0.2, 0.0, 0.0]) @ T_TRUE
    own_m = np.where(gate_m < 1.0, 0.1, 1.0)
    narrow = solver.register(source, target, start, own_m)
    world = source @ narrow.transformation[:3, :3].T + narrow.transformation[:3, 3]
    scan_index, map_index = narrow.correspondence_set.T
    pair_m = np.linalg.norm(world[scan_index] - target.points[map_index], axis=1)
    assert np.all(pair_m <= own_m[scan_index])
    # ... and the wide-gated third pulls the guess in.
    assert np.linalg.norm(narrow.transformation[:3, 3] - T_TRUE[:3, 3]) < 0.02


# Each per-point setting: its value, how a backend reads it, what it gives the scan points of
# smoothness 1, 0, 0.5 and unknown (NaN, counted rough), and what without frequencies.
PER_POINT_SETTINGS = {
    'rough_kernel_scale_m': (0.1, lambda backend: backend._point_kernel_scale_m(),
                             [0.3, 0.1, 0.2, 0.1], None),
    'rough_gate_ratio': (0.4, lambda backend: backend._point_gate_m(2.0), [2.0, 0.8, 1.4, 0.8],
                         2.0),
}


@pytest.mark.parametrize('name', sorted(PER_POINT_SETTINGS))
def test_a_per_point_setting_follows_the_frequency_and_needs_map_tree(name):
    value, read, expected, without = PER_POINT_SETTINGS[name]
    with pytest.raises(ConfigError, match=name):
        RegistrationConfig(**{name: value, 'solver': 'open3d'}).validate()
    with pytest.raises(ConfigError, match=name):
        RegistrationConfig(**{name: -value}).validate()
    from gft_odom.core.local_map import LocalMap
    config = RegistrationConfig(**{name: value})
    assert config.reads_scan_frequencies_before_pose
    backend = IcpBackend(config, LocalMap(0.3, 40.0, 80000, 60, 1.0, 0.2, 15))
    backend.use_smoothness(None, np.array([1.0, 0.0, 0.5, np.nan]))
    np.testing.assert_allclose(read(backend), expected)
    backend.use_smoothness(None, None)  # no frequencies: one value for all
    assert read(backend) == without
