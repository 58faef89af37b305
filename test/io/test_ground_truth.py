"""Ground truth in every shape a dataset ships it: gt.bag, rosbag2, gt.csv, TUM."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from gft_odom.core.geometry import rpy_transform, transform_points
from gft_odom.errors import ConfigError, GroundTruthError
from gft_odom.io.bags import BagWriter
from gft_odom.io.ground_truth import GroundTruthConfig, read_ground_truth
from gft_odom.io.tum import write_tum

T0_S = 1_680_000_000
GPS_TOPIC = '/gps/fix/odometry'


def gps_poses(n: int = 6) -> np.ndarray:
    return np.stack([rpy_transform((1.5 * i, -0.2 * i, 0.03 * i), (0.0, 0.0, 0.1 * i))
                     for i in range(n)])


def stamps_ns(n: int = 6) -> np.ndarray:
    return T0_S * 10**9 + np.arange(n, dtype=np.int64) * 200_000_001


@pytest.mark.parametrize('fmt, storage, name', [('ros1', 'sqlite3', 'gt.bag'),
                                                ('ros2', 'sqlite3', 'gt'),
                                                ('ros2', 'mcap', 'gt')])
def test_bag_ground_truth(tmp_path, fmt, storage, name):
    path = tmp_path / name
    with BagWriter(path, fmt=fmt, storage=storage) as writer:
        for t, T in zip(stamps_ns(), gps_poses()):
            writer.write_odometry(GPS_TOPIC, int(t), T)
    traj = read_ground_truth(path)
    np.testing.assert_array_equal(traj.stamps_ns, stamps_ns())
    np.testing.assert_allclose(traj.poses, gps_poses(), atol=1e-12)
    with pytest.raises(GroundTruthError, match='/gps/fix not in bag'):
        read_ground_truth(path, topic='/gps/fix')


def _csv_rows(sep: str, in_ns: bool, with_quat: bool) -> list[str]:
    rows = []
    for t, T in zip(stamps_ns(), gps_poses()):
        stamp = str(t) if in_ns else f'{t // 10**9}.{t % 10**9:09d}'
        values = [f'{v:.12f}' for v in T[:3, 3]]
        if with_quat:
            from scipy.spatial.transform import Rotation
            values += [f'{v:.15f}' for v in Rotation.from_matrix(T[:3, :3]).as_quat()]
        rows.append(sep.join([stamp] + values))
    return rows


@pytest.mark.parametrize('sep', [',', ' ', '\t', ', '])
@pytest.mark.parametrize('in_ns', [False, True])
@pytest.mark.parametrize('header', [None, 'time,x,y,z,qx,qy,qz,qw',
                                    'timestamp tx ty tz qx qy qz qw',
                                    '# a comment line, then positional columns'])
def test_csv_with_quaternion(tmp_path, sep, in_ns, header):
    path = tmp_path / 'gt.csv'
    lines = ([header] if header else []) + _csv_rows(sep, in_ns, with_quat=True)
    path.write_text('\n'.join(lines) + '\n')
    traj = read_ground_truth(path)
    np.testing.assert_array_equal(traj.stamps_ns, stamps_ns())
    np.testing.assert_allclose(traj.poses, gps_poses(), atol=1e-9)


def test_csv_position_only_gets_identity_orientation(tmp_path):
    path = tmp_path / 'gt.csv'
    path.write_text('\n'.join(_csv_rows(',', False, with_quat=False)) + '\n')
    traj = read_ground_truth(path)
    np.testing.assert_allclose(traj.positions_xyz, gps_poses()[:, :3, 3], atol=1e-12)
    np.testing.assert_array_equal(traj.poses[:, :3, :3], np.stack([np.eye(3)] * 6))


def test_csv_from_rostopic_echo_p(tmp_path):
    """`rostopic echo -p /gps/fix/odometry > gt.csv`: columns found by name."""
    header = ('%time,field.header.seq,field.header.stamp,field.header.frame_id,'
              'field.child_frame_id,field.pose.pose.position.x,field.pose.pose.position.y,'
              'field.pose.pose.position.z,field.pose.pose.orientation.x,'
              'field.pose.pose.orientation.y,field.pose.pose.orientation.z,'
              'field.pose.pose.orientation.w,field.twist.twist.linear.x')
    rows = [header]
    for i, (t, T) in enumerate(zip(stamps_ns(), gps_poses())):
        x, y, z = T[:3, 3]
        rows.append(f'{t + 12345},{i},{t},map,gps,{x:.12f},{y:.12f},{z:.12f},0,0,0,0,9.0')
    path = tmp_path / 'gt.csv'
    path.write_text('\n'.join(rows) + '\n')
    traj = read_ground_truth(path)
    np.testing.assert_array_equal(traj.stamps_ns, stamps_ns())  # header stamp, not %time
    np.testing.assert_allclose(traj.positions_xyz, gps_poses()[:, :3, 3], atol=1e-12)


def test_tum_ground_truth(tmp_path):
    from gft_odom.core.trajectory import Trajectory
    path = tmp_path / 'gt.tum'
    write_tum(path, Trajectory(stamps_ns(), gps_poses()))
    traj = read_ground_truth(path)
    np.testing.assert_array_equal(traj.stamps_ns, stamps_ns())
    np.testing.assert_allclose(traj.poses, gps_poses(), atol=1e-9)


def test_a_few_stamps_out_of_order_are_sorted_with_a_warning(tmp_path, caplog):
    rows = _csv_rows(',', False, with_quat=False)
    rows[2], rows[3] = rows[3], rows[2]
    path = tmp_path / 'gt.csv'
    path.write_text('\n'.join(rows) + '\n')
    with caplog.at_level(logging.WARNING):
        traj = read_ground_truth(path)
    np.testing.assert_array_equal(traj.stamps_ns, stamps_ns())
    assert any('time goes backwards 1 time' in r.getMessage() and 'line 4' in r.getMessage()
               for r in caplog.records)


def test_many_stamps_out_of_order_are_an_error(tmp_path):
    rows = _csv_rows(',', False, with_quat=False)[::-1]
    path = tmp_path / 'gt.csv'
    path.write_text('\n'.join(rows) + '\n')
    with pytest.raises(GroundTruthError, match='time goes backwards 5 times'):
        read_ground_truth(path)


@pytest.mark.parametrize('text, reason', [
    ('', 'holds no poses'),
    ('time,x,y,z\n', 'header but no poses'),
    ('when,where\n1,2\n', 'does not name time, x, y and z'),
    ('1,2,3\n', 'expected 4 .* or 8'),
    ('1,2,3,4\n2,3,4\n', 'line 2: expected at least 4'),
    ('time x y z\n1 2 3 4\n2 3 four 5\n', 'line 3'),
    ('1,2,3,4\n2,nan,3,4\n', 'line 2: non-finite'),
])
def test_bad_csv_files(refuses_file, text, reason):
    refuses_file(read_ground_truth, text, GroundTruthError, reason, name='gt.csv')


def test_missing_path(tmp_path):
    with pytest.raises(GroundTruthError, match='does not exist'):
        read_ground_truth(tmp_path / 'gt.csv')


def test_unknown_formats(refuses_file):
    refuses_file(read_ground_truth, '{}', GroundTruthError, 'unknown format', name='gt.json')
    refuses_file(read_ground_truth, 'nope', GroundTruthError, 'gt.bag', name='gt.bag')


def test_empty_bag_topic(tmp_path):
    path = tmp_path / 'gt.bag'
    with BagWriter(path, fmt='ros1') as writer:
        writer.write_odometry('/other', 10**9, np.eye(4))
    with pytest.raises(GroundTruthError, match='available topics: /other'):
        read_ground_truth(path)


def test_lidar_to_gps_extrinsic():
    config = GroundTruthConfig()
    config.validate()
    T = config.T_lidar_gps()
    # the antenna origin lands at the configured lever arm in the LiDAR frame
    np.testing.assert_array_equal(transform_points(T, np.zeros((1, 3)))[0],
                                  config.lidar_to_gps_xyz_m)
    np.testing.assert_array_equal(T[:3, :3], np.eye(3))
    assert all(isinstance(v, float) for v in config.lidar_to_gps_xyz_m)  # ROS-param friendly
    moved = GroundTruthConfig((1.0, 2.0, 3.0)).T_lidar_gps()
    assert moved[:3, 3].tolist() == [1.0, 2.0, 3.0]


@pytest.mark.parametrize('bad', [(1.0, 2.0), (0.0, float('nan'), 0.0), (0.0, 0.0, 250.0),
                                 ('a', 0.0, 0.0)])
def test_extrinsic_validation(bad):
    with pytest.raises(ConfigError, match='lidar_to_gps_xyz_m'):
        GroundTruthConfig(bad).validate()
