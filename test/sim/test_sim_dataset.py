"""The written dataset: bags readable by the project's reader in both formats, ground truth
consistent with the scans, determinism by seed, the CLI."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from gft_odom.core.geometry import transform_points
from gft_odom.errors import SimulationError
from gft_odom.io.bags import ScanBagReader, read_odometry
from gft_odom.io.ground_truth import read_ground_truth
from gft_odom.io.tum import read_tum
from gft_odom.sim.orchard import TRUNK
from gft_odom.sim.simulator import ScanSimulator, SimConfig
from gft_odom.sim.writer import GPS_TOPIC, LIDAR_TOPIC, simulate_to_bag
from gft_odom.tools.cli import main

N_SCANS = 6
SEED = 21
# Coarse columns keep the tests fast; the real 0.2 deg geometry is tested in test_vlp16_raycast.
FAST = dataclasses.replace(SimConfig(), azimuth_step_deg=1.0)
QUIET = FAST.quiet()


def _simulator(config, scenario='uturn', n_scans=N_SCANS, seed=SEED):
    """The same orchard, motion and simulator that simulate_to_bag builds."""
    return ScanSimulator.from_config(config, scenario, n_scans, seed)


@pytest.fixture(scope='module')
def quiet_ros2(tmp_path_factory):
    out = tmp_path_factory.mktemp('quiet_ros2')
    result = simulate_to_bag(out, 'uturn', N_SCANS, SEED, QUIET, fmt='ros2', topdown_png=False)
    with ScanBagReader(result.bag_path, LIDAR_TOPIC) as reader:
        scans = list(reader)
    return result, scans


@pytest.fixture(scope='module')
def legacy_ros1(tmp_path_factory):
    out = tmp_path_factory.mktemp('legacy_ros1')
    config = dataclasses.replace(FAST, legacy_fields=True)
    result = simulate_to_bag(out, 'row', 3, SEED, config, fmt='ros1', topdown_png=False)
    return result


def _interpolate(traj, stamps_ns):
    """Poses at arbitrary stamps between the trajectory's (slerp + linear)."""
    t = (traj.stamps_ns - traj.stamps_ns[0]).astype(float)
    slerp = Slerp(t, Rotation.from_matrix(traj.poses[:, :3, :3]))
    q = (np.asarray(stamps_ns) - traj.stamps_ns[0]).astype(float)
    out = np.tile(np.eye(4), (q.size, 1, 1))
    out[:, :3, :3] = slerp(q).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(q, t, traj.poses[:, k, 3])
    return out


def _axis_distance(points, base, axis):
    rel = points - base
    return np.linalg.norm(rel - (rel @ axis)[:, None] * axis, axis=1)


def test_layout_and_counts(quiet_ros2):
    result, scans = quiet_ros2
    assert result.bag_path == result.out_dir / f'base_uturn_{SEED}'
    assert result.bag_path.is_dir()
    assert result.gt_csv_path == result.out_dir / 'ground_truth' / 'gt.csv'
    assert result.gt_tum_path == result.out_dir / 'ground_truth' / 'gt_sensor_tum.txt'
    assert result.topdown_png_path is None
    assert len(scans) == N_SCANS
    assert all(s.frame_id == 'velodyne' for s in scans)
    stamps = np.array([s.stamp_ns for s in scans])
    np.testing.assert_array_equal(np.diff(stamps), 100_000_000)
    for scan in scans:
        assert scan.time_offset_s is not None and scan.ring is not None
        assert 0.0 <= scan.time_offset_s.min() and scan.time_offset_s.max() < 0.1
    assert result.points_per_scan == [len(s) for s in scans]


def test_trunk_points_agree_in_the_world_across_scans(quiet_ros2):
    """Noise and wind off: trunk points mapped with the ground-truth poses at their own time
    lie on their trunk's surface in every scan, and pooled over scans fit one circle."""
    result, scans = quiet_ros2
    sim = _simulator(QUIET)
    traj = read_tum(result.gt_tum_path)
    cyl = sim.orchard.cylinders
    centres: dict[int, list[np.ndarray]] = {}  # trunk -> world points per scan
    seen_far_error = 0.0
    for k, scan in enumerate(scans[:-1]):  # the last sweep ends after the last TUM pose
        truth = sim.scan(k)
        np.testing.assert_allclose(scan.points_xyz, truth.scan.points_xyz, atol=1e-5)
        on_trunk = (truth.surface == TRUNK) & (np.linalg.norm(scan.points_xyz, axis=1) < 8.0)
        pts = scan.points_xyz[on_trunk]
        stamps = scan.stamp_ns + np.round(scan.time_offset_s[on_trunk] * 1e9).astype(np.int64)
        T = _interpolate(traj, stamps)
        world = np.einsum('nij,nj->ni', T[:, :3, :3], pts) + T[:, :3, 3]
        stamp_only = transform_points(traj.poses[k], pts)
        for prim in np.unique(truth.primitive[on_trunk]):
            mine = truth.primitive[on_trunk] == prim
            if mine.sum() < 5:
                continue
            dist = _axis_distance(world[mine], cyl.base_m[prim], cyl.axis[prim])
            np.testing.assert_allclose(dist, cyl.radius_m[prim], atol=0.015)
            seen_far_error = max(seen_far_error, float(np.abs(
                _axis_distance(stamp_only[mine], cyl.base_m[prim], cyl.axis[prim])
                - cyl.radius_m[prim]).max()))
            centres.setdefault(int(prim), []).append(world[mine])
    # Pooled over all scans, each trunk's points fit one circle (no scan disagrees).
    assert len(centres) >= 2
    for prim, per_scan in centres.items():
        if len(per_scan) < 2:
            continue
        pts = np.concatenate(per_scan)
        axis = cyl.axis[prim]
        u = np.cross(axis, [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        x, y = (pts - cyl.base_m[prim]) @ u, (pts - cyl.base_m[prim]) @ v
        A = np.column_stack([2.0 * x, 2.0 * y, np.ones_like(x)])
        a, b, c = np.linalg.lstsq(A, x * x + y * y, rcond=None)[0]
        radius = np.sqrt(c + a * a + b * b)
        residual = np.hypot(x - a, y - b) - radius
        assert np.sqrt(np.mean(residual ** 2)) < 0.01, prim
        assert np.hypot(a, b) < 0.03, prim  # the fitted axis is the trunk's
    # Without the per-point time the sweep is visibly distorted (1 m/s over 0.1 s).
    assert seen_far_error > 0.02


def test_per_point_time_gives_exact_world_points(quiet_ros2):
    """With the exact pose at each point's time every trunk point is on its cylinder (mm)."""
    _, scans = quiet_ros2
    sim = _simulator(QUIET)
    cyl = sim.orchard.cylinders
    scan = scans[2]
    truth = sim.scan(2)
    trunk = truth.surface == TRUNK
    t = (scan.stamp_ns - sim.start_ns) / 1e9 + scan.time_offset_s[trunk].astype(float)
    T = sim.sensor_poses(t)
    world = np.einsum('nij,nj->ni', T[:, :3, :3], scan.points_xyz[trunk]) + T[:, :3, 3]
    prim = truth.primitive[trunk]
    dist = np.linalg.norm((world - cyl.base_m[prim])
                          - np.einsum('ni,ni->n', world - cyl.base_m[prim],
                                      cyl.axis[prim])[:, None] * cyl.axis[prim], axis=1)
    np.testing.assert_allclose(dist, cyl.radius_m[prim], atol=2e-3)


def test_gps_ground_truth_is_the_antenna_track(quiet_ros2):
    result, _ = quiet_ros2
    gps_bag = read_odometry(result.bag_path, GPS_TOPIC)
    gps_csv = read_ground_truth(result.gt_csv_path)
    np.testing.assert_array_equal(gps_bag.stamps_ns, gps_csv.stamps_ns)
    np.testing.assert_allclose(gps_bag.positions_xyz, gps_csv.positions_xyz, atol=1e-5)
    # ~10 Hz, not on the scan stamps.
    assert np.allclose(np.diff(gps_bag.stamps_s), 0.1, atol=1e-6)
    sensor = read_tum(result.gt_tum_path)
    assert not np.isin(gps_bag.stamps_ns, sensor.stamps_ns).any()
    # Antenna = sensor pose (interpolated to the GPS stamp) with the CitrusFarm lever arm.
    inside = gps_bag.stamps_ns <= sensor.stamps_ns[-1]
    T = _interpolate(sensor, gps_bag.stamps_ns[inside])
    lever = np.array([-0.22, 0.0, 0.153])
    expected = np.einsum('nij,j->ni', T[:, :3, :3], lever) + T[:, :3, 3]
    np.testing.assert_allclose(gps_bag.positions_xyz[inside], expected, atol=0.005)
    # The world is the orchard frame: the first pose is not the identity.
    assert np.linalg.norm(sensor.poses[0, :3, 3]) > 1.0
    assert not np.allclose(sensor.poses[0, :3, :3], np.eye(3), atol=1e-3)


def test_legacy_ros1_bag_has_no_time_field(legacy_ros1):
    result = legacy_ros1
    assert result.bag_path.name == f'base_row_{SEED}.bag' and result.bag_path.is_file()
    assert result.topdown_png_path is None
    with ScanBagReader(result.bag_path, LIDAR_TOPIC) as reader:
        msgs = [msg for _, msg in reader.iter_messages()]
        scans = list(ScanBagReader(result.bag_path, LIDAR_TOPIC))
    assert len(msgs) == 3 and len(scans) == 3
    names = [f.name for f in msgs[0].fields]
    assert names == ['x', 'y', 'z', 'intensity', 'ring'] and msgs[0].point_step == 32
    assert all(s.time_offset_s is None for s in scans)
    assert all(len(s) > 1000 and s.ring is not None for s in scans)
    assert len(read_odometry(result.bag_path, GPS_TOPIC)) >= 3


def test_ros2_bag_has_the_velodyne_fields(quiet_ros2):
    result, _ = quiet_ros2
    with ScanBagReader(result.bag_path, LIDAR_TOPIC) as reader:
        _, msg = next(iter(reader.iter_messages()))
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'intensity', 'ring', 'time']
    assert msg.point_step == 22 and msg.header.frame_id == 'velodyne'


def test_same_seed_same_bytes_other_seed_other_scans(tmp_path):
    def points(out, seed):
        result = simulate_to_bag(out, 'row', 1, seed, FAST, topdown_png=False)
        with ScanBagReader(result.bag_path, LIDAR_TOPIC) as reader:
            return [s.points_xyz for s in reader]
    a = points(tmp_path / 'a', 5)
    b = points(tmp_path / 'b', 5)
    c = points(tmp_path / 'c', 6)
    for pa, pb in zip(a, b):
        np.testing.assert_array_equal(pa, pb)
    assert len(a[0]) != len(c[0]) or not np.allclose(a[0], c[0])


def test_noise_and_dropout_match_the_config():
    noisy_cfg = dataclasses.replace(QUIET, range_noise_std_m=0.025, dropout_probability=0.05)
    quiet = _simulator(QUIET, 'row', 2).scan(1)
    noisy = _simulator(noisy_cfg, 'row', 2).scan(1)
    # Same rays, same scene draws: the noisy scan is a subset with perturbed ranges.
    assert 0.03 < 1.0 - len(noisy.scan) / len(quiet.scan) < 0.07
    key = lambda s: np.round(np.arctan2(s.scan.points_xyz[:, 1], s.scan.points_xyz[:, 0]) * 1e4)\
        * 100 + s.scan.ring  # noqa: E731
    kq, kn = key(quiet), key(noisy)
    common, iq, i_n = np.intersect1d(kq, kn, return_indices=True)
    rq = np.linalg.norm(quiet.scan.points_xyz[iq], axis=1)
    rn = np.linalg.norm(noisy.scan.points_xyz[i_n], axis=1)
    assert 0.022 < np.std(rn - rq) < 0.028
    assert abs(np.mean(rn - rq)) < 0.002


def test_existing_bag_is_not_overwritten(tmp_path):
    simulate_to_bag(tmp_path, 'row', 1, 1, FAST, topdown_png=False)
    with pytest.raises(SimulationError, match='exists'):
        simulate_to_bag(tmp_path, 'row', 1, 1, FAST, topdown_png=False)


def test_invalid_config_is_refused(tmp_path):
    from gft_odom.errors import ConfigError
    with pytest.raises(ConfigError, match='azimuth_step_deg'):
        simulate_to_bag(tmp_path, 'row', 1, 1,
                        dataclasses.replace(FAST, azimuth_step_deg=0.7))
    with pytest.raises(ConfigError, match='dropout_probability'):
        dataclasses.replace(FAST, dropout_probability=1.5).validate()
    with pytest.raises(SimulationError, match='scenario'):
        simulate_to_bag(tmp_path, 'zigzag', 1, 1, FAST)


@pytest.mark.slow
def test_cli_writes_a_dataset(tmp_path, capsys):
    out = tmp_path / 'cli'
    argv = ['simulate', '--scenario', 'loop', '--scans', '3', '--seed', '2', '--out', str(out),
            '--format', 'ros1', '--legacy-fields', '--no-distortion', '--azimuth-step-deg', '2']
    assert main(argv) == 0
    assert (out / 'base_loop_2.bag').is_file()
    assert (out / 'ground_truth' / 'gt.csv').is_file()
    assert (out / 'topdown.png').stat().st_size > 10_000
    assert 'base_loop_2.bag' in capsys.readouterr().out
    with ScanBagReader(out / 'base_loop_2.bag', LIDAR_TOPIC) as reader:
        scans = list(reader)
    assert len(scans) == 3 and scans[0].time_offset_s is None
    # Running again into the same folder fails cleanly (exit code 1, nothing overwritten).
    assert main(argv) == 1
